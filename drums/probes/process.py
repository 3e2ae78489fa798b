"""Memory, threads, file descriptors and storage I/O of the processes the agent chose, via psutil.

Only the chosen PIDs are read, since the agent may watch a thousand processes on a small robot computer.
"""
from __future__ import annotations

import heapq
import os
import time
from typing import Iterable

import psutil

from drums.metrics import COUNTER, GAUGE, Changes, Metric, Snapshot
from drums.probes.base import Probe, ProbeStatus
from drums.proctable import ProcessTable

LABELS = ("pid", "process")
GOLDEN = 0.6180339887  # spreads consecutive PIDs evenly over the unit interval
# A process that has not run since it was read has the memory, threads, open files and storage I/O
# it had then, but for what the kernel's reclaim took from its memory: it is read again after
# IDLE_INTERVAL times a half to one (by its PID, so that the idle processes of a host spread their
# reads over the scrapes rather than come due together). Most of a host's processes sleep: at 60 s,
# their reads were half of a small host's (4 of 7 a scrape at 180 processes, 0.5 ms).
INTERVAL, IDLE_INTERVAL = 5.0, 300.0
_READ = (f"read at most every {INTERVAL:g} s; one that has not run since, every {IDLE_INTERVAL / 2:g} to "
         f"{IDLE_INTERVAL:g} s")
# USS comes from smaps_rollup, for which the kernel walks the process's page tables: the dearest
# read of a process by far (0.3 ms and more for a large one). Unique memory changes with resident
# memory, which statm gives cheaply: USS is read again when RSS moved by more than 1/USS_MOVED of
# itself since, or once it is USS_EVERY seconds old. A process without resident memory (a kernel
# thread) has no unique memory either: nothing to walk.
USS_MOVED, USS_EVERY = 32, 60.0

RESIDENT_MEMORY = Metric("drums_process_resident_memory_bytes", GAUGE, f"Resident set size ({_READ})", LABELS)
UNIQUE_MEMORY = Metric(
    "drums_process_unique_memory_bytes", GAUGE,
    f"Memory freed if the process exited (USS; read with RSS when RSS moved by more than 1/{USS_MOVED} since, "
    f"else every {USS_EVERY:g} s)", LABELS
)
THREADS = Metric("drums_process_threads", GAUGE, "Threads in the process", LABELS)
OPEN_FDS = Metric("drums_process_open_fds", GAUGE, "Open file descriptors", LABELS)
READ_BYTES = Metric(
    "drums_process_read_bytes_total", COUNTER, "Bytes the process caused to be read from storage", LABELS
)
WRITTEN_BYTES = Metric(
    "drums_process_written_bytes_total", COUNTER, "Bytes the process caused to be written to storage", LABELS
)
START_TIME = Metric("drums_process_start_time_seconds", GAUGE, "Process start time, Unix seconds", LABELS,
                    additive=False)


def _spread(pid: int) -> float:
    """Where in [0, 1) a process's reads fall, by its PID: consecutive PIDs spread evenly."""
    return (pid * GOLDEN) % 1.0


class _Read:
    """A process's values at its last read, what tells whether they may have changed since, and its
    USS with the time and RSS it was read at; and its rows, made while its name stays (a process
    not read again gives the same tuples, which the budget and the render compare by identity)."""
    __slots__ = ("at", "values", "refresh", "cpu", "uss", "rows")

    def __init__(self, at: float, values: list, refresh: int, cpu: float | None, uss: tuple | None):
        self.at, self.values, self.refresh, self.cpu, self.uss = at, values, refresh, cpu, uss
        self.rows: tuple = ()  # ((metric, (labels, value)), ...)

    def rows_named(self, pid: int, name: str) -> tuple:
        if not self.rows or self.rows[0][1][0][1] != name:
            labels = (str(pid), name)
            self.rows = tuple((metric, (labels, value)) for metric, value in self.values)
        return self.rows


def _allowed(read):
    """What `read()` gives, None where the kernel denies it: a process of another user namespace,
    or one made undumpable, shows its statm, stat and status but not its smaps_rollup or io."""
    try:
        return read()
    except psutil.AccessDenied:
        return None


def open_fds(pid: int) -> int:
    """Open file descriptors of a process. Linux 6.2 and later give their count as the size of
    /proc/PID/fd: one stat, where listing it (psutil) costs milliseconds for a process with
    thousands of sockets; older kernels say 0 there, and it is listed."""
    path = f"/proc/{pid}/fd"
    try:
        return os.stat(path).st_size or len(os.listdir(path))
    except FileNotFoundError:
        raise psutil.NoSuchProcess(pid) from None
    except PermissionError:
        raise psutil.AccessDenied(pid) from None


