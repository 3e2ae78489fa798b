"""Bytes, calls and errors of every TCP, UDP and unix socket (bpf/sockets.bpf.c), exported per
socket, per process and per thread.

Per-process totals include threads that exited and sockets that closed, so they never go
backwards; a closed socket's own series simply ends.
"""
from __future__ import annotations

import struct
import time
from dataclasses import dataclass

from drums.kernel.btf import Btf
from drums.metrics import COUNTER, Metric, Monotonic, Snapshot
from drums.netfmt import endpoint
from drums.probes.bpf import (SOCK_ENDPOINT_FIELDS, TASK_IDENTITY_FIELDS, AttachPath, BpfProbe, ProcessTotals,
                              needs_fentry, needs_kprobes, needs_tracepoints, offset_defines)
from drums.proctable import ProcessTable

PROTOCOLS = ("tcp", "udp", "unix", "other")  # index = class in the C code
_COUNTS = ("sent_bytes", "send_calls", "received_bytes", "receive_calls", "send_errors", "receive_errors")
_HELP = {
    "sent_bytes": "Bytes sent",
    "send_calls": "Successful send calls",
    "received_bytes": "Bytes received",
    "receive_calls": "Successful receive calls",
    "send_errors": "Send calls that failed (not counting EAGAIN and EINTR)",
    "receive_errors": "Receive calls that failed (not counting EAGAIN and EINTR)",
}
SOCKET_LABELS = ("pid", "process", "protocol", "local", "remote", "netns", "inode")
PROCESS_LABELS = ("pid", "process", "protocol")
THREAD_LABELS = ("pid", "tid", "protocol")

SOCKET = {c: Metric(f"drums_socket_{c}_total", COUNTER, f"{_HELP[c]} on this socket", SOCKET_LABELS)
          for c in _COUNTS}
SOCKET_GROUP = tuple(SOCKET[c] for c in _COUNTS)  # a socket's counters, in SocketCounts.counts order
PROCESS = {c: Metric(f"drums_process_socket_{c}_total", COUNTER,
                     f"{_HELP[c]} by this process on sockets of this protocol, closed ones included",
                     PROCESS_LABELS) for c in _COUNTS}
THREAD = {c: Metric(f"drums_thread_socket_{c}_total", COUNTER,
                    f"{_HELP[c]} by this thread on sockets of this protocol", THREAD_LABELS)
          for c in ("sent_bytes", "received_bytes")}

# Map layouts, as in bpf/sockets.bpf.c.
_SOCKET_VALUE = struct.Struct("<QIIHHHHHHI16s16s6Q")
_IDENTITY = struct.Struct("<QIIHHHHHHI16s16s")  # the head of _SOCKET_VALUE: what names the socket
_COUNTS6 = struct.Struct("<6Q")
_THREAD_VALUE = struct.Struct("<IIQ24Q")
_PROCESS_VALUE = struct.Struct("<Q24Q")
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")

# Listing a process's open files costs a readlink per file: a process's idle non-TCP sockets are
# checked for having closed at most this often (seconds).
FD_CHECK_INTERVAL = 10.0

SEND_RECV = ("sock_send_length", "sock_recv_length")
LIFECYCLE = (
    ("raw_tracepoint", "inet_sock_set_state", "on_tcp_state"),
    ("raw_tracepoint", "sched_process_exit", "on_thread_exit"),
    ("raw_tracepoint", "sched_process_free", "on_task_free"),
    ("raw_tracepoint", "sched_process_exec", "on_exec"),
)
_LIFECYCLE_EVENTS = tuple(event for _, event, _ in LIFECYCLE)


@dataclass
class SocketCounts:
    """One socket as the kernel counted it."""

    sk: int
    inode: int
    pid: int
    netns: int
    protocol: str
    local: str
    remote: str
    counts: tuple[int, ...]  # in _COUNTS order


def _identity(raw: bytes) -> tuple:
    """(inode, pid, netns, protocol, local, remote) from the identity part of a map value."""
    ino, tgid, netns, family, _proto, _unused, lport, rport, klass, _pad, laddr, raddr = _IDENTITY.unpack(raw)
    return (ino, tgid, netns, PROTOCOLS[klass] if klass < len(PROTOCOLS) else "other",
            endpoint(family, laddr, lport), endpoint(family, raddr, rport))


