"""Reading BPF maps through libbpf, on real kernel maps: in batches, and entry by entry (the path
for kernels and map types without batch operations) while another thread churns the map."""
import ctypes
import os
import struct
import threading

import pytest

from drums.kernel.bpffs import PinnedMap, libbpf

HASH, LRU_HASH = 1, 9
ENTRIES = 2000


def new_map(kind: int, max_entries: int) -> PinnedMap:
    lib = libbpf()
    lib.bpf_map_create.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_uint32, ctypes.c_uint32,
                                   ctypes.c_uint32, ctypes.c_void_p]
    fd = lib.bpf_map_create(kind, b"drums_test", 4, 8, max_entries, None)
    assert fd >= 0, os.strerror(ctypes.get_errno())
    try:
        return PinnedMap.from_fd(fd, "drums_test")
    finally:
        os.close(fd)


def contents(keys: bytes, values: bytes) -> dict[int, int]:
    out = {}
    for (k,), (v,) in zip(struct.iter_unpack("<I", keys), struct.iter_unpack("<Q", values)):
        assert k not in out, f"key {k} read twice"
        out[k] = v
    return out


@pytest.mark.parametrize("kind", [HASH, LRU_HASH])
def test_a_batch_read_and_a_read_entry_by_entry_return_every_entry_once(kind):
    m = new_map(kind, ENTRIES * 2)
    try:
        truth = {k: k * 7 for k in range(ENTRIES)}
        for k, v in truth.items():
            m.update(struct.pack("<I", k), struct.pack("<Q", v))
        keys, values, count = m.read()
        assert count == ENTRIES and contents(keys, values) == truth
        keys, values, count = m._read_each()
        assert count == ENTRIES and contents(keys, values) == truth
    finally:
        m.close()


@pytest.mark.parametrize("kind", [HASH, LRU_HASH])
def test_batch_reads_sized_by_the_last_read_return_every_entry_as_the_map_grows_and_empties(kind):
    """A batch read's buffers hold what the last read found and a little more, doubled while its
    batches come back full: a map that grew from nothing to thousands is read whole at once, and
    one read with delete then comes back empty."""
    m = new_map(kind, ENTRIES * 2)
    try:
        for size in (0, 1, 17, ENTRIES, 3, ENTRIES, 0):  # an LRU map evicts some before it is full
            truth = {k: k * 3 + size for k in range(size)}
            for k, v in truth.items():
                m.update(struct.pack("<I", k), struct.pack("<Q", v))
            for k in range(size, ENTRIES * 2):
                m.delete(struct.pack("<I", k))
            keys, values, count = m.read()
            assert count == size and contents(keys, values) == truth, size
        for k in range(50):
            m.update(struct.pack("<I", k), struct.pack("<Q", k))
        keys, values, count = m.read(delete=True)
        assert contents(keys, values) == {k: k for k in range(50)} and m.read() == (b"", b"", 0)
    finally:
        m.close()


def test_a_read_entry_by_entry_under_churn_ends_and_repeats_no_key():
    """Deleting the key the walk stands on sends the kernel back to the first key: without care a
    walk repeats entries (a counter summed twice) and may never end. A walk that is sent back too
    often runs out of steps before the end (a fresh CI on a slow host: steady key 98 of 128
    missing), so completeness is asked of most walks, not of each."""
    m = new_map(HASH, ENTRIES)
    stop = threading.Event()
    steady = range(ENTRIES // 2)  # never touched: each must be read exactly once, with its value
    for k in steady:
        m.update(struct.pack("<I", k), struct.pack("<Q", k))

    churned = [struct.pack("<I", k) for k in range(ENTRIES // 2, ENTRIES)]
    for key in churned:
        m.update(key, struct.pack("<Q", 1))

    def churn():  # each churned key deleted and put back, again and again
        while not stop.is_set():
            for key in churned:
                m.delete(key)
                m.update(key, struct.pack("<Q", 1))

    thread = threading.Thread(target=churn)
    thread.start()
    complete = 0
    try:
        for _ in range(20):
            keys, values, count = m._read_each()
            read = contents(keys, values)
            assert count == len(read) <= ENTRIES
            assert {k: read[k] for k in steady if k in read} == {k: k for k in steady if k in read}
            complete += all(k in read for k in steady)
    finally:
        stop.set()
        thread.join()
        m.close()
    assert complete >= 15


# A program on the bpf_trace_printk tracepoint that prints too: its print fires the tracepoint
# again on the same CPU while it runs, which the kernel skips and counts. What prints first is a
# program on getppid, for this process's calls.
RECURSING = r"""
RAW_TRACEPOINT_PROBE(bpf_trace_printk) { bpf_trace_printk("again\n"); return 0; }
TRACEPOINT_PROBE(syscalls, sys_enter_getppid)
{
    if (bpf_get_current_pid_tgid() >> 32 == TGID)
        bpf_trace_printk("first\n");
    return 0;
}
"""


def test_the_runs_the_kernel_skipped_are_read_from_the_program(features):
    """Each of 500 getppid calls runs the printing program once and makes the kernel skip it once:
    500 runs missed, as struct bpf_prog_info's recursion_misses (at the offset the BTF gives) says."""
    from drums.kernel.bpffs import prog_runs_missed
    os.environ["BCC_KERNEL_SOURCE"] = features.kernel_headers
    from bcc import BPF
    at = features.btf.field("bpf_prog_info", "recursion_misses").offset
    b = BPF(text=RECURSING.encode(), cflags=[f"-DTGID={os.getpid()}"])
    try:
        fd = b.load_func(b"raw_tracepoint__bpf_trace_printk", BPF.RAW_TRACEPOINT).fd
        assert prog_runs_missed(fd, at) == 0
        for _ in range(500):
            os.getppid()
        assert prog_runs_missed(fd, at) == 500
    finally:
        b.cleanup()
