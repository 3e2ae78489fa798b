"""What the agent's own process tree costs: CPU and memory of the agent and of each helper process
it started (the ROS 2 graph reader, the /diagnostics publisher), by role."""
from __future__ import annotations

import ctypes
import importlib
import os
import sys
import time
import types

from drums.proctable import HELPER

AGENT = "agent"
_TICKS = os.sysconf("SC_CLK_TCK")
# glibc keeps in its heaps what the agent frees (the buffers of each scrape) and hands it back to
# the system only from their top: under churn the agent's USS crept by 0.5 MB a minute, nearly
# all of it given back by malloc_trim. At most this often (seconds), a sample of the tree trims
# first (a few milliseconds). And each thread that allocates would get a heap (arena) of its own,
# a MB or two more for each: the agent's threads share a few.
# A block of MMAP_THRESHOLD bytes or more (a scrape's larger map reads, its body) gets pages of its
# own, handed back when it is freed. glibc starts at 128 KiB and raises the threshold to the largest
# such block freed; the blocks under it then come from the heap and leave holes there. Measured at
# 1,000 processes (the agent with the ROS 2 graph, two or four runs each): fixed at 256 KiB, 61.0
# MB against 61.8-64.4 left to glibc, the collect unchanged (8.1-8.7 ms against 8.8); at 128 KiB,
# 60 MB but 1.3-3 ms more a collect, faulting in the pages of each mapped block.
TRIM_EVERY = 10.0
ARENAS = 2
MMAP_THRESHOLD = 256 * 1024
_M_ARENA_MAX, _M_MMAP_THRESHOLD = -8, -3  # mallopt's parameters, from glibc's malloc.h
# Reading smaps_rollup walks a process's page tables: a millisecond or more for the agent and for
# an rclpy helper. A process's memory moves with its work: each of the tree is read again once it
# has used BUSY seconds of CPU since it was last read (a helper loading its libraries), else at
# most every MEMORY_EVERY, as the process probe reads the processes it watches.
MEMORY_EVERY = 5.0
BUSY = 0.1


def leave_out(*modules: str) -> None:
    """Make each of these modules fail to import (ImportError), before anything imports it: for
    what this process never uses and what imports it copes without."""
    for name in modules:
        sys.modules.setdefault(name, None)


def without_openssl() -> None:
    """Leave OpenSSL out of this process, before anything imports it. The agent and its helpers
    speak no TLS, and each process that loads libcrypto holds 3-4 MB of it as its own memory: the
    agent did (aiohttp, its HTTP front then, built verified SSL contexts at import), and so did the
    ROS 2 graph reader (creating an rclpy node imports hashlib): 3.7 MB of its 58. Without the ssl
    module, asyncio and urllib leave TLS out; without _hashlib, hashlib takes Python's own hashes."""
    leave_out("ssl", "_hashlib")


class _OnFirstUse(types.ModuleType):
    """Stands in for a module in sys.modules: the first name looked up on it imports the module
    for real (which then takes its place) and is answered from there. Importing the stand-in
    executes nothing; its __spec__ is None, so `import` itself finds it complete."""

    def __getattr__(self, name: str):
        if sys.modules.get(self.__name__) is self:
            del sys.modules[self.__name__]
        return getattr(importlib.import_module(self.__name__), name)


def on_first_use(*modules: str) -> None:
    """Import each of these modules when something first uses one of its names, not when
    something imports it: for modules imported at the top of code that this process never runs."""
    for name in modules:
        sys.modules.setdefault(name, _OnFirstUse(name))


def _glibc():
    """The C library where it is glibc (with malloc_trim and mallopt), else None (musl)."""
    libc = ctypes.CDLL(None)
    return libc if hasattr(libc, "malloc_trim") and hasattr(libc, "mallopt") else None


