"""The common life of a BPF probe: choose an attach path, load it once, read its pinned maps.

A probe lists its attach paths in order of preference; the first one this kernel offers wins
(`choose_path`), and if it does not load, the next. Loaded programs and maps are pinned under
/sys/fs/bpf/drums/<probe>-<stamp>, where the stamp changes with the C source, the path and the
boot: an agent that restarts finds its pins and starts without compiling anything.
"""
from __future__ import annotations

import fcntl
import glob
import hashlib
import logging
import os
import shutil
import struct
from dataclasses import dataclass
from typing import Callable, Iterator

from drums.errors import KernelError, ProbeError
from drums.kernel import bpffs, loader, perflink
from drums.kernel.btf import VMLINUX_BTF, Btf
from drums.kernel.features import Features
from drums.probes.base import Probe
from drums.probes.entries import Entries, Marked, Matched

log = logging.getLogger("drums")

# The maps of bpf/drums.h, as `maps` entries: events lost, by reason; and the change marks, keyed
# as the map whose entries they mark.
DROPPED = {"dropped": (4, 8)}


def change_marks(key: object) -> dict[str, tuple[object, object]]:
    return {"generation": (4, 8), "changed_even": (key, 1), "changed_odd": (key, 1)}


# Values of DRUMS_ATTACH in bpf/drums.h.
ATTACH_DEFINES = {"raw_tracepoint": 1, "fentry": 2, "kprobe": 3, "tracepoint": 4, "uprobe": 5, "tp_btf": 6}


@dataclass(frozen=True)
class AttachPath:
    name: str  # raw_tracepoint, fentry or kprobe: also the value of the probe's attach_type
    attachments: tuple[tuple[str, str, str], ...]  # (kind, kernel target, BPF function)
    requires: Callable[[Features], str | None]  # why this kernel cannot use the path, or None
    serves: str  # which kernels this path is for, for the README and `drums doctor`
    optional: tuple[str, ...] = ()  # kernel functions attached only where the kernel has them
    defines: tuple[tuple[str, int], ...] = ()  # -D definitions of this path's programs


def needs_tracepoints(*events: str) -> Callable[[Features], str | None]:
    def check(f: Features) -> str | None:
        missing = [e for e in events if not f.tracepoint(e)]
        return f"no tracepoint {', '.join(missing)}" if missing else None
    return check


NO_KERNEL_BTF = "the kernel has no BTF of its own (CONFIG_DEBUG_INFO_BTF) to type programs with"


def needs_tp_btf(f: Features) -> str | None:
    if f.tp_btf:
        return None
    return "the kernel's BTF does not type its tracepoints (Linux >= 5.5)" if f.has_btf else NO_KERNEL_BTF


def needs_fentry(f: Features) -> str | None:
    if f.preempt_rt and f.kprobes:
        # A trampoline runs its program with migration, not preemption, disabled there: a program
        # preempted amid its run makes the kernel skip the program on that CPU meanwhile (its
        # recursion check), which lost 7% of a socket's calls under a SCHED_FIFO thread (6.1-rt).
        # A kprobe's runs with preemption disabled.
        return "PREEMPT_RT: a preempted trampoline makes the kernel skip its program's other runs on that CPU"
    if f.fentry:
        return None
    if not f.has_btf:
        return NO_KERNEL_BTF
    if f.kernel_headers is None:  # bcc compiles nothing without them, a trampoline's test program included
        return "no kernel headers for bcc to compile a trampoline with"
    return "the kernel refuses BPF trampolines (fentry/fexit)"


def needs_test_run(f: Features) -> str | None:
    return None if f.bpf_test_run else "the agent cannot run BPF programs itself (BPF_PROG_TEST_RUN, Linux >= 5.10)"


def needs_kprobes(f: Features) -> str | None:
    return None if f.kprobes else "kprobes are not available (CONFIG_KPROBES unset)"


def needs_uprobes(f: Features) -> str | None:
    return None if f.uprobes else "the kernel has no uprobes (CONFIG_UPROBE_EVENTS)"


