"""TCP sockets and their tcp_info, read over NETLINK_SOCK_DIAG (what `ss -ti` shows).

The fallback for per-connection byte counts without eBPF, and the source of smoothed RTT and retransmits.
"""
from __future__ import annotations

import errno
import os
import socket
import struct
import sys
import threading
from array import array
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from drums.errors import KernelError
from drums.netfmt import V4_MAPPED

# include/net/tcp_states.h. Request sockets are reported as SYN_RECV, never as NEW_SYN_RECV.
TCP_STATES = {
    1: "ESTABLISHED",
    2: "SYN_SENT",
    3: "SYN_RECV",
    4: "FIN_WAIT1",
    5: "FIN_WAIT2",
    6: "TIME_WAIT",
    7: "CLOSE",
    8: "CLOSE_WAIT",
    9: "LAST_ACK",
    10: "LISTEN",
    11: "CLOSING",
}
ALL_STATES = sum(1 << state for state in TCP_STATES)
# Those of full sockets, which a process may hold: not TIME_WAIT and SYN_RECV (the kernel's small
# stand-ins for a connection closing or being accepted), which may outnumber them on a busy host.
FULL_STATES = sum(1 << state for state, name in TCP_STATES.items() if name not in ("TIME_WAIT", "SYN_RECV"))

NETLINK_SOCK_DIAG = 4
SOCK_DIAG_BY_FAMILY = 20
NLMSG_ERROR, NLMSG_DONE = 2, 3
NLM_F_REQUEST, NLM_F_DUMP = 0x1, 0x300
INET_DIAG_INFO = 2

_NLMSGHDR = struct.Struct("=IHHII")  # len, type, flags, seq, pid
_RTATTR = struct.Struct("=HH")  # len, type
_ERRNO = struct.Struct("=i")
# struct inet_diag_req_v2: family, protocol, ext, pad, states, then an all-zero inet_diag_sockid.
_REQUEST = struct.Struct("=BBBxI48x")
# struct inet_diag_msg (include/uapi/linux/inet_diag.h): ports and addresses are in network order,
# the cookie is two host-order u32 (low half first), and timer, retrans, if, expires and queues are skipped.
_DIAG_MSG = struct.Struct("=BBxx2s2s16s16s4xII12xII")
# The same as a numpy record, for a dump read in bulk (ports and addresses in network order).
DIAG_RECORD = np.dtype({"names": ["family", "state", "sport", "dport", "src", "dst", "inode"],
                        "formats": ["u1", "u1", ">u2", ">u2", "V16", "V16", "=u4"],
                        "offsets": [0, 1, 4, 6, 8, 24, 68], "itemsize": _DIAG_MSG.size})
# The same request naming one socket: its ports, addresses (16 bytes each), interface and cookie.
_REQUEST_ONE = struct.Struct("=BBBxI2s2s16s16sI8s")
_NO_COOKIE = b"\xff" * 8  # INET_DIAG_NOCOOKIE in both halves: any socket with these endpoints
_ADDRESS_SIZE = {socket.AF_INET: 4, socket.AF_INET6: 16}

# (TcpConnection field, offset in struct tcp_info, format) per include/uapi/linux/tcp.h. The kernel
# copies only the tcp_info it knows, so a field past the end of an older kernel's reply reads as 0.
_TCP_INFO_FIELDS = (
    ("retransmits", 2, "B"),  # tcpi_retransmits: consecutive RTO retransmits now outstanding
    ("srtt_us", 68, "I"),  # tcpi_rtt
    ("rttvar_us", 72, "I"),  # tcpi_rttvar
    ("total_retrans", 100, "I"),  # tcpi_total_retrans
    ("bytes_acked", 120, "Q"),  # tcpi_bytes_acked, Linux 4.1
    ("bytes_received", 128, "Q"),  # tcpi_bytes_received, Linux 4.1
    ("segs_out", 136, "I"),  # tcpi_segs_out, Linux 4.2
    ("segs_in", 140, "I"),  # tcpi_segs_in, Linux 4.2
    ("bytes_sent", 200, "Q"),  # tcpi_bytes_sent (retransmits included), Linux 4.19
)
_TCP_INFO = tuple((name, offset, struct.Struct("=" + fmt)) for name, offset, fmt in _TCP_INFO_FIELDS)

