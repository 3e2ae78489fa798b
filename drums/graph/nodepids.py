"""Which process runs each ROS 2 node: ROS 2 has no node-to-PID API (ros2/ros2#600), so the PID
is inferred and every guess is checked against /proc.

In order:
1. "gid": Fast DDS writes the low 16 bits of the process id into bytes 4-5 of the GUID prefix that
   every endpoint GID of the node's participant starts with (vendor id 01.0f = eProsima). A guess
   counts only if a process with those low bits has librcl loaded; with several, none is taken.
2. "cmdline": a process started with `__node:=<name>` (and `__ns:=<namespace>` if not /).
3. "librcl": when exactly one process with librcl loaded is claimed by no node, the nodes still
   unmapped are in it.
A Fast DDS node whose GUID prefix names another host (bytes 2-3) is "remote": that host's agent
maps it; unless its PID bits are those of one process with librcl in our network namespace. Fast
DDS hashes every address of every interface into that host id, once per process: a process started
after an interface came or went (a VPN, a container bridge, a new DHCP lease) carries another id
than ours, though it runs beside us; one in another network namespace is another host. One of
this host whose process no longer runs is "gone": DDS forgets a participant that was killed only
when its lease runs out (20 s by default), /proc knows at once. So is one once mapped to a process
of ours that no longer runs, whatever host id it carries (a test lab's veths come and go), and one
placed by name (2, 3) before its endpoints were read, whose process no longer runs and which no
running process claims.
Other RMWs (Cyclone DDS, Connext, Zenoh) carry no PID in their GUIDs: their nodes go by 2 and 3.
"""
from __future__ import annotations

import os
from itertools import chain
from typing import Iterable

from drums.proctable import ProcessTable, mapped_libraries, netns, process_start

FASTDDS_VENDOR = b"\x01\x0f"
RCL_LIBRARY = "librcl.so"


def pid_bits_from_gid(gid: bytes) -> int | None:
    """The low 16 bits of the process id in a Fast DDS GUID prefix, None for other vendors."""
    if len(gid) >= 6 and gid[:2] == FASTDDS_VENDOR:
        return int.from_bytes(gid[4:6], "little")
    return None


class ProcScan:
    """What /proc says about processes, read once per process (start time keyed, so a reused PID
    is read again)."""

    def __init__(self, proc: str = "/proc"):
        self.proc = proc
        self.table = ProcessTable(proc)  # the listing and the names
        self._rcl: dict[tuple[int, int | None], bool] = {}
        self._cmdline: dict[tuple[int, int | None], list[str]] = {}
        # Participant GUID prefix -> (pid, start) of the process of ours it was mapped to.
        self.participants: dict[bytes, tuple[int, int | None]] = {}
        # Node -> (pid, start) of the process it was last placed in, for a node placed before its
        # participant was known (DDS tells a node's name before its endpoints).
        self.placed: dict[str, tuple[int, int | None]] = {}
        # The last mapping, what it was made of (the nodes with their prefixes, our own prefix) and
        # the start of each process it placed a node in, while every node in it was placed.
        self._settled: tuple[dict, bytes, dict, dict[int, int | None]] | None = None

    def settled(self, nodes: dict[str, bytes | None], own_prefix: bytes) -> dict | None:
        """The last mapping if it still holds without a look at every process: the same nodes with
        the same participants, each placed in a process that still runs, or remote."""
        last = self._settled
        if last is None or last[0] != nodes or last[1] != own_prefix:
            return None
        if any(process_start(self.proc, pid, running=True) != start for pid, start in last[3].items()):
            return None
        return dict(last[2])

    def settle(self, nodes: dict[str, bytes | None], own_prefix: bytes, mapping: dict) -> None:
        """Keep a mapping that placed every node (in a process by its GID or command line, or on
        another host) to be taken again while it holds; forget it otherwise."""
        placed = all(how in ("gid", "cmdline", "remote") for _, how in mapping.values())
        starts = {pid: process_start(self.proc, pid) for pid, _ in mapping.values() if pid is not None}
        self._settled = (dict(nodes), own_prefix, dict(mapping), starts) if placed else None

    def refresh(self) -> None:
        self.table.refresh()
        self._rcl = {k: v for k, v in self._rcl.items() if self.table.alive(k[0])}
        self._cmdline = {k: v for k, v in self._cmdline.items() if self.table.alive(k[0])}

    def pids(self) -> list[int]:
        return sorted(self.table.pids())

    def beside_us(self, pid: int) -> bool:
        """Whether the process shares our network namespace (has our interfaces)."""
        return netns(self.proc, pid) == netns(self.proc, "self")

    def name(self, pid: int) -> str:
        return self.table.name(pid)

    def has_rcl(self, pid: int, recheck: bool = False) -> bool:
        """Whether the process has librcl loaded. A no is kept too (a scan of every process asks),
        but `recheck` reads it again: a process asked while it still imported rclpy says no, and
        one whose participant the graph now shows has loaded it since."""
        key = (pid, process_start(self.proc, pid))
        if key not in self._rcl or (recheck and not self._rcl[key]):
            self._rcl[key] = bool(mapped_libraries(self.proc, pid, (RCL_LIBRARY,)))
        return self._rcl[key]

    def runs(self, pid: int, start: int | None) -> bool:
        """Whether the process that had this PID and start time still runs."""
        return self.table.alive(pid) and process_start(self.proc, pid) == start

    def remember(self, mapping: dict[str, tuple[int | None, str]], prefixes: dict[str, bytes | None],
                 listed: Iterable[bytes] = ()) -> None:
        """Keep which participants and processes the nodes seen now were mapped to, and forget the
        others; and those of the participants still `listed`."""
        seen = {prefix: self.participants.get(prefix) for prefix in chain(prefixes.values(), listed) if prefix}
        placed = {node: self.placed[node] for node in prefixes if node in self.placed}
        for node, (pid, how) in mapping.items():
            if pid is None:
                continue
            if placed.get(node, (None,))[0] != pid:
                placed[node] = (pid, process_start(self.proc, pid))
            prefix = prefixes[node]
            known = seen.get(prefix)
            if how in ("gid", "cmdline") and prefix and (known is None or known[0] != pid):  # not a "librcl" guess
                seen[prefix] = placed[node]
        self.participants = {prefix: owner for prefix, owner in seen.items() if owner is not None}
        self.placed = placed

    def left(self, node: str, bits: int | None = None) -> bool:
        """Whether the node was last placed in a process that no longer runs (whose PID has these
        low bits, when its participant's are known)."""
        where = self.placed.get(node)
        return where is not None and (bits is None or where[0] & 0xFFFF == bits) and not self.runs(*where)

    def left_participant(self, node: str, prefix: bytes) -> bool:
        """Whether the node's participant with this GUID prefix was in a process that no longer runs."""
        owner = self.participants.get(prefix)
        if owner is not None:
            return not self.runs(*owner)
        bits = pid_bits_from_gid(prefix)
        return bits is not None and self.left(node, bits)

    def cmdline(self, pid: int) -> list[str]:
        key = (pid, process_start(self.proc, pid))
        if key not in self._cmdline:
            try:
                with open(f"{self.proc}/{pid}/cmdline", "rb") as f:
                    self._cmdline[key] = f.read().decode(errors="replace").split("\0")
            except OSError:
                self._cmdline[key] = []
        return self._cmdline[key]


