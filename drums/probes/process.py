"""Memory, threads, file descriptors and storage I/O of the processes the agent chose, via psutil.

Only the chosen PIDs are read, since the agent may watch a thousand processes on a small robot computer.
"""
from __future__ import annotations

import os
import time
from typing import Iterable

import psutil

from drums.metrics import COUNTER, GAUGE, Metric, Snapshot
from drums.probes.base import Probe, ProbeStatus
from drums.proctable import ProcessTable

LABELS = ("pid", "process")
RESIDENT_MEMORY = Metric("drums_process_resident_memory_bytes", GAUGE, "Resident set size", LABELS)
UNIQUE_MEMORY = Metric(
    "drums_process_unique_memory_bytes", GAUGE, "Memory freed if the process exited (USS)", LABELS
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


GOLDEN = 0.6180339887  # spreads consecutive PIDs evenly over the unit interval


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

    def __init__(self, proctable: ProcessTable, interval: float = 5.0):
        super().__init__()
        self.proctable = proctable  # names as every probe gives them: following renames and exec
        # Each process costs several /proc reads (smaps_rollup above all), and memory, threads and
        # open files change slowly: a process is read at most once per interval (seconds).
        self.interval = interval
        self._pids: frozenset[int] = frozenset()
        self._procs: dict[int, psutil.Process] = {}
        self._read_at: dict[int, tuple[float, list, int]] = {}  # pid -> (when, values, table's refreshes)

    def start(self) -> None:
        self.status = ProbeStatus(attached=True, attach_type="psutil")

    def set_pids(self, pids: Iterable[int]) -> None:
        self._pids = frozenset(pids)
        for pid in self._procs.keys() - self._pids:
            del self._procs[pid]
        for pid in self._read_at.keys() - self._pids:
            del self._read_at[pid]

    def collect(self, snap: Snapshot) -> None:
        now, table = time.monotonic(), self.proctable
        for pid in self._pids:
            cached = self._read_at.get(pid)
            # The process table knows which PIDs have another process since a read, where the kernel
            # tells it of every exit and exec (new_at); else psutil checks the start time.
            new_at = table.new_at(pid)
            if cached and new_at is not None and new_at > cached[2]:
                self._procs.pop(pid, None)
                cached = None
            if cached and now - cached[0] < self.interval and (new_at is not None or self._procs[pid].is_running()):
                values = cached[1]
            else:
                try:
                    values = self._read(pid)
                except (psutil.NoSuchProcess, psutil.AccessDenied):  # ZombieProcess is a NoSuchProcess
                    self._procs.pop(pid, None)
                    self._read_at.pop(pid, None)
                    continue
                # A process read for the first time is given a phase within the interval, so that
                # a hundred processes found at once are read a few at each scrape afterwards, not
                # all at every fifth one (a scrape of 50 ms at the 95th percentile).
                phase = 0.0 if cached else (pid * GOLDEN) % 1.0 * self.interval
                self._read_at[pid] = (now - phase, values, table.refreshes)
            labels = (str(pid), self.proctable.name(pid))
            for metric, value in values:
                snap.add(metric, labels, value)

    def _read(self, pid: int) -> list[tuple[Metric, float]]:
        proc = self._procs.get(pid)
        if proc is None:
            proc = self._procs[pid] = psutil.Process(pid)
        with proc.oneshot():
            # A zombie has exited: psutil 7 reads its memory as zeros rather than raising.
            if proc.status() == psutil.STATUS_ZOMBIE:
                raise psutil.ZombieProcess(pid)
            # memory_full_info reads smaps_rollup for USS and includes RSS, so one call gives both.
            mem = proc.memory_full_info()
            io = proc.io_counters()
            values = [
                (RESIDENT_MEMORY, mem.rss),
                (UNIQUE_MEMORY, mem.uss),
                (THREADS, proc.num_threads()),
                (OPEN_FDS, open_fds(pid)),
                (READ_BYTES, io.read_bytes),
                (WRITTEN_BYTES, io.write_bytes),
                (START_TIME, proc.create_time()),
            ]
        # The cached object keeps the create_time of the process it was made for. Checking it after the
        # reads also catches a PID reused while they ran; the new owner gets a fresh object next time.
        if not proc.is_running():
            raise psutil.NoSuchProcess(pid)
        return values