_RECV_SIZE = 1 << 16  # the kernel fills at most 32 KiB of dump per read, so one read never truncates
_kept = threading.local()  # each thread's sock_diag socket (_diag_socket)


@dataclass(frozen=True, slots=True)
class TcpConnection:
    """One TCP socket; its tcp_info fields are 0 where the kernel gave none (TIME_WAIT, SYN_RECV).

    bytes_acked and bytes_received count sequence space as the kernel does: the connecting end's SYN
    adds 1 to its bytes_acked, and a FIN adds 1 to bytes_acked of its sender and bytes_received of its
    receiver. bytes_sent counts data only, retransmits included.
    """

    family: int
    state: int
    local_address: str
    local_port: int
    remote_address: str
    remote_port: int
    inode: int
    uid: int
    cookie: int
    bytes_sent: int = 0
    bytes_acked: int = 0
    bytes_received: int = 0
    segs_out: int = 0
    segs_in: int = 0
    srtt_us: int = 0
    rttvar_us: int = 0
    total_retrans: int = 0
    retransmits: int = 0


def own_netns() -> str:
    """The inode of this process's network namespace: the only one a sock_diag dump sees."""
    try:
        return str(os.stat("/proc/self/ns/net").st_ino)
    except OSError as e:
        raise KernelError(f"cannot read /proc/self/ns/net: {e.strerror}") from None


@contextmanager
def _diag_socket() -> Iterator[socket.socket]:
    """This thread's sock_diag socket, kept open from one request to the next: one made and closed
    at each would be a socket that comes and goes at every poll, which the sockets probe counts
    (and then sums the owners of all its sockets anew). A request that fails may leave replies
    unread: the socket is then closed, and the next request opens another."""
    sock = getattr(_kept, "sock", None)
    if sock is None:
        try:
            sock = _kept.sock = socket.socket(socket.AF_NETLINK, socket.SOCK_RAW | socket.SOCK_CLOEXEC,
                                              NETLINK_SOCK_DIAG)
        except OSError as e:
            raise KernelError(f"netlink NETLINK_SOCK_DIAG is unavailable: {e.strerror}") from None
    try:
        yield sock
    except BaseException:
        _kept.sock = None
        sock.close()
        raise


def dump_tcp(states: int = ALL_STATES, info: bool = True) -> list[TcpConnection]:
    """Every IPv4 and IPv6 TCP socket of this network namespace whose state bit is set in `states`;
    without `info`, their tcp_info fields are 0 (and the kernel sends a fifth of the bytes)."""
    with _diag_socket() as sock:
        return [_connection(data[start:end]) for family in (socket.AF_INET, socket.AF_INET6)
                for data, starts, ends in _dump(sock, family, states, info) for start, end in zip(starts, ends)]


def dump_tcp_table(states: int = ALL_STATES) -> np.ndarray:
    """The same sockets without tcp_info, as an array of DIAG_RECORD: ten thousand in a few ms,
    gathered from the replies in place (no Python object a socket)."""
    with _diag_socket() as sock:
        replies = [reply for family in (socket.AF_INET, socket.AF_INET6) for reply in _dump(sock, family, states, False)]
    tables = [np.empty(0, DIAG_RECORD)]
    for data, starts, ends in replies:
        starts = np.frombuffer(starts, np.int64)
        if (np.frombuffer(ends, np.int64) - starts < DIAG_RECORD.itemsize).any():
            raise KernelError("truncated inet_diag_msg in a sock_diag reply")
        record = np.frombuffer(data, np.uint8)[starts[:, None] + np.arange(DIAG_RECORD.itemsize)]
        tables.append(record.view(DIAG_RECORD)[:, 0])
    table = np.concatenate(tables)
    if not ((table["family"] == socket.AF_INET) | (table["family"] == socket.AF_INET6)).all():
        raise KernelError("unexpected address family in a sock_diag reply")
    return table