def needs_all(*checks: Callable[[Features], str | None]) -> Callable[[Features], str | None]:
    """The first reason any of the checks gives, or None."""
    def check(f: Features) -> str | None:
        return next((why for why in (c(f) for c in checks) if why), None)
    return check


def typed(raw: AttachPath, without: tuple[str, ...] = (), serves: str = "") -> AttachPath:
    """The raw tracepoint path `raw` with its programs loaded as BTF tracepoint programs, whose
    loads of kernel fields cost no helper call (drums.kernel.tracing); preferred where it loads.
    `without`: tracepoints whose programs the typed ones do without; `serves`: what else to say."""
    return AttachPath("tp_btf", tuple(("tp_btf" if k == "raw_tracepoint" else k, t, fn)
                                      for k, t, fn in raw.attachments if t not in without),
                      needs_all(needs_tp_btf, raw.requires),
                      f"{raw.serves}, with typed tracepoint arguments{serves}")


def usable_paths(paths: tuple[AttachPath, ...], features: Features) -> Iterator[AttachPath]:
    """The paths this kernel offers, best first. Lazily: a check may cost much (whether the kernel
    takes fentry is asked of bcc, which would leave its compiler in the agent), and is made only
    when the paths before it did not load."""
    return (path for path in paths if path.requires(features) is None)


def choose_path(paths: tuple[AttachPath, ...], features: Features) -> tuple[AttachPath | None, list[str]]:
    """The first usable path, and why each path before it was passed over."""
    reasons = []
    for path in paths:
        why = path.requires(features)
        if why is None:
            return path, reasons
        reasons.append(f"{path.name}: {why}")
    return None, reasons


def common_requirements(features: Features) -> list[str]:
    """What every BPF probe needs, whatever its path."""
    problems = []
    if not features.privileged:
        problems.append("not root (BPF needs CAP_BPF and CAP_PERFMON)")
    if not features.bpffs:
        problems.append("bpffs is not mounted at /sys/fs/bpf (mount -t bpf bpf /sys/fs/bpf)")
    if features.btf_source is None:
        problems.append(f"no kernel BTF at {VMLINUX_BTF} (CONFIG_DEBUG_INFO_BTF): {BTF_FIX}")
    if features.kernel_headers is None:
        problems.append("no kernel headers for bcc (apt-get install linux-headers-$(uname -r), or scripts/setup.sh)")
    return problems


# How to get a kernel's BTF where the kernel has none of its own (`drums agent --btf FILE`).
BTF_FIX = ("give this kernel's BTF with --btf FILE: `pahole --btf_encode_detached FILE vmlinux` from its "
           "debug symbols, or BTFHub's file for this kernel")


def _boot_id() -> str:
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            return f.read().strip()
    except OSError:
        return ""


