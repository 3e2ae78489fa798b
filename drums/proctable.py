"""The processes alive on this host, with their names: shared by probes, selection and budget.

Refreshed once per collect from one listing of /proc; a name is read only for a PID not seen in
the previous listing, so a process that exits and whose PID is reused gets its new name.

With $DRUMS_OWN_NETNS=1 (`drums agent --own-netns`, inherited by the graph reader the agent
starts) the table holds only the processes in this process's network namespace: where namespaces
or containers stand for hosts, one agent per namespace reports its own host and nothing else.
"""
from __future__ import annotations

import os

OWN_NETNS = "DRUMS_OWN_NETNS"


def netns(proc: str, pid: int | str) -> int | None:
    """The inode of a process's network namespace (None if it is gone or hidden)."""
    try:
        return os.stat(f"{proc}/{pid}/ns/net").st_ino
    except OSError:
        return None


class ProcessTable:
    def __init__(self, proc: str = "/proc"):
        self.proc = proc
        self.netns = netns(proc, "self") if os.environ.get(OWN_NETNS) == "1" else None
        self._names: dict[int, str] = {}
        self._elsewhere: set[int] = set()  # PIDs in other network namespaces, at the last listing

    def refresh(self) -> None:
        alive = {int(d) for d in os.listdir(self.proc) if d.isdigit()}
        if self.netns is not None:  # each PID is checked when it first appears, as its name is read
            self._elsewhere = {pid for pid in alive if pid in self._elsewhere or (
                pid not in self._names and netns(self.proc, pid) != self.netns)}
            alive -= self._elsewhere
        self._names = {pid: self._names.get(pid) or self._read_name(pid) for pid in alive}

    def _read_name(self, pid: int) -> str:
        try:
            with open(f"{self.proc}/{pid}/comm") as f:
                return f.read().rstrip("\n")
        except OSError:
            return ""

    def alive(self, pid: int) -> bool:
        return pid in self._names

    def name(self, pid: int) -> str:
        return self._names.get(pid, "")

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
    """Which processes map which of some shared libraries (by file name prefix, e.g. "librcl.so"),
    read from /proc/<pid>/maps once per process: the probes that follow a middleware find its
    processes and the library files to put uprobes on."""

    def __init__(self, table: ProcessTable, prefixes: tuple[str, ...]):
        self.table = table
        self.prefixes = prefixes
        self._seen: dict[int, dict[str, str]] = {}  # pid -> {prefix: path as that process sees it}

    def refresh(self) -> dict[int, dict[str, str]]:
        """Every live process that maps at least one of the libraries. Call after table.refresh()."""
        alive = self.table.pids()
        self._seen = {pid: self._seen[pid] if pid in self._seen else self._read(pid) for pid in alive}
        return {pid: libs for pid, libs in self._seen.items() if libs}

    def _read(self, pid: int) -> dict[str, str]:
        return mapped_libraries(self.table.proc, pid, self.prefixes)


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
