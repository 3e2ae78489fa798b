"""Attach a loaded BPF program to a tracepoint, a uprobe or a kprobe: as a BPF link, which bpffs can pin, or
where the kernel has no such links, through the perf event itself.

bcc attaches tracepoints and uprobes through perf events with an ioctl, which ends with the
process that made it. A link made with BPF_LINK_CREATE on the perf event (Linux >= 5.15) holds
the event itself: pinned, it outlives the loader, and the agent attaches new uprobes (a librcl.so
that appears later) to pinned programs without bcc or its compiler. Before 5.15 the agent holds
the perf event (`link=False`): the program stays attached while the agent runs. Kprobes made so
are pinned links alike (the tracepoint paths' few kprobes, on kernels that all have such links).
"""
from __future__ import annotations

import ctypes
import fcntl
import os

from drums.errors import ProbeError
from drums.kernel import TRACEFS, bpffs

_PERF_TYPE_TRACEPOINT = 2
_BPF_PERF_EVENT = 41  # enum bpf_attach_type
_SYS_PERF_EVENT_OPEN = {"x86_64": 298, "aarch64": 241, "armv7l": 364, "riscv64": 241}
_PERF_FLAG_FD_CLOEXEC = 8
_PERF_EVENT_IOC_ENABLE = 0x2400  # _IO('$', 0)
_PERF_EVENT_IOC_SET_BPF = 0x40042408  # _IOW('$', 8, __u32)


class _PerfEventAttr(ctypes.Structure):
    # The head of struct perf_event_attr (PERF_ATTR_SIZE_VER1, include/uapi/linux/perf_event.h).
    _fields_ = [
        ("type", ctypes.c_uint32),
        ("size", ctypes.c_uint32),
        ("config", ctypes.c_uint64),
        ("sample_period", ctypes.c_uint64),
        ("sample_type", ctypes.c_uint64),
        ("read_format", ctypes.c_uint64),
        ("flags", ctypes.c_uint64),
        ("wakeup_events", ctypes.c_uint32),
        ("bp_type", ctypes.c_uint32),
        ("config1", ctypes.c_uint64),  # uprobe: the path; kprobe: the function
        ("config2", ctypes.c_uint64),  # the offset in the file or function
    ]


def _perf_event_open(attr: _PerfEventAttr, what: str) -> int:
    nr = _SYS_PERF_EVENT_OPEN.get(os.uname().machine)
    if nr is None:
        raise ProbeError(f"{what}: perf_event_open is not known on {os.uname().machine}")
    libc = ctypes.CDLL(None, use_errno=True)
    # pid -1, cpu 0: a BPF program on a tracepoint or uprobe event runs on every CPU.
    fd = libc.syscall(nr, ctypes.byref(attr), -1, 0, -1, _PERF_FLAG_FD_CLOEXEC)
    if fd < 0:
        raise ProbeError(f"{what}: {os.strerror(ctypes.get_errno())}")
    return fd


def _attach(prog_fd: int, perf_fd: int, what: str, link: bool) -> int:
    """A BPF link of the program to the event (the event's fd closed: the link holds it), or with
    `link` False the event's own fd with the program set on it."""
    if not link:
        try:
            fcntl.ioctl(perf_fd, _PERF_EVENT_IOC_SET_BPF, prog_fd)
            fcntl.ioctl(perf_fd, _PERF_EVENT_IOC_ENABLE, 0)
        except OSError as e:
            os.close(perf_fd)
            raise ProbeError(f"{what}: {e.strerror}") from None
        return perf_fd
    lib = bpffs.libbpf()
    lib.bpf_link_create.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_void_p]
    try:
        fd = lib.bpf_link_create(prog_fd, perf_fd, _BPF_PERF_EVENT, None)
        if fd < 0:
            raise ProbeError(f"{what}: BPF link: {os.strerror(ctypes.get_errno() or -fd)} (needs Linux >= 5.15)")
        return fd
    finally:
        os.close(perf_fd)


def tracepoint(prog_fd: int, event: str, link: bool = True) -> int:
    """A link of the program to `category:name` (or its perf event, see _attach); returns its fd."""
    category, _, name = event.partition(":")
    try:
        with open(f"{TRACEFS}/events/{category}/{name}/id") as f:
            event_id = int(f.read())
    except (OSError, ValueError):
        raise ProbeError(f"no tracepoint {event} in {TRACEFS}") from None
    attr = _PerfEventAttr(type=_PERF_TYPE_TRACEPOINT, size=ctypes.sizeof(_PerfEventAttr), config=event_id,
                          sample_period=1, wakeup_events=1)
    return _attach(prog_fd, _perf_event_open(attr, f"tracepoint {event}"), f"tracepoint {event}", link)


def uprobe(prog_fd: int, path: str, offset: int, ret: bool = False, link: bool = True) -> int:
    """A link of the program to the instruction at file `offset` of `path` (a return probe on the
    function there if `ret`), or its perf event (see _attach); returns its fd."""
    return _probe_event(prog_fd, "uprobe", path, offset, ret, link, f"uprobe {path}+{offset:#x}")


def kprobe(prog_fd: int, function: str, ret: bool = False) -> int:
    """A link of the program to the kernel function's entry (its return if `ret`); returns its fd.
    A return probe made so follows at most the kernel's default of calls at once (max(10, 2 x CPUs)):
    a return past those goes uncounted."""
    return _probe_event(prog_fd, "kprobe", function, 0, ret, True, f"{'kretprobe' if ret else 'kprobe'} {function}")


def _probe_event(prog_fd: int, pmu_name: str, target: str, offset: int, ret: bool, link: bool, what: str) -> int:
    """A uprobe on file `target` at `offset`, or a kprobe on kernel function `target`, through the
    PMU of that name (as libbpf makes them)."""
    pmu_dir = f"/sys/bus/event_source/devices/{pmu_name}"
    try:
        with open(f"{pmu_dir}/type") as f:
            pmu = int(f.read())
        with open(f"{pmu_dir}/format/retprobe") as f:
            ret_bit = int(f.read().split(":")[1])  # "config:0"
    except (OSError, ValueError, IndexError):
        raise ProbeError(f"{what}: the kernel has no {pmu_name} PMU ({pmu_dir})") from None
    name = ctypes.create_string_buffer(target.encode())
    attr = _PerfEventAttr(type=pmu, size=ctypes.sizeof(_PerfEventAttr), config=(1 << ret_bit) if ret else 0,
                          sample_period=1, wakeup_events=1, config1=ctypes.addressof(name), config2=offset)
    return _attach(prog_fd, _perf_event_open(attr, what), what, link)