def lookup_tcp(connections: list[tuple[tuple[int, bytes, int], tuple[int, bytes, int]]]
               ) -> list[TcpConnection | None]:
    """The TCP socket of this network namespace with each of these (local, remote) endpoints, each
    a (family, address, port) as netfmt.parse_endpoint gives it, with its tcp_info; None for one
    that is gone. One request each: for a few hundred connections, cheaper than a dump of
    ten thousand. An IPv4 endpoint is looked for on an IPv6 socket too (as a mapped address)."""
    found = []
    with _diag_socket() as sock:
        for (family, local, lport), (_, remote, rport) in connections:
            tries = [(family, local, remote)]
            if family == socket.AF_INET:
                tries.append((socket.AF_INET6, V4_MAPPED + local, V4_MAPPED + remote))
            for fam, src, dst in tries:
                connection = _lookup(sock, fam, src, lport, dst, rport)
                if connection is not None:
                    break
            found.append(connection)
    return found


def _lookup(sock: socket.socket, family: int, src: bytes, sport: int, dst: bytes, dport: int) -> TcpConnection | None:
    body = _REQUEST_ONE.pack(family, socket.IPPROTO_TCP, 1 << (INET_DIAG_INFO - 1), ALL_STATES,
                             sport.to_bytes(2, "big"), dport.to_bytes(2, "big"), src, dst, 0, _NO_COOKIE)
    header = _NLMSGHDR.pack(_NLMSGHDR.size + len(body), SOCK_DIAG_BY_FAMILY, NLM_F_REQUEST, 1, 0)
    try:
        sock.send(header + body)
        data = sock.recv(_RECV_SIZE)
    except OSError as e:
        raise KernelError(f"reading a TCP socket over NETLINK_SOCK_DIAG failed: {e.strerror}") from None
    if len(data) >= _NLMSGHDR.size + _ERRNO.size and _NLMSGHDR.unpack_from(data)[1] == NLMSG_ERROR \
            and -_ERRNO.unpack_from(data, _NLMSGHDR.size)[0] == errno.ENOENT:
        return None
    payloads, _ = _payloads(data)
    return _connection(payloads[0]) if payloads else None


def _dump(sock: socket.socket, family: int, states: int, info: bool) -> list[tuple[bytes, array, array]]:
    """The replies of a dump, each with where its messages' payloads start and end (one a socket)."""
    body = _REQUEST.pack(family, socket.IPPROTO_TCP, 1 << (INET_DIAG_INFO - 1) if info else 0, states)
    header = _NLMSGHDR.pack(_NLMSGHDR.size + len(body), SOCK_DIAG_BY_FAMILY, NLM_F_REQUEST | NLM_F_DUMP, 1, 0)
    try:
        sock.send(header + body)
        replies = []
        while True:
            data, _, flags, _ = sock.recvmsg(_RECV_SIZE)
            if flags & socket.MSG_TRUNC:
                raise KernelError(f"a sock_diag reply did not fit in {_RECV_SIZE} bytes")
            starts, ends, done = _messages(data)
            replies.append((data, starts, ends))
            if done:
                return replies
    except OSError as e:
        raise KernelError(f"reading TCP sockets over NETLINK_SOCK_DIAG failed: {e.strerror}") from None


def parse_messages(data: bytes) -> list[TcpConnection]:
    """Decode the sock_diag messages in one netlink read.

    Malformed or truncated input raises KernelError rather than returning part of a dump: a
    connection missing from a dump would look closed, and its counters would be folded away.
    """
    return [_connection(payload) for payload in _payloads(data)[0]]


