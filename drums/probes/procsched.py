"""On-CPU time, run-queue wait and context switches from /proc, for when the BPF sched probe cannot
load (not root, no bcc, old kernel). It exports the same metric declarations as drums.probes.sched,
minus the run-queue latency histogram, and reads only the processes the agent passes to set_pids().
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Iterable, Optional

from drums.errors import KernelError
from drums.metrics import Snapshot
from drums.probes.base import Probe, ProbeStatus
from drums.probes.sched import (
    PROCESS_CPU,
    PROCESS_SWITCHES,
    THREAD_CPU,
    THREAD_RUNQ,
    THREAD_RUNQ_WAITS,
    THREAD_SWITCHES,
)
from drums.proctable import ProcessTable

CLOCK_TICK = 1 / os.sysconf("SC_CLK_TCK")  # the unit of utime and stime in /proc/<pid>/stat

REASON = ("no run-queue latency histogram; CPU time per process at clock-tick precision; "
          "context switches of a thread that exits count only up to the last collect before its exit")


@dataclass(frozen=True)
class Schedstat:
    """/proc/<pid>/task/<tid>/schedstat (Documentation/scheduler/sched-stats.rst)."""

    oncpu_ns: int  # se.sum_exec_runtime, the same clock as CLOCK_THREAD_CPUTIME_ID
    runq_ns: int  # sched_info.run_delay
    # sched_info.pcount, "# of timeslices run on this cpu". Since Linux 5.14 (commit 90a0ff4ec9c6,
    # "sched,stats: Further simplify sched_info") the kernel increments it only together with
    # run_delay, when a task that was queued gets the CPU: so it is the number of run-queue waits,
    # the quantity the BPF probe counts at sched_switch. Before 5.14 it also counted the rare
    # arrivals that had no queued timestamp.
    runs: int


def parse_schedstat(text: str) -> Optional[Schedstat]:
    fields = text.split()
    if len(fields) < 3:
        return None
    try:
        return Schedstat(int(fields[0]), int(fields[1]), int(fields[2]))
    except ValueError:
        return None


def parse_switches(status: str) -> Optional[tuple[int, int]]:
    """(voluntary, involuntary) context switches from /proc/<pid>/task/<tid>/status.

    In /proc/<pid>/status these lines are the main thread's alone (fs/proc/array.c prints the
    task's own nvcsw and nivcsw), which is why process totals are summed over threads here."""
    found = {}
    for line in status.splitlines():
        key, sep, value = line.partition(":")
        if sep and key in ("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches"):
            try:
                found[key] = int(value)
            except ValueError:
                return None
    if len(found) != 2:
        return None
    return found["voluntary_ctxt_switches"], found["nonvoluntary_ctxt_switches"]


def parse_stat(text: str) -> Optional[tuple[int, int]]:
    """(utime + stime in clock ticks, start time in clock ticks) from /proc/<pid>/stat.

    The process's utime and stime include its exited threads, and the kernel scales them to its
    nanosecond runtime, so their sum never goes backwards. comm may hold spaces and parentheses:
    the fields start after the last ')'."""
    head, sep, rest = text.rpartition(")")
    fields = rest.split()
    if not sep or len(fields) < 20:
        return None
    try:
        # Fields 14, 15 and 22 of proc(5); fields[0] is field 3 (state).
        return int(fields[11]) + int(fields[12]), int(fields[19])
    except ValueError:
        return None


def _read(path: str) -> Optional[str]:
    try:
        with open(path, "rb", buffering=0) as f:
            return f.read().decode(errors="replace")
    except OSError:  # the thread or process ended, or we may not read it
        return None


@dataclass
class _Process:
    """What the last collect saw of one process, so exited threads' switches stay in its totals."""

    start: int  # start time: a reused PID is a new process and starts a new record
    threads: dict[int, tuple[int, int]] = field(default_factory=dict)  # tid -> switches last seen
    exited: tuple[int, int] = (0, 0)  # switches of threads gone since


