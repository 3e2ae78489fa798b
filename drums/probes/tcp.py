"""TCP health per connection: retransmits, resets and state changes counted by bpf/tcp.bpf.c,
and the smoothed RTT the kernel keeps per connection, read with sock_diag at each collect.

The kernel keeps RTT itself (tcp_info), so nothing runs per packet to learn it. Host totals live
in a map that is never pruned, so they survive the connections that produced them.
"""
from __future__ import annotations

import socket
import struct
import time
from sys import intern

import numpy as np

from drums.errors import KernelError
from drums.kernel import sockdiag
from drums.kernel.bpffs import sum_percpu
from drums.kernel.btf import Btf
from drums.metrics import COUNTER, GAUGE, Columns, Metric, Snapshot
from drums.netfmt import endpoint, parse_endpoint
from drums.probes.base import Probe
from drums.probes.bpf import (DROPPED, SOCK_ENDPOINT_FIELDS, AttachPath, BpfProbe, change_marks, needs_tracepoints,
                              offset_defines)
from drums.probes.entries import Entries, Matched, Remembered

CONN_LABELS = ("local", "remote", "netns")
CONN_RETRANSMITS = Metric("drums_tcp_connection_retransmits_total", COUNTER,
                          "Segments this connection retransmitted, as the kernel counts them (tcpi_total_retrans)",
                          CONN_LABELS)
CONN_RESETS_SENT = Metric("drums_tcp_connection_resets_sent_total", COUNTER,
                          "Resets this connection sent", CONN_LABELS)
CONN_RESETS_RECEIVED = Metric("drums_tcp_connection_resets_received_total", COUNTER,
                              "Resets this connection received", CONN_LABELS)
CONN_STATE_CHANGES = Metric("drums_tcp_connection_state_changes_total", COUNTER,
                            "TCP state transitions of this connection", CONN_LABELS)
CONN_RTT = Metric("drums_tcp_connection_smoothed_rtt_seconds", GAUGE,
                  "The kernel's smoothed round-trip time of this connection (tcp_info), for "
                  "established connections of the agent's network namespace, sampled every 5 s",
                  ("local", "remote"), additive=False)
# The per-connection counters, in the order of the map value's counts.
CONN_GROUP = (CONN_RETRANSMITS, CONN_STATE_CHANGES, CONN_RESETS_SENT, CONN_RESETS_RECEIVED)
RETRANSMITS = Metric("drums_tcp_retransmits_total", COUNTER,
                     "TCP segments retransmitted on this host, a listener's SYN-ACKs among them (as nstat's TcpRetransSegs)")
RESETS_SENT = Metric("drums_tcp_resets_sent_total", COUNTER, "TCP resets sent by this host")
RESETS_RECEIVED = Metric("drums_tcp_resets_received_total", COUNTER,
                         "TCP resets received by connections of this host")
STATE_ENTERED = Metric("drums_tcp_state_transitions_total", COUNTER,
                       "TCP connections entering each state", ("state",))

_CONN_HEAD = struct.Struct("<IHHHH16s16s4x")  # what names a connection (and its state)
_CONN_VALUE = struct.Struct(_CONN_HEAD.format + "4QQ")  # then what it counted, and the generation marked in
_HEAD_WORDS = _CONN_HEAD.size // 8
_COUNT_WORDS = _HEAD_WORDS + 4  # the end of the counts
_STATE_WORD, _STATE_SHIFT = 1, 16  # the state's 8-byte word and bit offset in a value
ESTABLISHED, TCP_CLOSE = 1, 7
# Reading tcp_info costs a netlink round trip per connection (a dump of every established one,
# about 17 ms per 1,000), so RTT is sampled at this interval (seconds) rather than at every scrape.
RTT_INTERVAL = 5.0
_TOTALS_FMT = "<16Q"
_U64 = struct.Struct("<Q")
EVENTS = ("inet_sock_set_state", "tcp_retransmit_skb", "tcp_retransmit_synack", "tcp_send_reset", "tcp_receive_reset")
# What names a connection in its head's words: all but its state and the padding at the end.
_NAME_MASK = np.full(_HEAD_WORDS, ~np.uint64(0), np.uint64)
_NAME_MASK[_STATE_WORD] = ~np.uint64(0xFFFF << _STATE_SHIFT)
_NAME_MASK[-1] = np.uint64(0xFFFFFFFF)


