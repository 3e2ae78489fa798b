"""Bytes, calls and errors of every TCP, UDP and unix socket (bpf/sockets.bpf.c), exported per
socket and per process.

A socket counts for the process that first used it (its owner; a socket handed to another process
keeps it). Per-process totals include sockets that closed, so they never go backwards; a closed
socket's own series simply ends.
"""
from __future__ import annotations

import struct
import time
from sys import intern

import numpy as np

from drums.arrays import among, distinct
from drums.kernel.btf import Btf
from drums.metrics import COUNTER, Columns, Metric, Monotonic, Snapshot
from drums.netfmt import endpoint
from drums.probes.bpf import (SOCK_ENDPOINT_FIELDS, TASK_IDENTITY_FIELDS, AttachPath, BpfProbe, needs_fentry,
                              needs_kprobes, needs_tracepoints, offset_defines, typed)
from drums.probes.entries import Entries, Matched, Remembered
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

SOCKET = {c: Metric(f"drums_socket_{c}_total", COUNTER, f"{_HELP[c]} on this socket", SOCKET_LABELS)
          for c in _COUNTS}
SOCKET_GROUP = tuple(SOCKET[c] for c in _COUNTS)  # a socket's counters, in the map value's order
PROCESS = {c: Metric(f"drums_process_socket_{c}_total", COUNTER,
                     f"{_HELP[c]} on the sockets of this protocol that this process used first, closed ones "
                     "included", PROCESS_LABELS) for c in _COUNTS}

# Map layouts, as in bpf/sockets.bpf.c.
_SOCKET_VALUE = struct.Struct("<QIIHHHHHHI16s16s6QQQ")  # the counts, the generation marked in, the owner's start
_IDENTITY = struct.Struct("<QIIHHHHHHI16s16s")  # the head of _SOCKET_VALUE: what names the socket
_PROCESS_VALUE = struct.Struct("<Q24Q")
_U64 = struct.Struct("<Q")
_WORD = (1 << 64) - 1
_U32 = struct.Struct("<I")

# Listing a process's open files costs a readlink per file: a process's idle non-TCP sockets are
# checked for having closed at most this often (seconds).
FD_CHECK_INTERVAL = 10.0

SEND_RECV = ("sock_send_length", "sock_recv_length")
LIFECYCLE = (
    ("raw_tracepoint", "inet_sock_set_state", "on_tcp_state"),
    ("raw_tracepoint", "sched_process_free", "on_task_free"),
)
_LIFECYCLE_EVENTS = tuple(event for _, event, _ in LIFECYCLE)
_RAW = AttachPath("raw_tracepoint",
                  tuple(("raw_tracepoint", tp, fn) for tp, fn in zip(SEND_RECV, ("on_send", "on_recv"))) + LIFECYCLE,
                  needs_tracepoints(*SEND_RECV, *_LIFECYCLE_EVENTS),
                  "Linux >= 6.6: every socket family, one event per send and receive call")


# The map value as 8-byte words (bpf/sockets.bpf.c): the identity (inode, process, addresses) in
# the first 8, the six counts after it, then the generation marked in and the owner's start.
_WORDS_IDENTITY = _IDENTITY.size // 8
_WORDS_COUNTS = _WORDS_IDENTITY + len(_COUNTS)  # the end of the counts
_WORD_START = _WORDS_COUNTS + 1
_TCP = PROTOCOLS.index("tcp")


def _identity(raw: bytes) -> tuple:
    """(inode, pid, netns, protocol, local, remote) from the identity part of a map value."""
    ino, tgid, netns, family, _proto, _unused, lport, rport, klass, _pad, laddr, raddr = _IDENTITY.unpack(raw)
    return (ino, tgid, netns, PROTOCOLS[klass] if klass < len(PROTOCOLS) else "other",
            endpoint(family, laddr, lport), endpoint(family, raddr, rport))


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


def _add(totals: dict, key: tuple, counts) -> None:
    """Add six counts to those of `key`, unless they are all 0."""
    if any(counts):
        was = totals.get(key)
        totals[key] = list(counts) if was is None else [a + b for a, b in zip(was, counts)]