class SocketDecoder:
    """Map entries to sockets. Of ten thousand sockets most sit idle between two collects: an
    entry whose bytes did not change is not decoded again, and a socket's identity (its
    addresses) is decoded once, not at each change of its counts. Each call forgets what the
    entries it did not see."""

    def __init__(self):
        self._entries: dict[tuple[int, bytes], tuple[SocketCounts, tuple]] = {}  # -> (socket, identity)
        self._identities: dict[bytes, tuple] = {}

    def __call__(self, keys: bytes, values: bytes) -> list[tuple[SocketCounts, bytes]]:
        """(socket, its map value) for each entry."""
        entries, self._entries = self._entries, {}
        identities, self._identities = self._identities, {}
        out = []
        size, head = _SOCKET_VALUE.size, _IDENTITY.size
        for i, (sk,) in enumerate(_U64.iter_unpack(keys)):
            raw = values[i * size:(i + 1) * size]
            entry = entries.get((sk, raw))
            if entry is None:
                ident = identities.get(raw[:head]) or _identity(raw[:head])
                entry = (SocketCounts(sk, *ident, _COUNTS6.unpack_from(raw, head)), ident)
            self._entries[sk, raw] = entry
            self._identities[raw[:head]] = entry[1]
            out.append((entry[0], raw))
        return out


def unix_paths(path: str) -> dict[int, str]:
    """Inode -> bound path of the unix sockets in /proc/net/unix (this network namespace's);
    abstract names are shown with a leading @, as ss does."""
    out = {}
    try:
        with open(path) as f:
            next(f, None)
            for line in f:
                fields = line.split(None, 7)
                if len(fields) == 8 and fields[6].isdigit():
                    out[int(fields[6])] = fields[7].rstrip("\n")
    except OSError:
        pass
    return out


def _by_class(flat) -> list[tuple[int, ...]]:
    """24 counters -> 4 protocol classes x 6 counts, in _COUNTS order (the C struct's order)."""
    return [tuple(flat[6 * i: 6 * i + 6]) for i in range(len(PROTOCOLS))]