class ProcessProbe(Probe):
    name = "process"
    metrics = (RESIDENT_MEMORY, UNIQUE_MEMORY, THREADS, OPEN_FDS, READ_BYTES, WRITTEN_BYTES, START_TIME)

    def __init__(self, proctable: ProcessTable, interval: float = INTERVAL, idle_interval: float = IDLE_INTERVAL):
        super().__init__()
        self.proctable = proctable  # names as every probe gives them: following renames and exec
        # Each process costs several /proc reads (smaps_rollup above all), and memory, threads and
        # open files change slowly: a process is read at most once per interval (seconds), and one
        # that has not run since (as the sched probe tells the process table) once per idle_interval.
        self.interval, self.idle_interval = interval, idle_interval
        self._pids: frozenset[int] = frozenset()
        self._procs: dict[int, psutil.Process] = {}
        self._last: dict[int, _Read] = {}
        # A collect looks only at the processes that may be due (see _to_look_at), not at every
        # chosen one: every one when the process table cannot say what changed (no sched probe,
        # lost notices), and after a collect that failed midway.
        self._look_at: dict[int, float] = {}  # pid -> when its wait runs out, as last reckoned
        self._queue: list[tuple[float, int]] = []  # the same as a heap; an entry not in _look_at is stale
        self._refreshed = -1  # the process table's refresh at the last collect
        self._cpu: dict[int, float] = {}  # the CPU seconds the process table gave at the last collect
        self._look_at_all = True
        self._rows: dict[int, tuple] = {}  # pid -> its rows ((metric, (labels, value)), ...) as shown
        self._shown: dict[Metric, dict[int, tuple]] = {metric: {} for metric in self.metrics}  # the same by metric
        self._gone: list[tuple] = []  # rows of processes left out since the last collect
        self._collects = 0

    def start(self) -> None:
        self.status = ProbeStatus(attached=True, attach_type="psutil")

    def set_pids(self, pids: Iterable[int]) -> None:
        self._pids = frozenset(pids)
        for pid in self._procs.keys() - self._pids:
            del self._procs[pid]
        for pid in self._last.keys() - self._pids:
            del self._last[pid]
        for pid in self._rows.keys() - self._pids:
            self._show(pid, ())
        for pid in self._look_at.keys() - self._pids:
            del self._look_at[pid]

    def _wait(self, pid: int, cached: _Read) -> float:
        """Seconds from its last read until the process is read again, unless the kernel says its PID
        has another process: longer while it has not run since."""
        cpu = self.proctable.cpu(pid)
        idle = cpu is not None and cpu == cached.cpu
        return self.idle_interval * (1 + _spread(pid)) / 2 if idle else self.interval

    def _due(self, pid: int, cached: _Read | None, now: float) -> bool:
        """Whether the process must be read now rather than given its values of the last read."""
        table = self.proctable
        if cached is None:
            return True
        # The process table knows which PIDs have another process since a read, where the kernel
        # tells it of every exit and exec (new_at); else psutil checks the start time.
        new_at = table.new_at(pid)
        if new_at is not None and new_at > cached.refresh:
            self._procs.pop(pid, None)
            return True
        return now - cached.at >= self._wait(pid, cached) or (new_at is None and not self._procs[pid].is_running())

    def _to_look_at(self, now: float, whole: bool) -> tuple[set[int], bool]:
        """The chosen processes that may be due now (not read yet, ended, renamed or exec'd, run
        since the last collect, or whose wait ran out), and whether they are all of them: `whole`,
        or the table cannot tell what changed."""
        table = self.proctable
        renamed, cpu = table.renamed_since(self._refreshed), table.cpu_seconds()
        self._refreshed = table.refreshes
        was, self._cpu = self._cpu, cpu or {}
        if whole or renamed is None or cpu is None:
            return set(self._pids), True
        ran = {pid for pid, _ in cpu.items() - was.items()}  # moved or new: C's set work, not a loop here
        unread_or_ended = self._pids - table.alive_among(self._last.keys())  # read and alive: the others
        look = ((renamed | ran) & self._pids) | unread_or_ended
        queue = self._queue
        while queue and queue[0][0] <= now:
            at, pid = heapq.heappop(queue)
            if self._look_at.get(pid) == at:
                look.add(pid)
        return look, False

    def collect(self, snap: Snapshot) -> None:
        """The rows of every chosen process, told as what changed since the last collect: a process
        that is not due keeps its rows (the same tuples)."""
        now, table = time.monotonic(), self.proctable
        self._collects += 1  # first: a collect that fails is one the next cannot be told against
        whole, self._look_at_all = self._look_at_all, True  # until this collect is through
        look, whole = self._to_look_at(now, whole)
        changed = []
        for pid in look:
            cached = self._last.get(pid)
            if self._due(pid, cached, now):
                try:
                    values, uss = self._read(pid, cached.uss if cached else None, now)
                except (psutil.NoSuchProcess, psutil.AccessDenied):  # ZombieProcess is a NoSuchProcess
                    self._procs.pop(pid, None)
                    self._last.pop(pid, None)
                    self._look_at.pop(pid, None)  # looked at again at each collect, while chosen
                    self._show(pid, ())
                    continue
                # A process read for the first time is given a phase within the interval, so that
                # a hundred processes found at once are read a few at each scrape afterwards, not
                # all at every fifth one (a scrape of 50 ms at the 95th percentile).
                phase = 0.0 if cached else _spread(pid) * self.interval
                cached = self._last[pid] = _Read(now - phase, values, table.refreshes, table.cpu(pid), uss)
            rows = cached.rows_named(pid, table.name(pid))
            if rows is not self._rows.get(pid):
                self._show(pid, rows)
                changed += rows
            self._look_at[pid] = at = cached.at + self._wait(pid, cached)
            if not whole:
                heapq.heappush(self._queue, (at, pid))
        if whole:  # the queue made anew: every chosen process was looked at
            self._queue = [(at, pid) for pid, at in self._look_at.items()]
            heapq.heapify(self._queue)
        gone, self._gone, self._look_at_all = self._gone, [], False
        told = {metric: Changes(self._collects - 1, self._collects, [], []) for metric in self.metrics}
        for metric, row in changed:
            told[metric].rows.append(row)
        for metric, labels in gone:
            told[metric].gone.append(labels)
        for metric, rows in self._shown.items():
            if rows:
                snap.rows(metric).extend(rows.values())
            snap.changes[(metric,)] = told[metric]

    def _show(self, pid: int, rows: tuple) -> None:
        """Show these rows of the process from now on (none: it is left out). A row of a metric it
        had keeps its place (the render compares rows in place); the labels no longer shown are
        gone, for the collect to tell."""
        now = dict(rows)
        for metric, (labels, _) in self._rows.pop(pid, ()):
            row = now.get(metric)
            if row is None:
                del self._shown[metric][pid]
            if row is None or row[0] != labels:
                self._gone.append((metric, labels))
        if rows:
            self._rows[pid] = rows
            for metric, row in rows:
                self._shown[metric][pid] = row

    def _read(self, pid: int, uss: tuple | None, now: float) -> tuple[list[tuple[Metric, float]], tuple | None]:
        """The process's values, leaving out those the kernel denies, and its USS as (value, when
        read, RSS then): the one given if still fresh, else read anew."""
        proc = self._procs.get(pid)
        if proc is None:  # a process not read before, or another one at its PID: its USS is unknown
            proc = self._procs[pid] = psutil.Process(pid)
            uss = None
        with proc.oneshot():
            # A zombie has exited: psutil 7 reads its memory as zeros rather than raising.
            if proc.status() == psutil.STATUS_ZOMBIE:
                raise psutil.ZombieProcess(pid)
            rss = proc.memory_info().rss
            if not rss:
                uss = (0, now, 0)
            elif uss is None or now - uss[1] >= USS_EVERY or abs(rss - uss[2]) * USS_MOVED > uss[2]:
                full = _allowed(proc.memory_full_info)
                uss = (full.uss, now, rss) if full else None
            io = _allowed(proc.io_counters)
            values = [
                (RESIDENT_MEMORY, rss),
                *([(UNIQUE_MEMORY, uss[0])] if uss else ()),
                (THREADS, proc.num_threads()),
                (OPEN_FDS, open_fds(pid)),
                *([(READ_BYTES, io.read_bytes), (WRITTEN_BYTES, io.write_bytes)] if io else ()),
                (START_TIME, proc.create_time()),
            ]
        # The cached object keeps the create_time of the process it was made for. Checking it after the
        # reads also catches a PID reused while they ran; the new owner gets a fresh object next time.
        if not proc.is_running():
            raise psutil.NoSuchProcess(pid)
        return values, uss
