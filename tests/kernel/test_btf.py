"""The running kernel's BTF: the cheap look at its names agrees with the full parse."""
import tracemalloc

import pytest

from drums.errors import KernelError
from drums.kernel import btf
from drums.kernel.features import Features


def test_the_names_of_the_kernel_s_btf_say_what_its_parse_says_of_perf_links_and_structs():
    parsed = btf.Btf.load()
    strings = btf.names()
    for struct in ("task_struct", "bpf_perf_link", "sock", "no_such_struct_in_any_kernel"):
        assert (b"\0" + struct.encode() + b"\0" in strings) == bool(parsed._by_name.get(struct)), struct
    assert Features().perf_links == parsed.has_field("bpf_perf_link", "perf_file") is True  # Linux 6.18 here
    assert Features().tp_btf == (parsed.tracepoint_args("sched_switch") is not None) is True


def test_functions_are_found_by_name_and_nothing_else_is_taken_for_one():
    parsed = btf.Btf.load()
    # Every kernel of interest has these (the sockets probe's fentry and kprobe paths take them);
    # a struct, a struct's member and a made-up name are no functions.
    assert parsed.has_function("inet_sendmsg") and parsed.has_function("tcp_splice_read")
    assert parsed.has_function("unix_stream_sendmsg")  # static: BTF has it all the same
    for name in ("task_struct", "sk_protocol", "no_such_function_in_any_kernel"):
        assert not parsed.has_function(name), name


def test_the_features_read_from_the_names_keep_none_of_them():
    """The agent asks these at every start and keeps its Features: the names (2.3 MB here) must
    not stay with the answers, as they did for a while."""
    features = Features()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        assert features.perf_links and features.tp_btf
        kept = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert kept < 10_000, kept


def test_a_file_that_is_not_btf_is_one_kernel_error(tmp_path):
    (tmp_path / "vmlinux").write_bytes(b"\x7fELF" + bytes(40))
    with pytest.raises(KernelError, match="bad magic"):
        btf.names(str(tmp_path / "vmlinux"))
    with pytest.raises(KernelError, match="cannot read kernel BTF"):
        btf.names(str(tmp_path / "missing"))