def _ports(words: np.ndarray) -> np.ndarray:
    """Each socket's local port << 16 | remote port, from its value as 8-byte words."""
    return ((words[:, 2] >> 48) << 16 | (words[:, 3] & 0xFFFF)).astype(np.int64)


def _owner(words: list[int]) -> tuple[int, int, int]:
    """(pid, start, class) of a socket's entry, from its value as 8-byte words."""
    return words[1] & 0xFFFFFFFF, words[_WORD_START], (words[3] >> 16) & 0xFFFF


def _owned(tgid: np.ndarray, start: np.ndarray, klass: np.ndarray, counts: np.ndarray) -> dict:
    """(pid, start, class) -> its six counts summed: rows of sockets grouped by owner, in bulk."""
    if not len(tgid):
        return {}
    key = tgid << 2 | klass  # classes are 0 to 3
    order = np.lexsort((key, start))
    key, start = key[order], start[order]
    first = np.flatnonzero(np.concatenate(([True], (key[1:] != key[:-1]) | (start[1:] != start[:-1]))))
    sums = np.add.reduceat(np.take(counts, order, axis=0), first, axis=0).tolist()  # take: 4x faster here
    return {(k >> 2, s, k & 3): row for k, s, row in zip(key[first].tolist(), start[first].tolist(), sums)}


class _Labels:
    """The label values of sockets, made from their entries' words when the budget or a reader
    of the snapshot asks for them (of ten thousand sockets, the hundred with series of their own).
    What the last collect's asked for are taken again where the socket's words that name it and
    its process's name are the same. A reader that asks after the probe's next collect may find
    an entry given to another socket meanwhile, of a process this collect did not name: its name
    is then empty."""

    def __init__(self, words: np.ndarray, names: dict[int, str], proc_net_unix: str, remembered: Remembered):
        self.words, self.names, self.proc_net_unix = words, names, proc_net_unix
        self.remembered = remembered  # by the identity words, checked against the process's name
        self._paths: dict[int, str] | None = None  # unix sockets' bound paths, read at the first asked for

    def __call__(self, at: list[int]) -> list[tuple[str, ...]]:
        out = []
        for raw in self.words[at, :_WORDS_IDENTITY]:
            key, name = raw.tobytes(), self.names.get(int(raw[1]) & 0xFFFFFFFF, "")
            out.append(self.remembered.get(key, name, lambda: self._make(key, name)))
        return out

    def stamps(self, at: np.ndarray) -> np.ndarray:
        """What the labels of the sockets at these indices are made from: the words that name each,
        and a hash of its process's name."""
        names = [self.names.get(pid, "") for pid in (self.words[at, 1] & 0xFFFFFFFF).tolist()]
        hashes = np.fromiter((hash(name) & _WORD for name in names), np.uint64, len(names))
        return np.column_stack((self.words[at, :_WORDS_IDENTITY], hashes))

    def _make(self, key: bytes, name: str) -> tuple[str, ...]:
        ino, pid, netns, protocol, local, remote = _identity(key)
        if protocol == "unix":
            if self._paths is None:
                self._paths = unix_paths(self.proc_net_unix)
            local = self._paths.get(ino, "")
        # Interned: the label values many sockets share (their process's pid, their namespace),
        # and the addresses the tcp probe's rows name too, are one string each.
        return (intern(str(pid)), name, protocol, intern(local), intern(remote), intern(str(netns)), str(ino))


