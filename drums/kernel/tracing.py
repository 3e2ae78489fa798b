"""Loads a program bcc compiled as a BTF tracepoint program (tp_btf) and links it to its tracepoint.

bcc 0.26 loads raw tracepoint programs only as BPF_PROG_TYPE_RAW_TRACEPOINT, whose arguments are
bare numbers: every field of a task or socket costs a bpf_probe_read_kernel call (about 28 ns
each on the development VM). The same instructions loaded as a tracing program attached to the
tracepoint's BTF type see typed pointers, so the verifier lets the program load kernel fields
directly (bench/event_cost.py: sched_switch's program went from 303 ns a run to 180). bcc has
already put the map fds into the instructions; libbpf (which the agent uses to read pins) loads
them with the attach type bcc cannot give, and its raw tracepoint link can be pinned.
"""
from __future__ import annotations

import ctypes
import os
from functools import lru_cache

from drums.errors import ProbeError
from drums.kernel import bpffs

_PROG_TYPE_TRACING = 26  # enum bpf_prog_type
_TRACE_RAW_TP = 23  # enum bpf_attach_type
_LOG_SIZE = 1 << 20


class _LoadOpts(ctypes.Structure):
    # struct bpf_prog_load_opts of libbpf 1.1 (its `sz` lets older and newer libbpf read it).
    _fields_ = [
        ("sz", ctypes.c_size_t),
        ("attempts", ctypes.c_int),
        ("expected_attach_type", ctypes.c_uint32),
        ("prog_btf_fd", ctypes.c_uint32),
        ("prog_flags", ctypes.c_uint32),
        ("prog_ifindex", ctypes.c_uint32),
        ("kern_version", ctypes.c_uint32),
        ("attach_btf_id", ctypes.c_uint32),
        ("attach_prog_fd", ctypes.c_uint32),
        ("attach_btf_obj_fd", ctypes.c_uint32),
        ("fd_array", ctypes.c_void_p),
        ("func_info", ctypes.c_void_p),
        ("func_info_cnt", ctypes.c_uint32),
        ("func_info_rec_size", ctypes.c_uint32),
        ("line_info", ctypes.c_void_p),
        ("line_info_cnt", ctypes.c_uint32),
        ("line_info_rec_size", ctypes.c_uint32),
        ("log_level", ctypes.c_uint32),
        ("log_size", ctypes.c_uint32),
        ("log_buf", ctypes.c_char_p),
    ]


@lru_cache(maxsize=1)
def _lib() -> ctypes.CDLL:
    lib = bpffs.libbpf()
    lib.libbpf_find_vmlinux_btf_id.argtypes = [ctypes.c_char_p, ctypes.c_uint32]
    lib.bpf_prog_load.argtypes = [ctypes.c_uint32, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_void_p,
                                  ctypes.c_size_t, ctypes.POINTER(_LoadOpts)]
    lib.bpf_raw_tracepoint_open.argtypes = [ctypes.c_char_p, ctypes.c_int]
    return lib


def attach(module, fn: str, event: str) -> tuple[int, int]:
    """Load bcc's compiled function `fn` of `module` (a bcc BPF object's .module) as a tp_btf
    program on the tracepoint `event` and link it there; returns (program fd, link fd)."""
    from bcc.libbcc import lib as bcc

    lib = _lib()
    btf_id = lib.libbpf_find_vmlinux_btf_id(event.encode(), _TRACE_RAW_TP)
    if btf_id < 0:
        raise ProbeError(f"tp_btf {event}: the kernel's BTF has no tracepoint {event}")
    name = fn.encode()
    start, size = bcc.bpf_function_start(module, name), bcc.bpf_function_size(module, name)
    if not start:
        raise ProbeError(f"tp_btf {event}: no compiled function {fn}")
    opts = _LoadOpts(sz=ctypes.sizeof(_LoadOpts), expected_attach_type=_TRACE_RAW_TP, attach_btf_id=btf_id)

    def load() -> int:
        return lib.bpf_prog_load(_PROG_TYPE_TRACING, name[:15], bcc.bpf_module_license(module), start, size // 8,
                                 ctypes.byref(opts))
    prog = load()
    if prog < 0:
        err = -prog
        # Loaded again for the verifier's reason: asking for the log at once would cost every load.
        log = ctypes.create_string_buffer(_LOG_SIZE)
        opts.log_level, opts.log_size, opts.log_buf = 1, _LOG_SIZE, ctypes.cast(log, ctypes.c_char_p)
        load()
        # Its last lines are statistics; the reason comes before them.
        lines = [line for line in log.value.decode(errors="replace").splitlines()
                 if line.strip() and not line.startswith(("processed ", "verification time", "stack depth"))]
        raise ProbeError(f"tp_btf {event}: {fn}: {os.strerror(err)}" + (f": {lines[-1]}" if lines else ""))
    link = lib.bpf_raw_tracepoint_open(None, prog)
    if link < 0:
        os.close(prog)
        raise ProbeError(f"tp_btf {event}: link: {os.strerror(-link)}")
    return prog, link
