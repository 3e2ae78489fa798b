"""The processes alive on this host, with their names: shared by probes, selection and budget.

Refreshed once per collect from one listing of /proc; a name is read only for a PID not seen in
the previous listing, so a process that exits and whose PID is reused gets its new name.

With $DRUMS_OWN_NETNS=1 (`drums agent --own-netns`, inherited by the graph reader the agent
starts) the table holds only the processes in this process's network namespace: where namespaces
or containers stand for hosts, one agent per namespace reports its own host and nothing else.
"""
from __future__ import annotations

import ctypes
import os
import threading
import time
from typing import Callable, Iterable

OWN_NETNS = "DRUMS_OWN_NETNS"
# A process found in another network namespace is looked at again for this long, and at least at
# the next listing: `nsenter`, `ip netns exec` and container runtimes fork first and move the child
# to its namespace a few milliseconds later, and a listing may fall in between.
SETTLE = 2.0
RENAMES_KEPT = 8  # refreshes whose renamed PIDs are kept, for renamed_since()
_PR_SET_NAME = 15


def netns(proc: str, pid: int | str) -> int | None:
    """The inode of a process's network namespace (None if it is gone or hidden)."""
    try:
        return os.stat(f"{proc}/{pid}/ns/net").st_ino
    except OSError:
        return None


HELPER = "drums-"  # the name (comm) of the agent's own helper processes starts so


def name_helper(role: str) -> None:
    """Name this process drums-<role> in ps, top and /proc/<pid>/comm, so that the agent's own
    helpers (the ROS 2 graph reader, the /diagnostics publisher) are not taken for the robot's."""
    ctypes.CDLL(None).prctl(_PR_SET_NAME, (HELPER + role).encode()[:15], 0, 0, 0)


