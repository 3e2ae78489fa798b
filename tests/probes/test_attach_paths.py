"""Attach paths this kernel may not offer. On a kernel without kprobes (this project's 6.18) the
sockets probe's kprobe programs are still compiled and put through the kernel's verifier; the
probes' own tests run on every path a kernel offers (tests/conftest.py: offered_paths), and `make
test-kernels` runs them on the fentry and kprobe paths of Linux 5.10 to 6.1 in VMs. A path the
kernel refuses gives way to the next."""
import logging
import os
import re

import pytest

from drums.kernel.loader import BPF_DIR, program_text
from drums.probes.bpf import ATTACH_DEFINES, AttachPath
from drums.probes.sched import SchedProbe
from drums.probes import sockets
from drums.probes.sockets import SocketsProbe
from tests.conftest import TEST_PIN_ROOT, offered_paths


@pytest.mark.kernel
def test_kprobe_path_compiles_and_passes_the_verifier(features, proctable):
    if "kprobe" in offered_paths(SocketsProbe):
        pytest.skip("the kprobe path is offered here: the sockets probe's own tests load and count on it")
    os.environ["BCC_KERNEL_SOURCE"] = features.kernel_headers
    from bcc import BPF

    probe = SocketsProbe(features, proctable)
    (path,) = [p for p in probe.paths if p.name == "kprobe"]
    defines = dict(probe.offsets(features.btf), DRUMS_ATTACH=ATTACH_DEFINES["kprobe"])
    b = BPF(text=program_text(probe.source).encode(),
            cflags=[f"-D{k}={v}" for k, v in defines.items()] + [f"-I{BPF_DIR}"])
    try:
        functions = [fn for kind, _, fn in path.attachments if kind in ("kprobe", "kretprobe")]
        assert len(functions) == 24
        for fn in functions:
            assert b.load_func(fn.encode(), BPF.KPROBE).fd >= 0, fn
        # The lifecycle's programs, and the one the agent runs itself to forget a socket.
        others = [fn for kind, _, fn in path.attachments if kind in ("raw_tracepoint", "run")]
        assert others == ["on_tcp_state", "forget_gone"]
        for fn in others:
            assert b.load_func(fn.encode(), BPF.RAW_TRACEPOINT).fd >= 0, fn
    finally:
        b.cleanup()


@pytest.mark.kernel
@pytest.mark.parametrize("path", sockets.TRACEPOINT_PATHS)
def test_tracepoint_paths_splice_kprobes_compile_and_pass_the_verifier(features, proctable, path):
    """Where the kernel has kprobes the tracepoint paths count splice's reads with them (pinned as
    links); on a kernel without, their programs are still compiled in those paths' text and verified."""
    if features.kprobes:
        pytest.skip("kprobes are offered here: the sockets probe's splice tests load and count with them")
    if path not in offered_paths(SocketsProbe):
        pytest.skip(f"this kernel offers no {path} path")
    os.environ["BCC_KERNEL_SOURCE"] = features.kernel_headers
    from bcc import BPF

    probe = SocketsProbe(features, proctable)
    defines = dict(probe.offsets(features.btf), DRUMS_ATTACH=ATTACH_DEFINES[path],
                   SPLICE_READS=sockets.SPLICE_BY_KPROBES)
    b = BPF(text=program_text(probe.source).encode(),
            cflags=[f"-D{k}={v}" for k, v in defines.items()] + [f"-I{BPF_DIR}"])
    try:
        kinds = sockets._SPLICE_ATTACHMENTS[sockets.SPLICE_BY_KPROBES]
        assert sorted(kind for kind, _, _ in kinds) == ["kprobe_link", "kprobe_link", "kretprobe_link", "kretprobe_link"]
        for _, _, fn in kinds:
            assert b.load_func(fn.encode(), BPF.KPROBE).fd >= 0, fn
    finally:
        b.cleanup()


@pytest.mark.kernel
def test_a_path_the_kernel_refuses_gives_way_to_the_next(features, proctable, caplog):
    """The kernel's verifier refuses a tp_btf program that reads arguments its tracepoint does not
    have (on_switch, given sched_wakeup's one task): the probe says so and loads its next path."""
    probe = SchedProbe(features, proctable, pin_root=f"{TEST_PIN_ROOT}_refused")
    raw = next(p for p in probe.paths if p.name == "raw_tracepoint")
    bad = AttachPath("tp_btf", (("tp_btf", "sched_wakeup", "on_switch"),), lambda f: None, "a bad program")
    probe.paths = (bad, raw)
    with caplog.at_level(logging.WARNING, logger="drums"):
        probe.start()
    try:
        assert probe.status.attach_type == "raw_tracepoint"
        (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        # The verifier's own reason: on_switch reads arguments beyond the tracepoint's first (the
        # second or the third, as the compiler orders the loads: off=8 on 5.10, 16 on 6.1 and later).
        assert re.match(r"probe sched: the tp_btf path did not load \(tp_btf sched_wakeup: on_switch: "
                        r"Permission denied: invalid bpf_context access off=(8|16) size=8\)", warning), warning
        assert warning.endswith("; trying raw_tracepoint"), warning
    finally:
        probe.unload()


class _NoSchedInfo(SchedProbe):
    """The sched probe on a kernel built without CONFIG_SCHED_INFO, whose tasks keep no account of
    their run-queue waits."""

    def offsets(self, btf):
        return {k: v for k, v in super().offsets(btf).items() if k not in ("TASK_RUN_DELAY_OFF", "TASK_PCOUNT_OFF")}


@pytest.mark.kernel
def test_without_sched_info_the_sched_probe_times_waits_on_raw_tracepoints(features, proctable, caplog):
    probe = _NoSchedInfo(features, proctable, pin_root=f"{TEST_PIN_ROOT}_no_sched_info")
    with caplog.at_level(logging.WARNING, logger="drums"):
        probe.start()
    try:
        assert probe.status.attach_type == "raw_tracepoint"
        (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert "the tp_btf path did not load" in warning and "CONFIG_SCHED_INFO" in warning, warning
    finally:
        probe.unload()


@pytest.mark.kernel
def test_a_map_read_by_another_layout_than_its_programs_make_refuses_to_start(features, proctable):
    from drums.errors import ProbeError
    from drums.probes.rtps import _KEY, RtpsProbe

    class Stale(RtpsProbe):  # as if bpf/rtps.bpf.c had grown its counts without the Python side
        maps = {**RtpsProbe.maps, "writers": (_KEY, 32)}

    probe = Stale(features, proctable, pin_root=f"{TEST_PIN_ROOT}_stale")
    try:
        with pytest.raises(ProbeError, match=r"^map writers: bpf/rtps.bpf.c makes entries of 24\+40 bytes, "
                                             r"drums reads 24\+32 \(key\+value\): the two disagree$"):
            probe.start()
        assert not probe.opened and not probe.status.attached
    finally:
        probe.unload()