def _node_arg(args: list[str]) -> str | None:
    """The fully qualified node name a command line remaps to, if it does."""
    name = next((a.split(":=", 1)[1] for a in args if a.startswith("__node:=")), None)
    if name is None:
        return None
    ns = next((a.split(":=", 1)[1] for a in args if a.startswith("__ns:=")), "/")
    return f"{ns.rstrip('/')}/{name}"


def map_nodes(nodes: dict[str, bytes | None], scan: ProcScan, own_prefix: bytes = b"", listed: Iterable[bytes] = ()
              ) -> dict[str, tuple[int | None, str]]:
    """Fully qualified node name -> (pid, how), given each node's participant GUID prefix (None if
    it has no endpoint to read it from) and the prefix of our own participant: Fast DDS puts a
    host id in bytes 2-3, so a node whose host id differs from ours, and whose PID bits are those
    of no process with librcl in our network namespace, is "remote". `listed`: every participant
    DDS lists (a node's killed one beside its new one), whose owners are remembered. While the
    nodes and the processes they were placed in stay, /proc is not listed again (at a thousand
    processes a look took 0.8 ms, twice a second, in the reader's child)."""
    settled = scan.settled(nodes, own_prefix)
    if settled is not None:
        return settled
    scan.refresh()
    out: dict[str, tuple[int | None, str]] = {}
    by_bits: dict[int, list[int]] = {}
    for pid in scan.pids():
        by_bits.setdefault(pid & 0xFFFF, []).append(pid)
    know_host = pid_bits_from_gid(own_prefix) is not None
    for node, prefix in nodes.items():
        bits = pid_bits_from_gid(prefix) if prefix else None
        if bits is None:
            continue
        found = [pid for pid in by_bits.get(bits, ()) if scan.has_rcl(pid, recheck=True)]
        owner = scan.participants.get(prefix)
        if (not found and scan.left(node, bits)) or (
                owner is not None and owner[0] not in found and not scan.runs(*owner)):
            out[node] = (None, "gone")
            continue
        foreign = know_host and prefix[2:4] != own_prefix[2:4]
        if len(found) == 1 and (not foreign or scan.beside_us(found[0])):
            out[node] = (found[0], "gid")
        elif foreign:
            out[node] = (None, "remote")
        elif not found and know_host:
            out[node] = (None, "gone")
    unmapped = [n for n in nodes if n not in out]
    if unmapped:
        for pid in scan.pids():
            name = _node_arg(scan.cmdline(pid))
            if name in unmapped and scan.has_rcl(pid, recheck=True):
                out[name] = (pid, "cmdline")
        out.update((n, (None, "gone")) for n in nodes if n not in out and scan.left(n))
        unmapped = [n for n in nodes if n not in out]
    if unmapped:
        claimed = {pid for pid, _ in out.values()}
        free = [pid for pid in scan.pids() if pid not in claimed and pid != os.getpid() and scan.has_rcl(pid)]
        if len(free) == 1:
            out.update({n: (free[0], "librcl") for n in unmapped})
    for n in nodes:
        out.setdefault(n, (None, "unmapped"))
    scan.remember(out, nodes, listed)
    scan.settle(nodes, own_prefix, out)
    return out