def _ports(heads: np.ndarray) -> np.ndarray:
    """Each connection's local port << 16 | remote port, from the words of its head."""
    return ((heads[:, 0] >> 48) << 16 | (heads[:, 1] & 0xFFFF)).astype(np.int64)


def connection_ids(heads: np.ndarray) -> np.ndarray:
    """An int64 per connection from the words of its head: its addresses, ports and network
    namespace mixed (the rounds of splitmix64), so that the connections a series is named by are
    one id. Two of ten thousand differ in a few bits; the chance that two names share an id is
    about 3e-12."""
    h = np.full(len(heads), 0x9E3779B97F4A7C15, np.uint64)
    for j in range(_HEAD_WORDS):
        h ^= heads[:, j] & _NAME_MASK[j]
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    return h.view(np.int64)


def merged(ids: np.ndarray, counts: np.ndarray, closed: np.ndarray, carried: dict[int, np.ndarray]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[int, np.ndarray]]:
    """A connection's series is named by its addresses, which a later connection can reuse while
    the kernel still holds the earlier one: rows of one id are one series, their counts summed.
    A closed connection is exported once, with the reset that closed it, then forgotten. What it
    counted stays in its series while a connection with its addresses is in the next collect (a
    client that reconnects from its port at once): a series missing from a scrape is a new one to
    Prometheus anyway, and so no more counts are carried than connections were collected.
    `carried`: id -> what the connections with it that closed at the last collect had counted.
    (ids, counts, where each id's row came from or None when nothing was summed, what the next
    collect carries.)"""
    if not closed.any() and not carried:
        return ids, counts, None, {}
    unique, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
    sums = np.zeros((len(unique), counts.shape[1]), np.int64)
    np.add.at(sums, inverse, counts)
    kept = {}
    for id_, at in zip(carried, np.searchsorted(unique, list(carried)).tolist()):
        if at < len(unique) and unique[at] == id_:
            sums[at] += carried[id_]
            kept[id_] = carried[id_]
    for i in np.flatnonzero(closed).tolist():
        id_ = int(ids[i])
        kept[id_] = kept[id_] + counts[i] if id_ in kept else counts[i].copy()
    return unique, sums, first, kept


class _Labels:
    """The label values of connections, made from the words of their heads when the budget or a
    reader of the snapshot asks for them (of ten thousand connections, the hundred it keeps).
    What the last collect's asked for are taken again, by the words that name the connection."""

    def __init__(self, heads: np.ndarray, remembered: Remembered):
        self.heads, self.remembered = heads, remembered

    def __call__(self, at: list[int]) -> list[tuple[str, ...]]:
        return [self.remembered.get(key, None, lambda: _connection_labels(key))
                for key in map(bytes, self.heads[at, :_HEAD_WORDS] & _NAME_MASK)]


def _connection_labels(head: bytes) -> tuple[str, str, str]:
    netns, family, lport, rport, _state, laddr, raddr = _CONN_HEAD.unpack(head)
    # Interned: as the sockets probe's labels, one string each
    return intern(endpoint(family, laddr, lport)), intern(endpoint(family, raddr, rport)), intern(str(netns))


