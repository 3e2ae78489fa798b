"""The processes alive on this host, with their names: shared by probes, selection and budget.

Refreshed once per collect from one listing of /proc; a name is read only for a PID not seen in
the previous listing, so a process that exits and whose PID is reused gets its new name.
"""
from __future__ import annotations

import os


class ProcessTable:
    def __init__(self, proc: str = "/proc"):
        self.proc = proc
        self._names: dict[int, str] = {}

    def refresh(self) -> None:
        alive = {int(d) for d in os.listdir(self.proc) if d.isdigit()}
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