class BpfProbe(Probe):
    """Subclasses set source, maps and paths, give their BTF offsets, and decode their maps.

    `maps` names the maps the probe opens, each with the layout it reads it by: (key, value), each a
    struct.Struct, numpy dtype or size in bytes (None: not read by layout). This is the one layout
    source on the Python side; start() checks it against the map the C source made."""

    source = ""
    maps: dict[str, tuple[object, object] | None] = {}
    paths: tuple[AttachPath, ...] = ()
    options: dict[str, int] = {}  # -D definitions that choose what the programs do: part of the pins' name

    def __init__(self, features: Features, pin_root: str = bpffs.PIN_ROOT):
        super().__init__()
        self.features = features
        self.pin_root = pin_root
        self.opened: dict[str, bpffs.PinnedMap] = {}
        self.pin_dir = ""
        self._in_process = None  # the bcc object, for paths the kernel cannot pin
        self.programs: dict[str, int] = {}  # fds of the programs the agent attaches or runs itself, by name
        self._marked: dict[str, Marked] = {}  # maps read as far as their programs marked them changed
        self._reader: int | None = None  # the pins' directory, locked while this process reads their marks
        self._held: list[int] = []  # perf events this process attached programs to (see hold)
        self._misses_at: int | None = None  # where struct bpf_prog_info counts skipped runs, if it does

    def offsets(self, btf: Btf) -> dict[str, int]:
        """-D definitions for the C code: kernel struct offsets and tracepoint shapes."""
        raise NotImplementedError

    def _stamp(self, path: AttachPath) -> str:
        h = hashlib.sha256(loader.program_text(self.source).encode())
        h.update(f"{path.name}\0{path.defines}\0{self.features.kernel_release}\0{_boot_id()}\0"
                 f"{sorted(self.options.items())}".encode())
        return h.hexdigest()[:16]

    def start(self) -> None:
        problems = common_requirements(self.features)
        if problems:
            raise KernelError("; ".join(problems))
        refused = None  # the last path that did not load, and why
        for path in usable_paths(self.paths, self.features):
            if refused:
                log.warning("probe %s: the %s path did not load (%s); trying %s", self.name, *refused, path.name)
            try:
                self._start(path)
                return
            except ProbeError as e:
                refused = (path.name, e)
        if refused:
            raise refused[1]
        raise KernelError("no attach path: " + "; ".join(choose_path(self.paths, self.features)[1]))

    def caveat(self, path: AttachPath) -> str:
        """What the path leaves uncounted on this kernel, said by `drums doctor` and when it attaches."""
        return ""

    def attachments(self, path: AttachPath) -> list[tuple[str, str, str]]:
        """The path's attachments on this kernel: its optional functions where the kernel has them,
        and its tracepoints held by the agent where they cannot be linked (see drums.kernel.perflink)."""
        btf = self.features.btf
        return [("held_tracepoint" if kind == "tracepoint" and not self.features.perf_links else kind, target, fn)
                for kind, target, fn in path.attachments if target not in path.optional or btf.has_function(target)]

    def _start(self, path: AttachPath) -> None:
        btf = self.features.btf
        if btf is None:
            raise KernelError(f"cannot parse the kernel's BTF ({self.features.btf_source})")
        if btf.has_field("bpf_prog_info", "recursion_misses"):
            self._misses_at = btf.field("bpf_prog_info", "recursion_misses").offset
        self.pin_dir = pin_dir = os.path.join(self.pin_root, f"{self.name}-{self._stamp(path)}")
        attachments = self.attachments(path)
        if path.name in loader.PINNABLE:
            if not all(os.path.exists(os.path.join(pin_dir, m)) for m in self.maps):
                self._remove_pins()
                loader.load_in_child(self._request(path, attachments, pin_dir))
            try:
                for m in self.maps:
                    self.opened[m] = bpffs.PinnedMap(os.path.join(pin_dir, m))
                for kind, _, fn in attachments:
                    if kind in loader.PROGRAMS:
                        self.programs[fn] = bpffs.obj_get(os.path.join(pin_dir, f"prog_{fn}"))
                for kind, target, fn in attachments:
                    if kind == "held_tracepoint":
                        self.hold(perflink.tracepoint(self.programs[fn], target, link=False))
            except ProbeError:
                self.stop()
                raise
        else:
            self._in_process, fds = loader.attach(self._request(path, attachments, pin_dir))
            self.opened = {m: bpffs.PinnedMap.from_fd(self._in_process[m.encode()].map_fd, m)
                           for m in self.maps}
            self.programs = {fn: os.dup(fds[f"prog_{fn}"]) for kind, _, fn in attachments
                             if kind in loader.PROGRAMS}
        try:
            self._check_layouts()
        except ProbeError:
            self.stop()
            raise
        self.status.attached = True
        self.status.attach_type = path.name
        self.status.reason = ""
        caveat = self.caveat(path)
        if caveat:
            log.warning("probe %s: %s", self.name, caveat)

    def _check_layouts(self) -> None:
        for name, layout in self.maps.items():
            if layout is None:
                continue
            expected = tuple(n if isinstance(n, int) else getattr(n, "itemsize", None) or n.size for n in layout)
            m = self.opened[name]
            if (m.key_size, m.declared_value_size) != expected:
                raise ProbeError(f"map {name}: bpf/{self.source} makes entries of {m.key_size}+{m.declared_value_size}"
                                 f" bytes, drums reads {expected[0]}+{expected[1]} (key+value): the two disagree")

    def _request(self, path: AttachPath, attachments: list[tuple[str, str, str]], pin_dir: str) -> loader.LoadRequest:
        defines = dict(self.offsets(self.features.btf), **self.options, **dict(path.defines),
                       DRUMS_ATTACH=ATTACH_DEFINES[path.name])
        return loader.LoadRequest(
            source=self.source,
            cflags=[f"-D{k}={v}" for k, v in sorted(defines.items())],
            attachments=attachments,
            maps=list(self.maps),
            pin_dir=pin_dir,
            headers=self.features.kernel_headers,
        )

    def hold(self, fd: int) -> None:
        """Keep a perf event with a program attached until the probe stops (Linux < 5.15, whose
        perf events cannot be linked and pinned)."""
        self._held.append(fd)

    def attached(self, fd: int, pin: str) -> None:
        """An attachment perflink made: pinned if it is a link, which then outlives this process,
        else held while the probe runs."""
        if not self.features.perf_links:
            self.hold(fd)
            return
        try:
            bpffs.pin(fd, pin)
        finally:
            os.close(fd)

    def read(self, name: str) -> tuple[bytes, bytes, int]:
        m = self.opened[name]
        keys, values, count = m.read()
        if m.type not in bpffs.ARRAY_TYPES:  # arrays are always full; hash maps fill up
            self.status.map_fill[name] = count / m.max_entries
        return keys, values, count

    def _marks_ours(self) -> bool:
        """Whether this process reads the marks of the probe's maps (see Marked). They are one set
        per set of pins, and each read takes them: of two readers of the pins (two agents on one
        host), each would miss what the other took, and show counts a collect late. The first to
        read holds a lock on the pins' directory while it runs; another reads the maps whole, and
        takes the marks over once the lock is free."""
        if self._in_process is not None:
            return True  # maps of this process alone
        if self._reader is None:
            try:
                fd = os.open(self.pin_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
            except OSError:
                return False  # the pins went (unloaded): the whole read says so
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                return False
            self._reader = fd
        return True

    def marks(self, name: str, whole_above: int = 8) -> Marked | None:
        """The marks of the map `name`, whose programs mark the keys they change (in the maps
        `generation`, `changed_even` and `changed_odd`); None while another process reads them."""
        if not self._marks_ours():
            self._marked.pop(name, None)  # their generation is the other reader's now
            return None
        marked = self._marked.get(name)
        if marked is None or marked.map is not self.opened[name]:
            marked = self._marked[name] = Marked(self.opened[name], self.opened["generation"],
                                                 (self.opened["changed_even"], self.opened["changed_odd"]), whole_above)
        return marked

    def read_marked(self, name: str, entries: Entries) -> Matched:
        """The map `name`, whose programs mark the keys they change, matched against `entries`:
        looked up as far as it changed, read whole when much did (and always, while another process
        reads the marks)."""
        marked = self.marks(name)
        if marked is None:
            return entries.read(*self.read(name)[:2])
        got = marked.read(len(entries), whole=not entries.kept)
        m = entries.read(*got[:2]) if isinstance(got, tuple) else entries.update(got)
        self.status.map_fill[name] = len(m.keys) / marked.map.max_entries
        return m

    def read_map_memory(self) -> None:
        self.status.map_memory = sum(m.memory() for m in self.opened.values())

    def read_dropped(self) -> None:
        """Events lost to full maps (every program counts them in its `dropped` array), and runs of
        its programs the kernel skipped, where it counts them (Linux >= 5.12)."""
        _, values, _ = self.read("dropped")
        self.status.dropped = sum(v for (v,) in struct.iter_unpack("<Q", values))
        if self._misses_at is not None:
            self.status.missed = sum(bpffs.prog_runs_missed(fd, self._misses_at) for fd in self.programs.values())

    def stop(self) -> None:
        for m in self.opened.values():
            m.close()
        self.opened = {}
        for fd in list(self.programs.values()) + self._held:
            os.close(fd)
        self.programs, self._held = {}, []
        if self._reader is not None:
            os.close(self._reader)  # another reader of the pins may take the marks over
            self._reader = None
        if self._in_process is not None:
            self._in_process.cleanup()
            self._in_process = None
        self.status.attached = False

    def unload(self) -> None:
        """Stop and remove this probe's pins, which detaches its programs."""
        self.stop()
        self._remove_pins()

    def _remove_pins(self) -> None:
        for old in glob.glob(os.path.join(self.pin_root, f"{self.name}-*")):
            shutil.rmtree(old, ignore_errors=True)
        try:
            os.rmdir(self.pin_root)  # the last probe out leaves no empty folder behind
        except OSError:
            pass


# What leader_tgid() and process_start() in bpf/drums.h read from a struct task_struct.
TASK_IDENTITY_FIELDS = {
    "TASK_PID_OFF": ("task_struct", "pid"),
    "TASK_TGID_OFF": ("task_struct", "tgid"),
    "TASK_GROUP_LEADER_OFF": ("task_struct", "group_leader"),
    "TASK_START_TIME_OFF": ("task_struct", "start_time"),
}

# What read_endpoints() in bpf/drums.h reads from a struct sock.
SOCK_ENDPOINT_FIELDS = {
    "SK_FAMILY_OFF": ("sock", "__sk_common.skc_family"),
    "SK_NUM_OFF": ("sock", "__sk_common.skc_num"),
    "SK_DPORT_OFF": ("sock", "__sk_common.skc_dport"),
    "SK_DADDR_OFF": ("sock", "__sk_common.skc_daddr"),
    "SK_RCV_SADDR_OFF": ("sock", "__sk_common.skc_rcv_saddr"),
    "SK_V6_DADDR_OFF": ("sock", "__sk_common.skc_v6_daddr"),
    "SK_V6_RCV_SADDR_OFF": ("sock", "__sk_common.skc_v6_rcv_saddr"),
    "SK_NET_OFF": ("sock", "__sk_common.skc_net"),
    "NET_INUM_OFF": ("net", "ns.inum"),
}


def comm_text(comm: bytes) -> str:
    """A task's name as a BPF program copied it (16 bytes, NUL-padded)."""
    return comm.split(b"\0", 1)[0].decode(errors="replace")


class ProcessTotals:
    """A process's totals from two maps: its exited threads (folded per process by the kernel) and
    its live threads. A process is its PID and its start time, so the folded threads of a process
    that had the PID before are left out."""

    def __init__(self):
        self._totals: dict[tuple[int, int], list] = {}
        self._live_start: dict[int, int] = {}

    def add_exited(self, tgid: int, start: int, values) -> None:
        self._totals[(tgid, start)] = list(values)

    def add_thread(self, tgid: int, start: int, values) -> None:
        self._live_start[tgid] = start
        acc = self._totals.get((tgid, start))
        self._totals[(tgid, start)] = list(values) if acc is None else [a + b for a, b in zip(acc, values)]

    def items(self):
        """((pid, start time), summed values) of every process."""
        for (tgid, start), values in self._totals.items():
            if self._live_start.get(tgid, start) == start:
                yield (tgid, start), values


def offset_defines(btf: Btf, fields: dict[str, tuple[str, str]]) -> dict[str, int]:
    """NAME -> byte offset, for each NAME: (struct, member path)."""
    try:
        return {name: btf.field(s, p).offset for name, (s, p) in fields.items()}
    except KernelError as e:
        raise ProbeError(str(e)) from None
