"""The graph without middleware: the processes of this host and their TCP connections, like a
service map. A process with a listening or connected TCP socket is a node (`/<name>/<pid>`);
each connection is an edge from the connecting process to the listening one, keyed by the
service port (`tcp:<port>`). A peer on another host is a node named by its address, with no
process. UDP and unix sockets carry no direction, so they are not edges here.
"""
from __future__ import annotations

import socket
import time
from itertools import chain
from typing import Callable

import numpy as np

from drums.arrays import among, distinct, distinct_rows, within
from drums.errors import GraphError, KernelError
from drums.graph.adapter import Adapter
from drums.graph.model import Connection, GraphState, Host, Node, Process
from drums.graph.nodepids import ProcScan
from drums.kernel import sockdiag

ESTABLISHED, LISTEN = 1, 10
# Seconds between re-reads of the open files of the processes that ran since their last read (a
# socket handed to another process keeps its inode: only a re-read tells its new holder), and
# between reads of every process's, whatever the sched probe says (it may lose events).
OWNERS_REREAD, OWNERS_FULL = 60.0, 600.0
# What names the edge of a connection's end: its process, the address it talks to, and the port
# of the service (its peer's, or its own where it accepted the connection).
_END = np.dtype({"names": ["pid", "address", "family", "port", "accepting"],
                 "formats": ["<i8", "V16", "u1", "<u2", "?"], "offsets": [0, 8, 24, 26, 28], "itemsize": 32})
_ADDRESS = np.dtype({"names": ["src", "family"], "formats": ["V16", "u1"], "offsets": [0, 16], "itemsize": 24})


def _endpoint(address: str, port: int) -> str:
    return f"[{address}]:{port}" if ":" in address else f"{address}:{port}"