class SocketsProbe(BpfProbe):
    name = "sockets"
    source = "sockets.bpf.c"
    maps = ("socket_traffic", "generation", "changed_even", "changed_odd", "closed_traffic", "dropped")
    metrics = tuple(SOCKET.values()) + tuple(PROCESS.values())
    paths = (
        typed(_RAW),
        _RAW,
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
        self._monotonic = Monotonic()
        self._fds_read_at: dict[int, float] = {}
        self._entries = Entries(_SOCKET_VALUE.size, _IDENTITY.size)
        # (pid, start, class) -> the counts of sockets whose entries this probe deleted (they had
        # closed) while their owner lives on: closed_traffic's counterpart in user space.
        self._forgotten: dict[tuple[int, int, int], list[int]] = {}
        self._live_totals: dict = {}  # _owned() of the live entries, as of the last collect
        self._entries_summed = False  # whether _live_totals is that of the entries the last collect kept
        self._labelled = Remembered()  # the labels the last collect's sockets were asked for

    def offsets(self, btf: Btf) -> dict[str, int]:
        d = offset_defines(btf, {**SOCK_ENDPOINT_FIELDS,
            "SK_STATE_OFF": ("sock", "__sk_common.skc_state"),
            "SK_PROTOCOL_OFF": ("sock", "sk_protocol"),
            "SK_SOCKET_OFF": ("sock", "sk_socket"),
            **TASK_IDENTITY_FIELDS,
        })
        # The socket's inode sits right after struct socket in struct socket_alloc; a tp_btf program
        # may only load fields of the struct it holds, and goes through the socket's file instead.
        d["SOCKET_INO_OFF"] = (btf.field("socket_alloc", "vfs_inode").offset
                               + btf.field("inode", "i_ino").offset)
        d.update(offset_defines(btf, {"SOCKET_FILE_OFF": ("socket", "file"), "FILE_INODE_OFF": ("file", "f_inode"),
                                      "INODE_INO_OFF": ("inode", "i_ino")}))
        return d

    def collect(self, snap: Snapshot) -> None:
        pt = self.proctable
        # First: a collect that fails leaves sums the next cannot bring up to date.
        summed, self._entries_summed = self._entries_summed, False
        # Before the sockets: an entry the kernel deletes between the two reads is then missing
        # from both for this collect (which Monotonic holds back), never counted twice.
        closed_keys, closed_values, _ = self.read("closed_traffic")
        m = self.read_marked("socket_traffic", self._entries)
        words = m.words
        pids = (words[:, 1] & 0xFFFFFFFF).astype(np.int64)
        klass = (words[:, 3] >> 16) & 0xFFFF
        # Per process, not per socket: which are gone, and the names of the others.
        names, dead = {}, []
        for pid in distinct(pids).tolist():
            if pt.alive(pid):
                names[pid] = pt.name(pid)
            else:
                dead.append(pid)
        stale = among(pids, dead) | self._closed(m, pids, klass)
        if stale.any():
            self._forget(m, np.flatnonzero(stale))
        live = ~stale
        self._entries.keep(m, live)
        # The entries' own arrays as a rule (no socket went): a copy a scrape of ten thousand sockets'
        # words costs page faults more than it saves. The next collect writes over them in place,
        # so what a reader keeps of the columns it copies.
        w = words if live.all() else words[live]
        # Each socket by its inode; one without (it had no struct socket when first counted) by its
        # entry's key, a kernel address, which as an int64 is below 0 and so no inode.
        ino, key = w[:, 0].astype(np.int64), m.keys[live].astype(np.int64)
        labels = _Labels(w, names, self.proc_net_unix, self._labelled.turn())
        snap.groups[SOCKET_GROUP] = Columns(
            np.where(ino != 0, ino, key), w[:, _WORDS_IDENTITY:_WORDS_COUNTS].view(np.int64),
            klass[live].astype(np.intp), PROTOCOLS, pids[live],
            labels, _ports(w), stamps=labels.stamps)
        # The owners' sums: brought up to date by what the sockets counted since the last collect
        # when no socket came or went, else summed anew.
        if (live & ~m.same_head).any() or stale.any() or len(m.gone) or not summed:
            self._live_totals = _owned(w[:, 1] & 0xFFFFFFFF, w[:, _WORD_START], (w[:, 3] >> 16) & 0xFFFF,
                                       w[:, _WORDS_IDENTITY:_WORDS_COUNTS])
        else:
            for now, was in zip(words[m.grown].tolist(), m.before.tolist()):
                _add(self._live_totals, _owner(now), [a - b for a, b in zip(now[_WORDS_IDENTITY:_WORDS_COUNTS],
                                                                            was[_WORDS_IDENTITY:_WORDS_COUNTS])])
        self._entries_summed = True
        self._process_totals(snap, closed_keys, closed_values)
        self.read_dropped()

    def _process_totals(self, snap: Snapshot, closed_keys: bytes, closed_values: bytes) -> None:
        """Per process and protocol: its live sockets' counts (_live_totals) and what its closed sockets
        left in closed_traffic and in this probe's _forgotten."""
        pt = self.proctable
        totals = dict(self._live_totals)
        # A process's closed_traffic goes when the kernel reaps it, unless a socket it owned (and
        # handed on) closes after that: such are deleted here.
        ended = []
        size = _PROCESS_VALUE.size
        for i, ((tgid,), (start, *flat)) in enumerate(zip(_U32.iter_unpack(closed_keys),
                                                           _PROCESS_VALUE.iter_unpack(closed_values))):
            if not pt.alive(tgid):
                ended.append((closed_keys[4 * i: 4 * i + 4], closed_values[size * i: size * (i + 1)]))
                continue
            for klass in range(len(PROTOCOLS)):
                _add(totals, (tgid, start, klass), flat[6 * klass: 6 * klass + 6])
        if ended:
            self.opened["closed_traffic"].delete_unchanged(ended)
        self._forgotten = {k: v for k, v in self._forgotten.items() if pt.alive(k[0])}
        for key, row in self._forgotten.items():
            _add(totals, key, row)
        # A PID's counts are those of its latest process (the highest start): what an earlier one
        # left is gone with it.
        latest: dict[int, int] = {}
        for tgid, start, _ in totals:
            latest[tgid] = max(start, latest.get(tgid, start))
        m = self._monotonic
        for (tgid, start, klass), row in totals.items():
            if latest[tgid] != start or not pt.alive(tgid):
                continue
            labels = (str(tgid), pt.name(tgid), PROTOCOLS[klass])
            for c, value in zip(_COUNTS, row):
                snap.add(PROCESS[c], labels, m((c, tgid, start, klass), value))
        m.next_collect()

    def _forget(self, m: Matched, stale: np.ndarray) -> None:
        """Delete the entries of sockets that are gone (their process ended, or it holds them no
        more); the counts of those that the deletion took go to _forgotten."""
        words = m.words[stale]
        entries = [(_U64.pack(k), w.tobytes()) for k, w in zip(m.keys[stale].tolist(), words)]
        deleted = self.opened["socket_traffic"].delete_unchanged(entries)  # one that changed comes back marked
        for w in words[np.array(deleted, bool)].tolist():
            owner = _owner(w)
            if self.proctable.alive(owner[0]):
                _add(self._forgotten, owner, w[_WORDS_IDENTITY:_WORDS_COUNTS])

    def _closed(self, m: Matched, pids: np.ndarray, klass: np.ndarray) -> np.ndarray:
        """Entries of sockets the kernel freed without a tracepoint (all but TCP): the process no
        longer holds the inode. Only sockets idle since the last collect are checked, each process
        at most once per FD_CHECK_INTERVAL, which keeps the /proc reads few."""
        closed = np.zeros(len(pids), bool)
        idle = m.same & (klass != _TCP)
        now = time.monotonic()
        due = [pid for pid in distinct(pids[idle]).tolist()
               if self.proctable.alive(pid) and now - self._fds_read_at.get(pid, float("-inf")) >= FD_CHECK_INTERVAL]
        if due:
            inodes_of = {pid: self.proctable.socket_inodes(pid) for pid in due}
            for pid in due:
                self._fds_read_at[pid] = now
            for i in np.flatnonzero(idle & among(pids, due)).tolist():
                closed[i] = int(m.words[i, 0]) not in inodes_of[int(pids[i])]
            self._fds_read_at = {pid: t for pid, t in self._fds_read_at.items() if self.proctable.alive(pid)}
        return closed