def process_start(proc: str, pid: int | str, running: bool = False) -> int | None:
    """When the process with this PID started (clock ticks after boot): with the PID, what tells it
    from a later process that got the PID. None if there is none (with `running`, nor if it has
    exited and waits to be reaped)."""
    try:
        with open(f"{proc}/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return None if running and fields[0] in (b"Z", b"X") else int(fields[19])
    except (OSError, IndexError, ValueError):
        return None


def comm(proc: str, pid: int) -> str:
    """A process's name as the kernel keeps it ("" if it is gone)."""
    try:
        with open(f"{proc}/{pid}/comm") as f:
            return f.read().rstrip("\n")
    except OSError:
        return ""


class ProcessTable:
    def __init__(self, proc: str = "/proc"):
        self.proc = proc
        self.netns = netns(proc, "self") if os.environ.get(OWN_NETNS) == "1" else None
        self._names: dict[int, str] = {}
        # The PIDs that left the table at the last refresh, with their names (a probe whose kernel
        # maps keep an ended process's final totals shows them once, and names it so), and those
        # of processes that started and ended between two refreshes, as the kernel told them.
        self._ended: dict[int, str] = {}
        self._cmdlines: dict[int, list[str]] = {}  # read when first asked for, kept while the PID lives
        # PIDs in other network namespaces at the last listing -> (when first found there, whether a
        # later listing found it there too)
        self._elsewhere: dict[int, tuple[float, bool]] = {}
        # For each PID, the refresh at which its process was last found new: it appeared, or was
        # renamed, exec'd, or exited and came back. Known while every refresh is told by the kernel
        # which processes were renamed (a set, as the agent's is by the sched probe) or reads every
        # name (None); one that is told nothing (the default) may miss a PID reused meanwhile.
        self.refreshes = 0
        self._new_at: dict[int, int] = {}
        self._told = True
        self._cpu: dict[int, float] = {}  # what the sched probe said at the refresh _cpu_at
        self._cpu_at = -1
        # The last refreshes: (refresh, the PIDs whose names it read, None if it read every one).
        self._renames: list[tuple[int, set[int] | None]] = []

    def refresh(self, renamed: Iterable[int] | None = (), complete: bool = False) -> None:
        """List the processes. A name is read when its PID first appears, and again when the PID is
        in `renamed` (its process exec'd or was renamed, or exited: a PID that comes back is another
        process); its command line is then read anew when next asked for. `renamed` None: any may
        have been, so every name is read. `complete`: `renamed` also names every process forked
        since the last refresh (the sched probe's does), so when it is empty nothing came, went or
        changed its name, and /proc is not listed (1,000 processes: 2 ms)."""
        if complete and renamed is not None and not renamed and self.refreshes:
            self.refreshes += 1
            self._renamed_at(set())
            self._ended = {}
            return
        alive = set(self.listing())
        known = {} if renamed is None else self._names
        if renamed:
            known = dict(known)
            for pid in renamed:
                known.pop(pid, None)
                self._cmdlines.pop(pid, None)
                self._elsewhere.pop(pid, None)
        if self.netns is not None:
            self._elsewhere = self._still_elsewhere(alive, known)
            alive -= self._elsewhere.keys()
        self.refreshes += 1
        self._told = self._told and (renamed is None or isinstance(renamed, set))
        self._new_at = {pid: self._new_at.get(pid, 0) if pid in known else self.refreshes for pid in alive}
        self._ended = {pid: name for pid, name in self._names.items() if pid not in alive}
        self._names = {pid: known.get(pid) or comm(self.proc, pid) for pid in alive}
        self._renamed_at(None if renamed is None else alive - known.keys())
        self._cmdlines = {pid: line for pid, line in self._cmdlines.items() if pid in alive and pid in known}

    def _still_elsewhere(self, alive: set[int], known: dict) -> dict[int, tuple[float, bool]]:
        """Of the PIDs alive, those in another network namespace: each is checked when it first
        appears, as its name is read, and again while it may still be on its way to its own."""
        now = time.monotonic()
        out = {}
        for pid in alive:
            found = self._elsewhere.get(pid)
            if found is not None and found[1] and now - found[0] >= SETTLE:
                out[pid] = found
            elif (found is not None or pid not in known) and netns(self.proc, pid) != self.netns:
                out[pid] = (now, False) if found is None else (found[0], True)
        return out

    def _renamed_at(self, pids: set[int] | None) -> None:
        self._renames = self._renames[-RENAMES_KEPT + 1:] + [(self.refreshes, pids)]

    def renamed_since(self, refresh: int) -> set[int] | None:
        """The PIDs whose names may have changed after that refresh (they came, or were renamed,
        exec'd, or exited and came back); None when it cannot say (a refresh read every name, or
        the refresh is too long ago): any may have."""
        later = [pids for at, pids in self._renames if at > refresh]
        if len(later) != self.refreshes - refresh or any(pids is None for pids in later):
            return None
        return set().union(*later)

    def alive_among(self, pids: Iterable[int]) -> set[int]:
        """Those of the PIDs whose processes are in the table."""
        return self._names.keys() & pids

    def new_at(self, pid: int) -> int | None:
        """The refresh at which the process with this PID was last found new; None when that cannot
        be known (a refresh was not told which processes were renamed) or the PID is gone."""
        return self._new_at.get(pid) if self._told else None

    def ran(self, cpu: dict[int, float]) -> None:
        """Told by the sched probe at each collect: the CPU seconds each process that has run
        since the probe attached has used. A process whose count has not moved has not run, so its
        memory, threads, open files and storage I/O are as they were (but for the kernel's reclaim)."""
        self._cpu, self._cpu_at = cpu, self.refreshes

    def cpu(self, pid: int) -> float | None:
        """The process's CPU seconds as the sched probe counted them at this refresh (0: it has not
        run since the probe attached); None when no sched probe said so at this refresh."""
        told = self.cpu_seconds()
        return None if told is None else told.get(pid, 0.0)

    def cpu_seconds(self) -> dict[int, float] | None:
        """Each process's CPU seconds as the sched probe said at this refresh (one it did not name
        has not run since it attached); None when it did not (it failed, or is not attached). The
        dict is replaced whole, never changed: a reader on another thread may keep it."""
        return self._cpu if self._cpu_at == self.refreshes else None

    def alive(self, pid: int) -> bool:
        return pid in self._names

    def listing(self) -> list[int]:
        """The PIDs in /proc now, whatever their network namespace."""
        return [int(d) for d in os.listdir(self.proc) if d.isdigit()]

    def belongs(self, pid: int) -> bool:
        """Whether the process is one of this table's, though it may have started after the last
        listing: alive, and in this agent's network namespace where it reports only its own."""
        if pid in self._names:
            return True
        if pid in self._elsewhere:
            return False
        if self.netns is None:
            return os.path.exists(f"{self.proc}/{pid}")
        return netns(self.proc, pid) == self.netns

    def name(self, pid: int) -> str:
        return self._names.get(pid, "")

    def ended_name(self, pid: int) -> str:
        """The name of a process that ended since the last refresh but one ("" if unknown)."""
        return self._ended.get(pid, "")

    def tell_ended(self, names: dict[int, str]) -> None:
        """Told by a probe: processes that ended since the last refresh, with their names as the
        kernel knew them (those that started and ended in between were never listed)."""
        for pid, name in names.items():
            self._ended.setdefault(pid, name)

    def cmdline(self, pid: int) -> list[str]:
        """The command line joined with spaces, as one string in a list ([] for a kernel thread)."""
        if pid not in self._cmdlines:
            try:
                with open(f"{self.proc}/{pid}/cmdline", "rb") as f:
                    raw = f.read(4096)
            except OSError:
                raw = b""
            if not raw:  # a kernel thread, or a process caught between fork and exec: ask again later
                return []
            self._cmdlines[pid] = [raw.replace(b"\0", b" ").decode(errors="replace").strip()]
        return self._cmdlines[pid]

    def pids(self) -> set[int]:
        return set(self._names)

    def socket_inodes(self, pid: int) -> set[int]:
        """Inodes of the sockets a process holds open."""
        inodes = set()
        fd_dir = f"{self.proc}/{pid}/fd"
        try:
            fds = os.listdir(fd_dir)
        except OSError:
            return inodes
        for fd in fds:
            try:
                target = os.readlink(f"{fd_dir}/{fd}")
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(int(target[8:-1]))
        return inodes


class MappedLibraries:
    """Which processes map which of some shared libraries (by file name prefix, e.g. "librcl.so"):
    the probes that follow a middleware find its processes, and the library files to put uprobes
    on, here.

    A process's memory map is read when the process is first listed, and again whenever the loads
    probe (drums.probes.loads) says it exec'd or loaded a library, from that probe's thread: a
    Python node maps librcl only when it imports rclpy, a second or more after it started. Each
    process found to map a library it did not map before is handed to every listener, under
    `lock`, before it can have used that library much."""

    def __init__(self, table: ProcessTable, prefixes: tuple[str, ...]):
        self.table = table
        self.prefixes = prefixes
        self.lock = threading.RLock()
        self.listeners: list[Callable[[int, dict[str, str]], None]] = []
        self._seen: dict[int, dict[str, str]] = {}  # pid -> {prefix: path as that process sees it}

    def refresh(self) -> None:
        """Read the maps of processes listed for the first time. Call after table.refresh()."""
        with self.lock:
            for pid in self.table.pids() - self._seen.keys():
                self._read(pid)
            for pid in [pid for pid in self._seen if not self.table.belongs(pid)]:
                del self._seen[pid]

    def look(self, pid: int) -> None:
        """Read the process's map again: it exec'd or loaded a library just now."""
        with self.lock:
            if self.table.belongs(pid):
                self._read(pid)

    def rescan(self) -> None:
        """Read every process's map again (when notices of loads were lost)."""
        with self.lock:
            for pid in self.table.listing():
                self.look(pid)

    def processes(self, prefixes: tuple[str, ...]) -> dict[int, dict[str, str]]:
        """The processes that map at least one of `prefixes`, with the paths of all they map."""
        with self.lock:
            return {pid: libs for pid, libs in self._seen.items() if any(p in libs for p in prefixes)}

    def _read(self, pid: int) -> None:
        libs = mapped_libraries(self.table.proc, pid, self.prefixes)
        if libs and comm(self.table.proc, pid).startswith(HELPER):
            libs = {}  # the agent's own ROS 2 helpers are not the robot's: their topics are not counted
        new = libs.keys() - self._seen.get(pid, {}).keys()
        self._seen[pid] = libs
        if new:
            for listener in self.listeners:
                listener(pid, libs)


def mapped_file(proc: str, pid: int, path: str) -> tuple[str, tuple[int, int]] | None:
    """A file the process maps, as this agent reaches it (through the process's root: in another
    mount namespace the path may name another file), and its identity (device, inode); None if
    the process is gone."""
    host_path = f"{proc}/{pid}/root{path}"
    try:
        st = os.stat(host_path)
    except OSError:
        return None
    return host_path, (st.st_dev, st.st_ino)


def mapped_libraries(proc: str, pid: int, prefixes: tuple[str, ...]) -> dict[str, str]:
    """{prefix: path} of the libraries the process maps whose file names start with a prefix."""
    try:
        with open(f"{proc}/{pid}/maps") as f:
            text = f.read()
    except OSError:
        return {}
    found = {}
    for prefix in prefixes:
        at = text.find("/" + prefix)  # most processes map none: one search each, no parsing
        if at >= 0:
            start = text.rfind(" ", 0, at) + 1
            found[prefix] = text[start:text.find("\n", at)]
    return found