def _words(records: np.ndarray) -> np.ndarray:
    """Records as rows of 8-byte words, to be compared and sorted as integers."""
    return np.ascontiguousarray(records).view(np.uint64).reshape(len(records), records.itemsize // 8)


def _address(family: int, raw: bytes) -> str:
    return socket.inet_ntop(family, raw[:4] if family == socket.AF_INET else raw)


class AutoAdapter(Adapter):
    name = "auto"
    interval = 5.0  # reading every process's open files costs a readlink per file

    def __init__(self, proc: str = "/proc", tcp_changes: Callable[[], int | None] | None = None,
                 ran: Callable[[], dict[int, float] | None] | None = None):
        """`tcp_changes`: a count that moves whenever a TCP socket of the host changes state (the
        tcp probe's; None when it cannot say). While it holds still, the connections and listeners
        are those of the last dump: a poll dumps them again (10,000 sockets: 40 ms) only when it
        moved, when a process of the graph ended, or at least every OWNERS_REREAD seconds.
        `ran`: each process's CPU seconds as the sched probe last counted them (None when it cannot
        say): a process whose count has not moved has not run, so holds the sockets it held."""
        self.scan = ProcScan(proc)
        self.tcp_changes, self.ran = tcp_changes, ran
        self._dumped: tuple[int | None, float, GraphState] | None = None  # (changes, when, state)
        empty = np.empty(0, np.int64)
        # From the last reading of each process's open files: its socket inodes, with the PID
        # holding each; the processes read, ascending, with their CPU seconds then (NaN: unknown);
        # the inodes no process held.
        self._held = (empty, empty)
        self._read_pids, self._read_cpu = empty, np.empty(0)
        self._unowned = empty
        self._read_at = self._full_at = float("-inf")

    def hear_from(self, tcp_changes, ran) -> None:
        self.tcp_changes, self.ran = tcp_changes, ran

    def _read_owners(self, everyone: bool) -> bool:
        """Read the open files of every process that may hold other sockets than at its last read:
        one not read before, or that ran since (the sched probe says), or every one when the probe
        cannot say or `everyone` (then True). A host of a thousand idle processes with ten thousand
        sockets costs a readlink per file otherwise (150 ms)."""
        table = self.scan.table
        told = self.ran() if self.ran else None
        alive = np.array(sorted(table.pids()), np.int64)
        cpu = np.full(len(alive), np.nan)  # NaN equals nothing: read again next time
        if told is not None:
            cpu[:] = np.fromiter((told.get(pid, 0.0) for pid in alive.tolist()), np.float64, len(alive))
        last = np.full(len(alive), np.nan)
        known = within(alive, self._read_pids)
        last[known] = self._read_cpu[np.searchsorted(self._read_pids, alive[known])]
        everyone = everyone or told is None
        again = alive if everyone else alive[last != cpu]
        inodes, pids = self._held
        keep = within(pids, alive) & ~within(pids, again)
        read = [(pid, table.socket_inodes(pid)) for pid in again.tolist()]
        inodes = np.concatenate([inodes[keep], np.fromiter(chain.from_iterable(i for _, i in read), np.int64)])
        pids = np.concatenate([pids[keep], np.repeat(again, [len(i) for _, i in read])])
        self._held, self._read_pids, self._read_cpu = (inodes, pids), alive, cpu
        return everyone

    def _holders(self) -> tuple[np.ndarray, np.ndarray]:
        """Socket inodes, ascending, and the PID holding each (one, where several do), of the
        processes alive."""
        inodes, pids = self._held
        live = among(pids, [pid for pid in distinct(pids).tolist() if self.scan.table.alive(pid)])
        inodes, pids = inodes[live], pids[live]
        first = distinct_rows(inodes[:, None])
        return inodes[first], pids[first]

    def _owners_of(self, inodes: np.ndarray) -> np.ndarray:
        """The PID holding each of these socket inodes (-1: none known). Open files are read when
        a socket is new since the last reading, and at least every OWNERS_REREAD seconds: on a
        host whose connections stay, rarely, and then those of the processes that ran."""
        held, pids = self._holders()
        wanted = np.unique(inodes[inodes != 0], return_counts=True)[0]  # with counts: see arrays.distinct
        now = time.monotonic()
        unknown = ~within(wanted, held) & ~within(wanted, self._unowned)
        if unknown.any() or now - self._read_at >= OWNERS_REREAD:
            everyone = self._read_owners(now - self._full_at >= OWNERS_FULL)
            # A new socket's holder ran as it opened it, though maybe after the sched probe's last
            # count: one still without a holder is looked for in every process.
            held, pids = self._holders()
            if not everyone and (unknown & ~within(wanted, held)).any():
                everyone = self._read_owners(True)
                held, pids = self._holders()
            self._unowned = wanted[~within(wanted, held)]
            self._read_at = now
            self._full_at = now if everyone else self._full_at
        else:
            self._unowned = self._unowned[within(self._unowned, wanted)]
        if not len(held):
            return np.full(len(inodes), -1, np.int64)
        at = np.minimum(np.searchsorted(held, inodes), len(held) - 1)
        return np.where(held[at] == inodes, pids[at], -1)

    def _changes(self) -> int | None:
        try:
            return self.tcp_changes() if self.tcp_changes else None
        except Exception:  # noqa: BLE001 - a probe stopped or failing: the poll dumps, as without one
            return None

    def poll(self) -> GraphState:
        changes = self._changes()
        self.scan.refresh()
        if self._dumped is not None and changes is not None:
            was, at, state = self._dumped
            alive = self.scan.table.alive
            if changes == was and time.monotonic() - at < OWNERS_REREAD and all(
                    p.pid is None or alive(p.pid) for p in state.processes):
                return state
        state = self._dump()
        self._dumped = (changes, time.monotonic(), state)
        return state

    def _dump(self) -> GraphState:
        """The graph of one dump. Ten thousand connections between a few processes make a few
        edges: each end is reduced to what names its edge (a client end: its process and the
        address and port it connects to; an accepting end: its process, port and peer's address),
        and only the distinct ones are looked at one by one."""
        try:
            table = sockdiag.dump_tcp_table((1 << ESTABLISHED) | (1 << LISTEN))
        except KernelError as e:
            raise GraphError(str(e)) from None
        addresses = np.zeros(len(table), _ADDRESS)  # this host's, as its sockets' local ones say
        addresses["src"], addresses["family"] = table["src"], table["family"]
        addresses = addresses[distinct_rows(_words(addresses))]
        local = {_address(f, bytes(a)) for f, a in zip(addresses["family"].tolist(), addresses["src"].tolist())}
        local |= {"127.0.0.1", "::1", "0.0.0.0", "::"}
        pid = self._owners_of(table["inode"].astype(np.int64))
        owned = pid >= 0
        table, pid = table[owned], pid[owned]
        host = socket.gethostname()
        listeners: dict[int, int] = {}  # port -> pid (any address)
        listening = table["state"] == LISTEN
        for port, p in zip(table["sport"][listening].tolist(), pid[listening].tolist()):
            listeners.setdefault(port, p)
        ends = np.zeros(len(table), _END)  # zeros: the padding compares equal
        ends["pid"], ends["family"], ends["address"] = pid, table["family"], table["dst"]
        established = table["state"] == ESTABLISHED
        listener = np.full(1 << 16, -1, np.int64)
        listener[list(listeners)] = list(listeners.values())
        accepting = established & (listener[table["sport"]] == pid)
        ends["port"] = np.where(accepting, table["sport"], table["dport"])
        ends["accepting"] = accepting
        names = {p: f"/{self.scan.name(p) or 'process'}/{p}" for p in distinct(pid).tolist()}
        edges, remote_nodes = set(), set()
        ends = ends[established]
        for end in ends[distinct_rows(_words(ends))].tolist():
            p, raw, family, port, accepts = end
            address = _address(family, bytes(raw))
            if accepts:  # its client is on another host, or seen as it connects
                if address not in local:
                    peer = f"/remote/{address}"
                    remote_nodes.add(peer)
                    edges.add((peer, names[p], f"tcp:{port}"))
                continue
            if address in local and port in listeners:
                target = names[listeners[port]]
            else:
                target = f"/remote/{_endpoint(address, port)}"
                remote_nodes.add(target)
            edges.add((names[p], target, f"tcp:{port}"))
        state = GraphState(hosts=[Host(host)])
        state.processes = [Process(host, p, self.scan.name(p)) for p in sorted(names)]
        state.nodes = [Node(name, host, p, "process") for p, name in sorted(names.items())]
        state.nodes += [Node(name, "", None, "remote") for name in sorted(remote_nodes)]
        state.connections = [Connection(topic, u, v, "tcp") for (u, v, topic) in sorted(edges)]
        return state