class ProcSchedProbe(Probe):
    name = "sched"
    metrics = (PROCESS_CPU, PROCESS_SWITCHES, THREAD_CPU, THREAD_RUNQ, THREAD_RUNQ_WAITS, THREAD_SWITCHES)

    def __init__(self, proctable: ProcessTable, proc: str = "/proc"):
        super().__init__()
        self.proctable = proctable
        self.proc = proc
        self._pids: frozenset[int] = frozenset()
        self._seen: dict[int, _Process] = {}
        self._schedstat = True

    def start(self) -> None:
        if not os.path.isdir(f"{self.proc}/self/task"):
            raise KernelError(f"{self.proc} is not a mounted procfs")
        # Without CONFIG_SCHED_INFO the file is missing; before Linux 5.14 it reads "0 0 0" unless
        # schedstats or delay accounting are on. This process has surely run, so zeros mean off.
        own = parse_schedstat(_read(f"{self.proc}/self/schedstat") or "")
        self._schedstat = own is not None and own != Schedstat(0, 0, 0)
        reason = REASON
        if not self._schedstat:
            reason += "; no per-thread CPU or run-queue time (no /proc/<pid>/schedstat)"
        self.status = ProbeStatus(attached=True, attach_type="proc", reason=reason)

    def set_pids(self, pids: Iterable[int]) -> None:
        self._pids = frozenset(pids)
        for pid in self._seen.keys() - self._pids:
            del self._seen[pid]

    def collect(self, snap: Snapshot) -> None:
        for pid in self._pids:
            stat = parse_stat(_read(f"{self.proc}/{pid}/stat") or "")
            if stat is None:
                self._seen.pop(pid, None)
                continue
            ticks, start = stat
            seen = self._seen.get(pid)
            if seen is None or seen.start != start:
                seen = self._seen[pid] = _Process(start)
            switches = self._threads(pid, seen, snap)
            if switches is None:
                continue
            labels = (str(pid), self.proctable.name(pid))
            snap.add(PROCESS_CPU, labels, ticks * CLOCK_TICK)
            snap.add(PROCESS_SWITCHES, labels + ("voluntary",), switches[0])
            snap.add(PROCESS_SWITCHES, labels + ("involuntary",), switches[1])

    def _threads(self, pid: int, seen: _Process, snap: Snapshot) -> Optional[tuple[int, int]]:
        """Emit each thread's series; return the process's switches, exited threads included."""
        try:
            tids = [int(t) for t in os.listdir(f"{self.proc}/{pid}/task") if t.isdigit()]
        except OSError:
            return None
        now: dict[int, tuple[int, int]] = {}
        for tid in tids:
            task = f"{self.proc}/{pid}/task/{tid}"
            switches = parse_switches(_read(f"{task}/status") or "")
            if switches is None:
                # Listed but unreadable: most likely exiting. Keep what we saw, so it is folded
                # once, when it is no longer listed.
                if tid in seen.threads:
                    now[tid] = seen.threads[tid]
                continue
            now[tid] = switches
            labels = (str(pid), str(tid), (_read(f"{task}/comm") or "").rstrip("\n"))
            sched = parse_schedstat(_read(f"{task}/schedstat") or "") if self._schedstat else None
            if sched is not None:
                snap.add(THREAD_CPU, labels, sched.oncpu_ns / 1e9)
                snap.add(THREAD_RUNQ, labels, sched.runq_ns / 1e9)
                snap.add(THREAD_RUNQ_WAITS, labels, sched.runs)
            snap.add(THREAD_SWITCHES, labels + ("voluntary",), switches[0])
            snap.add(THREAD_SWITCHES, labels + ("involuntary",), switches[1])
        exited = seen.exited
        for tid, last in seen.threads.items():
            new = now.get(tid)
            # Gone, or its TID reused by a new thread (counts fell): keep what the old one did.
            if new is None or new[0] < last[0] or new[1] < last[1]:
                exited = (exited[0] + last[0], exited[1] + last[1])
        seen.threads, seen.exited = now, exited
        return (exited[0] + sum(v for v, _ in now.values()),
                exited[1] + sum(i for _, i in now.values()))