class SocketsProbe(BpfProbe):
    name = "sockets"
    source = "sockets.bpf.c"
    maps = ("socket_traffic", "thread_traffic", "exited_traffic", "dropped")
    metrics = tuple(SOCKET.values()) + tuple(PROCESS.values()) + tuple(THREAD.values())
    paths = (
        AttachPath("raw_tracepoint",
                   tuple(("raw_tracepoint", tp, fn) for tp, fn in zip(SEND_RECV, ("on_send", "on_recv")))
                   + LIFECYCLE,
                   needs_tracepoints(*SEND_RECV, *_LIFECYCLE_EVENTS),
                   "Linux >= 6.6: every socket family, one event per send and receive call"),
        AttachPath("fentry", (("fentry", "", ""),) + LIFECYCLE,
                   lambda f: needs_fentry(f) or needs_tracepoints(*_LIFECYCLE_EVENTS)(f),
                   "Linux 5.7 to 6.5 with BPF trampolines (Ubuntu 22.04): TCP and UDP only"),
        AttachPath("kprobe",
                   (("kprobe", "tcp_sendmsg", "enter_tcp_sendmsg"),
                    ("kretprobe", "tcp_sendmsg", "exit_tcp_sendmsg"),
                    ("kprobe", "tcp_cleanup_rbuf", "enter_tcp_cleanup_rbuf"),
                    ("kprobe", "udp_sendmsg", "enter_udp_sendmsg"),
                    ("kretprobe", "udp_sendmsg", "exit_udp_sendmsg"),
                    ("kprobe", "udp_recvmsg", "enter_udp_recvmsg"),
                    ("kretprobe", "udp_recvmsg", "exit_udp_recvmsg")) + LIFECYCLE,
                   lambda f: needs_kprobes(f) or needs_tracepoints(*_LIFECYCLE_EVENTS)(f),
                   "Linux 5.7 to 6.5 with kprobes but no BPF trampolines: TCP and UDP only, loaded in the agent"),
    )

    def __init__(self, features, proctable: ProcessTable, proc_net_unix: str = "/proc/net/unix", **kw):
        super().__init__(features, **kw)
        self.proctable = proctable
        self.proc_net_unix = proc_net_unix
        self._last_counts: dict[int, tuple[int, ...]] = {}
        self._monotonic = Monotonic()
        self._fds_read_at: dict[int, float] = {}
        self._decode = SocketDecoder()
        self._rows: dict[int, tuple] = {}  # sk -> (socket, process name, local, row) at the last collect

    def offsets(self, btf: Btf) -> dict[str, int]:
        d = offset_defines(btf, {**SOCK_ENDPOINT_FIELDS,
            "SK_STATE_OFF": ("sock", "__sk_common.skc_state"),
            "SK_PROTOCOL_OFF": ("sock", "sk_protocol"),
            "SK_SOCKET_OFF": ("sock", "sk_socket"),
            **TASK_IDENTITY_FIELDS,
        })
        # The socket's inode sits right after struct socket in struct socket_alloc.
        d["SOCKET_INO_OFF"] = (btf.field("socket_alloc", "vfs_inode").offset
                               + btf.field("inode", "i_ino").offset)
        return d

    def collect(self, snap: Snapshot) -> None:
        pt = self.proctable
        keys, values, _ = self.read("socket_traffic")
        sockets = self._decode(keys, values)
        stale = self._stale([s for s, _ in sockets])
        if stale:
            self.opened["socket_traffic"].delete_unchanged(
                [(_U64.pack(s.sk), raw) for s, raw in sockets if s.sk in stale])
        paths = unix_paths(self.proc_net_unix) if any(s.protocol == "unix" for s, _ in sockets) else {}
        rows = snap.group_rows(SOCKET_GROUP)
        # An idle socket's row is the very one of the last collect, and a busy one's labels are:
        # what the budget compares them with next is found at once.
        made, self._rows = self._rows, {}
        for s, _ in sockets:
            if s.sk in stale:
                continue
            local = paths.get(s.inode, "") if s.protocol == "unix" else s.local
            name = pt.name(s.pid)
            last = made.get(s.sk)
            if last is not None and last[1] == name and last[2] == local and last[0].inode == s.inode \
                    and last[0].pid == s.pid and last[0].remote == s.remote:
                row = last[3] if last[0] is s else (last[3][0], s.counts)
            else:
                row = ((str(s.pid), name, s.protocol, local, s.remote, str(s.netns), str(s.inode)), s.counts)
            self._rows[s.sk] = (s, name, local, row)
            rows.append(row)

        totals = ProcessTotals()
        keys, values, _ = self.read("exited_traffic")
        for (tgid,), (start, *flat) in zip(_U32.iter_unpack(keys), _PROCESS_VALUE.iter_unpack(values)):
            if pt.alive(tgid):
                totals.add_exited(tgid, start, flat)
        keys, values, _ = self.read("thread_traffic")
        for (tid,), (tgid, _pad, start, *flat) in zip(_U32.iter_unpack(keys), _THREAD_VALUE.iter_unpack(values)):
            if not pt.alive(tgid):
                continue
            totals.add_thread(tgid, start, flat)
            for klass, row in enumerate(_by_class(flat)):
                if any(row):
                    labels = (str(tgid), str(tid), PROTOCOLS[klass])
                    snap.add(THREAD["sent_bytes"], labels, row[0])
                    snap.add(THREAD["received_bytes"], labels, row[2])
        m = self._monotonic
        for (tgid, start), flat in totals.items():
            for klass, row in enumerate(_by_class(flat)):
                if any(row):
                    labels = (str(tgid), pt.name(tgid), PROTOCOLS[klass])
                    for c, value in zip(_COUNTS, row):
                        snap.add(PROCESS[c], labels, m((c, tgid, start, klass), value))
        m.next_collect()
        self.read_dropped()

    def _stale(self, sockets: list[SocketCounts]) -> set[int]:
        """Entries of sockets that are gone: their process exited, or (for sockets the kernel
        frees without a tracepoint) the process no longer holds the inode. Only sockets idle since
        the last collect are checked, each process at most once per FD_CHECK_INTERVAL, which keeps
        the /proc reads few."""
        stale = set()
        now = time.monotonic()
        inodes_of: dict[int, set[int]] = {}
        last, self._last_counts = self._last_counts, {s.sk: s.counts for s in sockets}
        for s in sockets:
            if not self.proctable.alive(s.pid):
                stale.add(s.sk)
            elif s.protocol != "tcp" and last.get(s.sk) == s.counts:
                if s.pid not in inodes_of:
                    if now - self._fds_read_at.get(s.pid, float("-inf")) < FD_CHECK_INTERVAL:
                        continue
                    self._fds_read_at[s.pid] = now
                    inodes_of[s.pid] = self.proctable.socket_inodes(s.pid)
                if s.inode not in inodes_of[s.pid]:
                    stale.add(s.sk)
        self._fds_read_at = {pid: t for pid, t in self._fds_read_at.items() if self.proctable.alive(pid)}
        return stale