def _payloads(data: bytes) -> tuple[list[bytes], bool]:
    """The sock_diag messages' payloads in `data`, one a socket, and whether the dump ended in it."""
    starts, ends, done = _messages(data)
    return [data[start:end] for start, end in zip(starts, ends)], done


def _messages(data: bytes) -> tuple[array, array, bool]:
    """Where the sock_diag messages' payloads in `data` start and end (machine integers: a dump of
    ten thousand sockets makes no object each), and whether the dump ended in it (NLMSG_DONE)."""
    starts, ends = array("q"), array("q")
    offset = 0
    while offset < len(data):
        if len(data) - offset < _NLMSGHDR.size:
            raise KernelError(f"truncated netlink header at byte {offset} of a sock_diag reply")
        length, kind, _, _, _ = _NLMSGHDR.unpack_from(data, offset)
        if length < _NLMSGHDR.size or offset + length > len(data):
            raise KernelError(f"bad netlink message length {length} at byte {offset} of a sock_diag reply")
        if kind in (NLMSG_ERROR, NLMSG_DONE):
            # NLMSG_ERROR with 0 is an ACK; NLMSG_DONE of a dump carries the error that ended it, if any.
            payload = data[offset + _NLMSGHDR.size : offset + length]
            err = -_ERRNO.unpack_from(payload)[0] if len(payload) >= _ERRNO.size else 0
            if err:
                raise KernelError(f"the kernel refused the sock_diag request: {_strerror(err)}")
            if kind == NLMSG_DONE:
                return starts, ends, True
        elif kind == SOCK_DIAG_BY_FAMILY:
            starts.append(offset + _NLMSGHDR.size)
            ends.append(offset + length)
        offset += _align(length)
    return starts, ends, False


def _connection(payload: bytes) -> TcpConnection:
    if len(payload) < _DIAG_MSG.size:
        raise KernelError(f"truncated inet_diag_msg ({len(payload)} bytes) in a sock_diag reply")
    family, state, sport, dport, src, dst, cookie_lo, cookie_hi, uid, inode = _DIAG_MSG.unpack_from(payload)
    if family not in _ADDRESS_SIZE:
        raise KernelError(f"unexpected address family {family} in a sock_diag reply")
    size = _ADDRESS_SIZE[family]
    rest = payload[_align(_DIAG_MSG.size) :]
    info = _attributes(rest).get(INET_DIAG_INFO, b"") if rest else b""
    counters = {name: fmt.unpack_from(info, at)[0] for name, at, fmt in _TCP_INFO
                if at + fmt.size <= len(info)} if info else {}
    return TcpConnection(
        family=family,
        state=state,
        # Interned: a host's connections share a few addresses, and the auto graph keeps a dump
        # of ten thousand of them between polls (20,000 strings, 1.1 MB, were a handful).
        local_address=sys.intern(socket.inet_ntop(family, src[:size])),
        local_port=int.from_bytes(sport, "big"),
        remote_address=sys.intern(socket.inet_ntop(family, dst[:size])),
        remote_port=int.from_bytes(dport, "big"),
        inode=inode,
        uid=uid,
        cookie=cookie_hi << 32 | cookie_lo,
        **counters,
    )


def _attributes(data: bytes) -> dict[int, bytes]:
    """The netlink attributes (struct rtattr) of one message, by type."""
    attrs = {}
    offset = 0
    while len(data) - offset >= _RTATTR.size:
        length, kind = _RTATTR.unpack_from(data, offset)
        if length < _RTATTR.size or offset + length > len(data):
            raise KernelError(f"bad attribute length {length} in a sock_diag reply")
        attrs[kind] = data[offset + _RTATTR.size : offset + length]
        offset += _align(length)
    return attrs


def _align(length: int) -> int:
    return (length + 3) & ~3


def _strerror(err: int) -> str:
    if err == errno.ENOENT:
        return "no TCP diag handler (is the tcp_diag module available?)"
    return os.strerror(err)
