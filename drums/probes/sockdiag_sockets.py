"""Bytes sent and received per TCP connection from sock_diag (what `ss -ti` reads), for when the BPF
sockets probe cannot load. It exports the same per-socket declarations as drums.probes.sockets,
for the processes the agent passes to set_pids().
"""
from __future__ import annotations

import socket
from typing import Iterable

from drums.kernel.sockdiag import TCP_STATES, TcpConnection, dump_tcp, own_netns
from drums.metrics import Snapshot
from drums.netfmt import endpoint
from drums.probes.base import Probe, ProbeStatus
from drums.probes.sockets import SOCKET
from drums.proctable import ProcessTable

_STATE = {name: number for number, name in TCP_STATES.items()}
# Connections that carry or have carried data and still have an owner's inode and a tcp_info.
# TIME_WAIT sockets have neither; LISTEN sockets are read only to tell which end connected.
CONNECTED = tuple(_STATE[s] for s in ("ESTABLISHED", "FIN_WAIT1", "FIN_WAIT2", "CLOSE_WAIT", "LAST_ACK", "CLOSING"))
LISTEN = _STATE["LISTEN"]
_OUR_FIN_ACKED = {_STATE["FIN_WAIT2"]}
_THEIR_FIN_RECEIVED = {_STATE[s] for s in ("CLOSE_WAIT", "LAST_ACK", "CLOSING")}
_ANY = {socket.AF_INET: "0.0.0.0", socket.AF_INET6: "::"}

REASON = ("TCP only; no UDP or unix; no call counts or errors; no per-process or per-thread totals, "
          "since closed connections are not kept; sent bytes are bytes the peer acknowledged; "
          "connections in other network namespaces are not seen")


def application_bytes(conn: TcpConnection, connected: bool) -> tuple[int, int]:
    """(sent, received) data bytes of a connection, from tcp_info's sequence-space counts.

    tcpi_bytes_acked counts the connecting end's SYN and our FIN once acknowledged, and
    tcpi_bytes_received counts the peer's FIN: take those out. Sent is then what the application
    wrote and the peer acknowledged, never a retransmit twice (tcpi_bytes_sent counts those); it
    trails what the application wrote by what is still queued or in flight.
    """
    sent = conn.bytes_acked - int(connected) - int(conn.state in _OUR_FIN_ACKED)
    received = conn.bytes_received - int(conn.state in _THEIR_FIN_RECEIVED)
    return max(sent, 0), max(received, 0)


def _label(conn: TcpConnection, address: str, port: int) -> str:
    # The BPF probe's format, so series match whichever probe is loaded: [::1]:80, and
    # v4-mapped IPv6 shown as IPv4.
    return endpoint(conn.family, socket.inet_pton(conn.family, address), port)


class SockDiagSocketsProbe(Probe):
    name = "sockets"
    metrics = (SOCKET["sent_bytes"], SOCKET["received_bytes"])

    def __init__(self, proctable: ProcessTable):
        super().__init__()
        self.proctable = proctable
        self._pids: frozenset[int] = frozenset()
        self._connected: dict[int, bool] = {}  # socket cookie -> this end sent the SYN
        self._netns = ""

    def start(self) -> None:
        dump_tcp(1 << LISTEN)  # raises KernelError, with the reason, if sock_diag is unusable
        self._netns = own_netns()
        self.status = ProbeStatus(attached=True, attach_type="sock_diag", reason=REASON)

    def set_pids(self, pids: Iterable[int]) -> None:
        self._pids = frozenset(pids)

    def collect(self, snap: Snapshot) -> None:
        pt = self.proctable
        conns = dump_tcp(sum(1 << s for s in CONNECTED + (LISTEN,)))
        owner: dict[int, int] = {}
        # A socket shared by several processes (inherited across fork) goes to the lowest PID, so
        # it is one series, not counted twice.
        for pid in sorted(self._pids, reverse=True):
            for inode in pt.socket_inodes(pid):
                owner[inode] = pid
        listening = {(c.family, c.local_address, c.local_port) for c in conns if c.state == LISTEN}
        connected = {}
        for c in conns:
            if c.state == LISTEN:
                continue
            end = self._connected.get(c.cookie)
            if end is None:
                end = self._connecting_end(c, listening)
            connected[c.cookie] = end
            pid = owner.get(c.inode)
            if not c.inode or pid is None:
                continue
            sent, received = application_bytes(c, end)
            labels = (str(pid), pt.name(pid), "tcp", _label(c, c.local_address, c.local_port),
                      _label(c, c.remote_address, c.remote_port), self._netns, str(c.inode))
            snap.add(SOCKET["sent_bytes"], labels, sent)
            snap.add(SOCKET["received_bytes"], labels, received)
        # Decided once per connection, so its counts cannot jump by one when a listener closes.
        self._connected = connected

    @staticmethod
    def _connecting_end(c: TcpConnection, listening: set) -> bool:
        """Whether this end sent the SYN, which the kernel counts in its bytes_acked.

        sock_diag does not say which end connected. An accepted socket shares its port with a
        listener; one accepted after its listener closed is taken for the connecting end, and its
        sent bytes read one low. With nothing acknowledged, this end cannot have sent a SYN."""
        if c.bytes_acked == 0:
            return False
        return not ({(c.family, c.local_address, c.local_port), (c.family, _ANY[c.family], c.local_port)}
                    & listening)
