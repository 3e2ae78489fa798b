"""`drums doctor`: what this host offers each probe, which attach path each will use, and what to
do about every problem. Exits 1 only when the agent could not run at all."""
from __future__ import annotations

import importlib.util
import os

from drums.kernel import TRACEFS
from drums.kernel.features import Features, is_mount_of_type
from drums.kernel.btf import VMLINUX_BTF
from drums.probes.bpf import BTF_FIX, NO_KERNEL_BTF, BpfProbe, choose_path, common_requirements, needs_tp_btf
from drums.probes.registry import build
from drums.proctable import ProcessTable

KEY_TRACEPOINTS = ("sock_send_length", "sock_recv_length", "inet_sock_set_state", "sched_switch",
                   "sched_wakeup", "tcp_retransmit_skb", "tcp_send_reset", "tcp_receive_reset")


def _line(name: str, ok: bool, text: str, fix: str = "") -> str:
    mark = "ok " if ok else "NO "
    return f"{mark} {name:<12} {text}" + (f"\n    fix: {fix}" if fix and not ok else "")


def _mount_line(name: str, ok: bool, path: str, fstype: str, why: str = "") -> str:
    """A file system the agent needs: there, mounted but closed to this user, or not mounted."""
    if not ok and is_mount_of_type("/proc/mounts", path, fstype):
        return _line(name, False, f"{path} is mounted but not readable as uid {os.geteuid()}",
                     "run the agent (and this doctor) as root")
    return _line(name, ok, path if ok else "not mounted",
                 f"mount -t {fstype} {fstype} {path}" + (f" ({why})" if why else ""))


def _bcc_version() -> str | None:
    if importlib.util.find_spec("bcc") is None:
        return None
    try:
        from bcc import __version__
        return __version__
    except ImportError:
        return "unknown version"


def _libbpf() -> bool:
    from drums.errors import KernelError
    from drums.kernel.bpffs import libbpf
    try:
        libbpf()
        return True
    except KernelError:
        return False


def report(f: Features) -> tuple[list[str], bool]:
    """Lines to print, and whether the agent can run at all."""
    lines = [f"    kernel       {f.kernel_release}"]
    lines.append(_line("privileges", f.privileged, "root" if f.privileged else f"uid {os.geteuid()}",
                       "run the agent as root (BPF needs CAP_BPF and CAP_PERFMON)"))
    if f.btf_file:
        said = f"{f.btf_file} (given with --btf" + ("" if f.has_btf else "; the kernel has none of its own: no "
                                                   "tp_btf or fentry paths, no helpers that return typed pointers") + ")"
    else:
        said = VMLINUX_BTF if f.has_btf else "missing"
    lines.append(_line("BTF", f.btf is not None, said,
                       f"{BTF_FIX}; without BTF only the /proc and sock_diag fallbacks run"))
    lines.append(_mount_line("tracefs", f.tracefs, TRACEFS, "tracefs", "kprobes need it"))
    lines.append(_mount_line("bpffs", f.bpffs, "/sys/fs/bpf", "bpf"))
    version = _bcc_version()
    lines.append(_line("bcc", version is not None, version or "not installed",
                       "apt-get install python3-bpfcc, and run Drums from a venv made with "
                       "/usr/bin/python3 -m venv --system-site-packages"))
    headers = f.kernel_headers
    own = headers == f"/lib/modules/{f.kernel_release}/build"
    lines.append(_line("headers", headers is not None,
                       (headers + ("" if own else " (not this kernel's own; fine: struct offsets come from BTF)"))
                       if headers else "none found",
                       "apt-get install linux-headers-$(uname -r), or run scripts/setup.sh"))
    lines.append(_line("libbpf", _libbpf(), "loaded" if _libbpf() else "missing", "apt-get install libbpf1"))
    missing = [tp for tp in KEY_TRACEPOINTS if not f.tracepoint(tp)]
    lines.append(_line("tracepoints", not missing,
                       "all of " + ", ".join(KEY_TRACEPOINTS) if not missing else "missing " + ", ".join(missing),
                       "paths that need these fall back to others (below)"))
    lines.append(_line("kprobes", f.kprobes, "available" if f.kprobes else "not available (CONFIG_KPROBES unset)",
                       "none needed while the tracepoint paths work"))
    lines.append(_line("tp_btf", f.tp_btf, "tracepoints typed in BTF: programs read kernel fields directly"
                       if f.tp_btf else needs_tp_btf(f),
                       "none needed: the raw tracepoint paths serve, at a helper call per field"))
    lines.append(_line("fentry", f.fentry, "BPF trampolines load" if f.fentry
                       else "untested: bcc has no kernel headers to compile with" if headers is None and f.has_btf
                       else NO_KERNEL_BTF if not f.has_btf
                       else "refused (fentry/fexit programs cannot load)", "none needed while the tracepoint paths work"))

    problems = common_requirements(f)
    for probe in build(f, ProcessTable()):
        if not isinstance(probe, BpfProbe):
            lines.append(f"    probe {probe.name:<8} psutil and /proc")
            continue
        chosen, reasons = choose_path(probe.paths, f) if not problems else (None, problems)
        if chosen:
            lines.append(f"    probe {probe.name:<8} will use {chosen.name} ({chosen.serves})")
            caveat = probe.caveat(chosen)
            if caveat:
                lines.append(f"      note: {caveat}")
        else:
            lines.append(f"NO  probe {probe.name:<8} cannot attach: {'; '.join(reasons)}")
        for path in probe.paths:
            if path is not chosen:
                why = path.requires(f)
                state = "available" if why is None else f"unavailable: {why}"
                lines.append(f"      {path.name:<15} {state} ({path.serves})")
    can_run = os.path.isdir("/proc/self")
    if not can_run:
        lines.append("NO  the agent cannot run: /proc is not mounted (mount -t proc proc /proc)")
    return lines, can_run


def run(btf_file: str = "") -> int:
    lines, can_run = report(Features(btf_file))
    print("\n".join(lines))
    return 0 if can_run else 1