class Heap:
    """Keeps a long-running process's heap lean (glibc only; elsewhere it does nothing): its threads
    share ARENAS arenas (made before they start), blocks of MMAP_THRESHOLD bytes or more are mapped
    apart, and `trim()` gives the heaps' free pages back at most every TRIM_EVERY seconds. The agent
    and `drums detect` use it."""

    def __init__(self):
        self._libc = _glibc()
        if self._libc is not None:
            self._libc.mallopt(_M_ARENA_MAX, ARENAS)
            self._libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
        self._trimmed_at = time.monotonic()
        self.trim_every = TRIM_EVERY

    def trim(self) -> None:
        if self._libc is not None and time.monotonic() - self._trimmed_at >= self.trim_every:
            self._libc.malloc_trim(0)
            self._trimmed_at = time.monotonic()


def memory(pid: int | str = "self") -> tuple[int, int]:
    """(RSS, USS) of a process in bytes, from smaps_rollup; zeros if it is gone."""
    rss = uss = 0
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                key, _, rest = line.partition(":")
                if key == "Rss":
                    rss = int(rest.split()[0]) * 1024
                elif key in ("Private_Clean", "Private_Dirty"):
                    uss += int(rest.split()[0]) * 1024
    except (OSError, ValueError):
        pass
    return rss, uss


def _cpu_and_role(pid: int) -> tuple[float, str] | None:
    """(CPU seconds, role) of a child, None if it is gone. A helper names itself drums-<role>."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    comm = stat[stat.index(b"(") + 1:stat.rindex(b")")].decode(errors="replace")
    fields = stat.rsplit(b")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICKS, comm.removeprefix(HELPER)


def _children() -> list[int]:
    pids = []
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/children") as f:
                pids += [int(p) for p in f.read().split()]
        except (OSError, ValueError):
            pass
    return pids


class TreeCost:
    """CPU seconds (a counter per role that never goes backwards: a helper that is restarted adds
    to what the one before it used), resident and unique memory of the agent and its children."""

    def __init__(self):
        self._last: dict[int, tuple[str, float]] = {}  # child pid -> (role, CPU seconds) when last seen
        self._ended: dict[str, float] = {}  # role -> CPU seconds of its children that ended
        self._heap = Heap()  # made before the agent starts its threads
        # pid ("self": the agent) -> (when read, its CPU seconds then, (RSS, USS))
        self._memory: dict[int | str, tuple[float, float, tuple[int, int]]] = {}

    def _memory_of(self, pid: int | str, now: float, cpu: float) -> tuple[int, int]:
        read_at, cpu_then, rss_uss = self._memory.get(pid, (float("-inf"), 0.0, (0, 0)))
        if now - read_at >= MEMORY_EVERY or cpu - cpu_then >= BUSY:
            read_at, cpu_then, rss_uss = now, cpu, memory(pid)
        self._memory[pid] = read_at, cpu_then, rss_uss
        return rss_uss

    def sample(self) -> dict[str, tuple[float, int, int]]:
        """role -> (CPU seconds, RSS, USS)."""
        self._heap.trim()
        now, times = time.monotonic(), os.times()
        cpu = times.user + times.system
        rss, uss = self._memory_of("self", now, cpu)
        out = {AGENT: [cpu, rss, uss]}
        seen = {}
        for pid in _children():
            got = _cpu_and_role(pid)
            if got is None:
                continue
            cpu, role = got
            seen[pid] = (role, cpu)
            rss, uss = self._memory_of(pid, now, cpu)
            row = out.setdefault(role, [0.0, 0, 0])
            row[0] += cpu
            row[1] += rss
            row[2] += uss
        for pid in self._last.keys() - seen.keys():
            role, cpu = self._last[pid]
            self._ended[role] = self._ended.get(role, 0.0) + cpu
        self._last = seen
        for pid in self._memory.keys() - seen.keys() - {"self"}:
            del self._memory[pid]
        for role, cpu in self._ended.items():
            out.setdefault(role, [0.0, 0, 0])[0] += cpu
        return {role: tuple(row) for role, row in out.items()}