class TcpProbe(BpfProbe):
    name = "tcp"
    source = "tcp.bpf.c"
    maps = {"tcp_conns": (_U64, _CONN_VALUE), "tcp_totals": (4, struct.calcsize(_TOTALS_FMT)),
            **change_marks(_U64), **DROPPED}
    metrics = (CONN_RETRANSMITS, CONN_RESETS_SENT, CONN_RESETS_RECEIVED, CONN_STATE_CHANGES, CONN_RTT, RETRANSMITS, RESETS_SENT,
               RESETS_RECEIVED, STATE_ENTERED)
    paths = (
        AttachPath("raw_tracepoint",
                   tuple(("raw_tracepoint", e, f) for e, f in zip(
                       EVENTS, ("on_state", "on_retransmit", "on_retransmit_synack", "on_send_reset",
                                "on_receive_reset"))),
                   needs_tracepoints(*EVENTS),
                   "Linux >= 5.7 (raw tracepoint links; tcp_send_reset and tcp_receive_reset since 5.5)"),
    )

    def __init__(self, features, rtt_interval: float = RTT_INTERVAL, **kw):
        super().__init__(features, **kw)
        self.rtt_interval = rtt_interval
        self._rtt: list = []
        self._rtt_at = float("-inf")
        self._carried: dict[int, np.ndarray] = {}  # connection id -> what closed connections with it counted
        self._entries = Entries(_CONN_VALUE.size, _CONN_HEAD.size)
        self._labelled = Remembered()  # the labels the last collect's connections were asked for
        self._wanted: set[tuple[str, str]] | None = None
        # The entries' keys at the last collect, with each connection's id and ports
        self._identity = (np.empty(0, np.uint64), np.empty(0, np.int64), np.empty(0, np.int64))

    def _identities(self, m: Matched) -> tuple[np.ndarray, np.ndarray]:
        """Each entry's connection id and its ports (local << 16 | remote): where the entries are
        those of the last collect (the same keys array: no connection came or went), made again only
        for those whose head changed; of ten thousand idle connections, none."""
        keys, ids, ports = self._identity
        if m.keys is not keys:
            heads = m.words[:, :_HEAD_WORDS]
            ids, ports = connection_ids(heads), _ports(heads)
        elif not m.same_head.all():  # new arrays: the budget keeps the ids it was given last
            fresh = np.flatnonzero(~m.same_head)
            ids, ports = ids.copy(), ports.copy()
            ids[fresh], ports[fresh] = connection_ids(m.words[fresh, :_HEAD_WORDS]), _ports(m.words[fresh])
        self._identity = m.keys, ids, ports
        return ids, ports

    def want_rtt(self, connections: set[tuple[str, str]]) -> None:
        """Read RTT for these (local, remote) connections only (the agent's: those with series of
        their own, and the graph's edges), not for every established one. One not read yet is
        read at the next collect, not after the interval."""
        if self._wanted is None or not connections <= self._wanted:
            self._rtt_at = float("-inf")
        self._wanted = connections

    def offsets(self, btf: Btf) -> dict[str, int]:
        d = {"RETRANSMIT_HAS_ERR": 1} if len(btf.tracepoint_args("tcp_retransmit_skb") or ()) >= 3 else {}
        return d | offset_defines(btf, {**SOCK_ENDPOINT_FIELDS,
            "SK_PROTOCOL_OFF": ("sock", "sk_protocol"),
            "TP_TOTAL_RETRANS_OFF": ("tcp_sock", "total_retrans"),
        })

    def collect(self, snap: Snapshot) -> None:
        """The connections are handed on as arrays (Columns): of ten thousand, the budget asks the
        labels of the hundred it keeps, and the rest hold no Python object each."""
        m = self.read_marked("tcp_conns", self._entries)
        words = m.words
        closed = (words[:, _STATE_WORD] >> _STATE_SHIFT & 0xFFFF) == TCP_CLOSE
        ids, ports = self._identities(m)
        ids, counts, first, self._carried = merged(
            ids, words[:, _HEAD_WORDS:_COUNT_WORDS].view(np.int64), closed, self._carried)
        # The entries' own arrays as a rule (no connection closed, none summed): the next collect
        # writes over them in place, so what a reader keeps of the columns it copies.
        heads, ports = (words, ports) if first is None else (words[first], ports[first])
        snap.groups[CONN_GROUP] = Columns(ids, counts, np.zeros(len(ids), np.intp), ("",), None,
                                          _Labels(heads, self._labelled.turn()), ports,
                                          stamps=lambda at: heads[at, :_HEAD_WORDS] & _NAME_MASK,
                                          told=m.told() if first is None else None)
        if closed.any():
            self.opened["tcp_conns"].delete_unchanged(  # one that changed instead comes back marked
                [(_U64.pack(k), w.tobytes()) for k, w in zip(m.keys[closed].tolist(), words[closed])])
        self._entries.keep(m, ~closed)  # one not deleted (it counted on meanwhile) comes back as new
        _, values, _ = self.read("tcp_totals")
        totals = sum_percpu(values, _TOTALS_FMT, self.opened["tcp_totals"].ncpus)[0]
        snap.add(RETRANSMITS, (), totals[0])
        snap.add(RESETS_SENT, (), totals[1])
        snap.add(RESETS_RECEIVED, (), totals[2])
        for state, name in sockdiag.TCP_STATES.items():
            snap.add(STATE_ENTERED, (name.lower(),), totals[3 + state])
        now = time.monotonic()
        if now - self._rtt_at >= self.rtt_interval:
            try:
                self._rtt = self._read_rtt()
                self.status.reason = ""
            except KernelError as e:
                self._rtt = []
                self.status.reason = f"no RTT: {e}"
            self._rtt_at = now
        for labels, rtt in self._rtt:
            snap.add(CONN_RTT, labels, rtt)
        self.read_dropped()

    def transitions(self) -> int:
        """TCP state changes on the host (every network namespace's) since the programs were loaded:
        while this holds still, no connection or listener came or went. A read of its own, safe
        beside a collect in another thread."""
        _, values, _ = self.opened["tcp_totals"].read()
        return sum(sum_percpu(values, _TOTALS_FMT, self.opened["tcp_totals"].ncpus)[0][3:])

    def _read_rtt(self) -> list[tuple[tuple[str, str], float]]:
        if self._wanted is None:
            return [((local, remote), c.srtt_us / 1e6) for c, local, remote in established()]
        wanted = [(pair, parse_endpoint(pair[0]), parse_endpoint(pair[1])) for pair in self._wanted]
        wanted = [(pair, local, remote) for pair, local, remote in wanted if local and remote]
        found = sockdiag.lookup_tcp([(local, remote) for _, local, remote in wanted])
        return [(pair, c.srtt_us / 1e6) for (pair, _, _), c in zip(wanted, found)
                if c is not None and c.state == ESTABLISHED]



