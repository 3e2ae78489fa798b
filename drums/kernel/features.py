"""What this kernel and host offer to the probes, detected once and without side effects.

Probes pick their attach path from these facts (drums.probes.bpf.choose_path); `drums doctor`
prints them. The one check that must load a program, fentry, runs only when asked for.
"""
from __future__ import annotations

import importlib.util
import os
import platform
from functools import cached_property
from itertools import takewhile

from drums.errors import KernelError
from drums.kernel import TRACEFS
from drums.kernel.btf import VMLINUX_BTF, Btf, names

HEADERS_CACHE = "/var/cache/drums/kernel-headers"  # made by scripts/setup.sh for custom kernels


class Features:
    """Lazily evaluated facts about the running kernel; tests override them in a subclass.
    `btf_file`: the kernel's BTF as a file (`--btf`), for a kernel built without it."""

    def __init__(self, btf_file: str = ""):
        self.btf_file = btf_file

    @cached_property
    def kernel_release(self) -> str:
        return platform.release()

    @cached_property
    def has_btf(self) -> bool:
        """The kernel's own BTF (CONFIG_DEBUG_INFO_BTF): what typed programs (tp_btf, fentry) and
        the helpers that return typed pointers need, whatever file gives the agent its offsets."""
        return os.path.exists(VMLINUX_BTF)

    @cached_property
    def btf_source(self) -> str | None:
        """Where struct offsets and the kernel's names are read: the file given, else the kernel's."""
        return self.btf_file or (VMLINUX_BTF if self.has_btf else None)

    @cached_property
    def btf(self) -> Btf | None:
        """The parsed BTF (about 20 MB in memory): only loading a probe needs it."""
        try:
            return Btf.load(self.btf_source) if self.btf_source else None
        except KernelError:
            return None

    def release_btf(self) -> None:
        """Drop the parsed BTF once the probes are loaded; the agent keeps running without it."""
        self.__dict__.pop("btf", None)

    @cached_property
    def privileged(self) -> bool:
        # CAP_BPF and CAP_PERFMON would do; root is what this checks, and what setup documents.
        return os.geteuid() == 0

    @cached_property
    def tracefs(self) -> bool:
        return os.path.isdir(f"{TRACEFS}/events")

    @cached_property
    def bpffs(self) -> bool:
        return is_mount_of_type("/proc/mounts", "/sys/fs/bpf", "bpf")

    @cached_property
    def bcc(self) -> bool:
        return importlib.util.find_spec("bcc") is not None

    @cached_property
    def kernel_headers(self) -> str | None:
        """Where bcc finds kernel headers: the running kernel's own, or setup's merged tree."""
        candidates = [os.environ.get("BCC_KERNEL_SOURCE", ""),
                      f"/lib/modules/{self.kernel_release}/build", HEADERS_CACHE]
        for path in candidates:
            if path and os.path.isdir(os.path.join(path, "include")):
                return path
        return None

    @cached_property
    def kprobes(self) -> bool:
        # CONFIG_KPROBES registers this PMU; without it no kprobe can attach.
        return os.path.isdir("/sys/bus/event_source/devices/kprobe")

    @cached_property
    def perf_links(self) -> bool:
        """BPF links on perf events (Linux >= 5.15): tracepoints and uprobes that can be pinned."""
        # struct bpf_perf_link came with them, and its name alone says so: a warm start, which needs
        # nothing else of BTF, no longer indexes all of it for this (0.15 s of 0.7).
        return self._btf_has_names[0]

    @cached_property
    def tp_btf(self) -> bool:
        """Whether raw tracepoints are typed in BTF (Linux >= 5.5), so that a tracing program can
        attach to one (drums.kernel.tracing): each has a `btf_trace_<event>` typedef."""
        return self._btf_has_names[1]

    @cached_property
    def _btf_has_names(self) -> tuple[bool, bool, bool]:
        # The answers from one read; the names themselves (2.3 MB) are not kept.
        try:
            found = names(self.btf_source) if self.btf_source else b""
        except KernelError:
            found = b""
        # Typed tracepoints and bpf_task_pt_regs (which takes a typed task) need the kernel's own.
        return (b"\0bpf_perf_link\0" in found, self.has_btf and b"\0btf_trace_sched_switch\0" in found,
                self.has_btf and b"\0BPF_FUNC_task_pt_regs\0" in found)

    @cached_property
    def bpf_atomics(self) -> bool:
        """BPF atomic operations that return a value, compare-and-swap among them (Linux >= 5.12)."""
        return release_version(self.kernel_release) >= (5, 12)

    @cached_property
    def task_pt_regs(self) -> bool:
        """bpf_task_pt_regs (Linux >= 5.15): a syscall's exit program reads the call's arguments."""
        return self._btf_has_names[2]

    @cached_property
    def task_storage(self) -> bool:
        """Task-local storage in tracing programs (Linux >= 5.12, "bpf: Enable task local storage
        for tracing programs"; the map type itself came in 5.11, for LSM programs only)."""
        return self.has_btf and release_version(self.kernel_release) >= (5, 12)

    @cached_property
    def preempt_rt(self) -> bool:
        """A PREEMPT_RT kernel, whose BPF programs run with migration, not preemption, disabled:
        programs of two tasks on one CPU can interleave, so no per-CPU scratch is safe."""
        return os.path.exists("/sys/kernel/realtime")

    @cached_property
    def bpf_test_run(self) -> bool:
        """The agent may run a raw tracepoint program itself (BPF_PROG_TEST_RUN, Linux >= 5.10)."""
        return release_version(self.kernel_release) >= (5, 10)

    @cached_property
    def uprobes(self) -> bool:
        return os.path.isdir("/sys/bus/event_source/devices/uprobe")

    def tracepoint(self, event: str) -> bool:
        """Whether a raw tracepoint exists: from tracefs when mounted (cheap), else from BTF."""
        if self.tracefs:
            return event in self._tracefs_events
        return self.btf is not None and self.btf.tracepoint_args(event) is not None

    @cached_property
    def _tracefs_events(self) -> set[str]:
        root = f"{TRACEFS}/events"
        return {event for category in _listdir(root) for event in _listdir(os.path.join(root, category))}

    @cached_property
    def fentry(self) -> bool:
        """BPF trampolines: only loading one tells (a kernel may refuse them with EPERM)."""
        if not (self.bcc and self.has_btf and self.privileged):
            return False
        from drums.kernel.loader import can_load_fentry
        return can_load_fentry(self.kernel_headers)


def release_version(release: str) -> tuple[int, int]:
    """(major, minor) of a kernel release string: 6.1.0-18-amd64 -> (6, 1); (0, 0) if it has none."""
    try:
        major, minor = release.split(".")[:2]
        return int(major), int("".join(takewhile(str.isdigit, minor)) or 0)
    except ValueError:
        return 0, 0


def _listdir(path: str) -> list[str]:
    try:
        return os.listdir(path)
    except OSError:
        return []


def is_mount_of_type(mounts: str, target: str, fstype: str) -> bool:
    try:
        with open(mounts) as f:
            return any(line.split()[1:3] == [target, fstype] for line in f)
    except OSError:
        return False