def established():
    """(connection, local, remote) of the established TCP connections in this network namespace."""
    for c in sockdiag.dump_tcp(1 << 1):
        local = endpoint(c.family, socket.inet_pton(c.family, c.local_address), c.local_port)
        remote = endpoint(c.family, socket.inet_pton(c.family, c.remote_address), c.remote_port)
        yield c, local, remote


def parse_snmp_tcp(text: str) -> dict[str, int]:
    """The Tcp: counters of /proc/net/snmp (a header line of names, then a line of values)."""
    lines = [line.split()[1:] for line in text.splitlines() if line.startswith("Tcp:")]
    if len(lines) < 2 or len(lines[0]) != len(lines[1]):
        return {}
    try:
        return {name: int(value) for name, value in zip(lines[0], lines[1])}
    except ValueError:
        return {}


class SockDiagTcpProbe(Probe):
    """Without eBPF: RTT and retransmits of open connections from tcp_info, host counters from
    /proc/net/snmp. Resets and state changes per connection, and closed connections, are lost."""

    name = "tcp"
    metrics = (CONN_RETRANSMITS, CONN_RTT, RETRANSMITS, RESETS_SENT)

    def __init__(self, snmp: str = "/proc/net/snmp"):
        super().__init__()
        self.snmp = snmp
        self.netns = ""

    def start(self) -> None:
        sockdiag.dump_tcp(1 << 1)  # fails here, not at each collect, where netlink is missing
        self.netns = sockdiag.own_netns()
        self.status.attached = True
        self.status.attach_type = "sock_diag"
        self.status.reason = ("open connections of the agent's network namespace only; no resets or "
                              "state changes per connection")

    def collect(self, snap: Snapshot) -> None:
        for c, local, remote in established():
            snap.add(CONN_RTT, (local, remote), c.srtt_us / 1e6)
            snap.add(CONN_RETRANSMITS, (local, remote, self.netns), c.total_retrans)
        try:
            with open(self.snmp) as f:
                counters = parse_snmp_tcp(f.read())
        except OSError:
            counters = {}
        if "RetransSegs" in counters:
            snap.add(RETRANSMITS, (), counters["RetransSegs"])
        if "OutRsts" in counters:
            snap.add(RESETS_SENT, (), counters["OutRsts"])
