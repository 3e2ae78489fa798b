"""Bytes, calls and errors of every TCP, UDP and unix socket (bpf/sockets.bpf.c), exported per
socket and per process.

A socket counts for the process that first used it (its owner; a socket handed to another process
keeps it). Per-process totals include sockets that closed, so they never go backwards; a closed
socket's own series simply ends.
"""
from __future__ import annotations

import socket
import struct
import time
from dataclasses import replace
from sys import intern

import numpy as np

from drums.arrays import among, distinct, within
from drums.errors import KernelError
from drums.kernel import bpffs, sockdiag
from drums.kernel.btf import Btf
from drums.metrics import COUNTER, Columns, Metric, Monotonic, Snapshot
from drums.netfmt import endpoint
from drums.probes.bpf import (DROPPED, SOCK_ENDPOINT_FIELDS, TASK_IDENTITY_FIELDS, AttachPath, BpfProbe, change_marks,
                              comm_text, needs_all, needs_fentry, needs_kprobes, needs_test_run, needs_tracepoints,
                              offset_defines, typed)
from drums.probes.entries import Entries, Matched, Remembered
from drums.proctable import ProcessTable, comm

PROTOCOLS = ("tcp", "udp", "unix", "other")  # index = class in the C code
_COUNTS = ("sent_bytes", "send_calls", "received_bytes", "receive_calls", "send_errors", "receive_errors")
_HELP = {
    "sent_bytes": "Bytes sent",
    "send_calls": "Successful send operations (one per send, sendmsg, write or writev call, per datagram of "
                  "sendmmsg, and per batch of pages that sendfile or splice hands the socket)",
    "received_bytes": "Bytes received",
    "receive_calls": "Successful receive operations (one per recv, recvmsg, read or readv call, per datagram "
                     "of recvmmsg, and per splice from the socket; a MSG_PEEK is none)",
    "send_errors": "Send calls that failed with an error the application saw (not EAGAIN or EINTR)",
    "receive_errors": "Receive calls that failed with an error the application saw (not EAGAIN or EINTR)",
}
SOCKET_LABELS = ("pid", "process", "protocol", "local", "remote", "netns", "inode")
PROCESS_LABELS = ("pid", "process", "protocol")

SOCKET = {c: Metric(f"drums_socket_{c}_total", COUNTER, f"{_HELP[c]} on this socket", SOCKET_LABELS)
          for c in _COUNTS}
SOCKET_GROUP = tuple(SOCKET[c] for c in _COUNTS)  # a socket's counters, in the map value's order
PROCESS = {c: Metric(f"drums_process_socket_{c}_total", COUNTER,
                     f"{_HELP[c]} on the sockets of this protocol that this process used first, closed ones "
                     "included", PROCESS_LABELS) for c in _COUNTS}

# Map layouts, as in bpf/sockets.bpf.c. A socket's: its identity, counts, the generation marked in,
# the owner's start, and in a slot the slot's owner.
_SOCKET_VALUE = struct.Struct("<QIIHHHHHHI16s16s6QQQQ")
_IDENTITY = struct.Struct("<QIIHHHHHHI16s16s")  # the head of _SOCKET_VALUE: what names the socket
_PROCESS_VALUE = struct.Struct("<Q24Q16s")  # struct process_traffic_t
_U64 = struct.Struct("<Q")
_WORD = (1 << 64) - 1
_U32 = struct.Struct("<I")

# Listing a process's open files costs a readlink per file: a process's idle non-TCP sockets are
# checked for having closed at most this often (seconds).
FD_CHECK_INTERVAL = 10.0
# A TCP entry whose CLOSE the programs missed is rare (a call raced with it), and finding one costs
# a sock_diag dump of the namespace's TCP sockets (2.5 ms for a few, 22 for 20,000): idle TCP
# entries are checked at most this often (seconds).
TCP_CHECK_INTERVAL = 60.0

# Slots of socket entries (bpf/sockets.bpf.c, whose slot_of() hashes a socket's id as _slot_index() does).
SOCKET_SLOTS = 16384
_SLOT_HASH = np.uint64(0x9E3779B97F4A7C15)

SEND_RECV = ("sock_send_length", "sock_recv_length")
# Before those tracepoints (Linux 6.6): what sock_sendmsg and sock_recvmsg call for each family, where
# the tracepoints later came (bpf/sockets.bpf.c).
FAMILY_CALLS = tuple(f"{family}_{call}msg" for call in ("send", "recv")
                     for family in ("inet", "inet6", "unix_stream", "unix_dgram"))
# What splice(2) takes from a TCP or unix stream socket, and (Linux < 6.5) what sendfile and splice
# hand a socket: neither goes through sendmsg or recvmsg there.
SPLICE_READS = ("tcp_splice_read", "unix_stream_splice_read")
SENDPAGES = ("inet_sendpage", "unix_stream_sendpage")
LIFECYCLE = (("raw_tracepoint", "inet_sock_set_state", "on_tcp_state"),
             ("run", "", "forget_gone"))  # the agent's, for sockets freed without a tracepoint (see _forget)
_NEEDS_LIFECYCLE = needs_all(needs_test_run, needs_tracepoints("inet_sock_set_state"))
_RAW = AttachPath("raw_tracepoint",
                  tuple(("raw_tracepoint", tp, fn) for tp, fn in zip(SEND_RECV, ("on_send", "on_recv"))) + LIFECYCLE,
                  needs_all(needs_tracepoints(*SEND_RECV), _NEEDS_LIFECYCLE),
                  "Linux >= 6.6: every socket family, one event per send and receive call")
TRACEPOINT_PATHS = ("tp_btf", "raw_tracepoint")

# On the tracepoint paths only splice's reads miss the tracepoints; what counts them (SPLICE_READS in
# bpf/sockets.bpf.c): kprobes on the two functions, pinned as links (they cost splices alone), or
# where the kernel has no kprobes and the agent was asked to, the syscall's tracepoints, which slow
# every system call of every process on the host (enabling one sets the kernel's syscall tracing
# work on every task; bench/event_cost.py measures it); else nothing.
SPLICE_UNCOUNTED, SPLICE_BY_KPROBES, SPLICE_BY_SYSCALLS = 0, 1, 2
SPLICE_EVENTS = ("sys_enter_splice", "sys_exit_splice")
_SPLICE_ATTACHMENTS = {
    SPLICE_UNCOUNTED: (),
    SPLICE_BY_KPROBES: tuple((kind, fn, f"{side}_{fn}") for fn in SPLICE_READS
                             for kind, side in (("kprobe_link", "enter"), ("kretprobe_link", "exit"))),
    SPLICE_BY_SYSCALLS: tuple(("tracepoint", f"syscalls:{e}", fn)
                              for e, fn in zip(SPLICE_EVENTS, ("on_splice_enter", "on_splice_exit"))),
}
SPLICE_UNCOUNTED_WHY = ("splice(2) reads from TCP and unix stream sockets are not counted on the tracepoint "
                        "paths of a kernel without kprobes; `drums agent --splice-tracepoints` counts them "
                        "through the syscall tracepoints, which slow every system call on the host")


def splice_reads(features, splice_tracepoints: bool) -> int:
    """How the tracepoint paths count splice's reads on this kernel (SPLICE_*)."""
    if features.kprobes:
        return SPLICE_BY_KPROBES
    if splice_tracepoints and all(features.tracepoint(e) for e in SPLICE_EVENTS):
        return SPLICE_BY_SYSCALLS
    return SPLICE_UNCOUNTED


# The map value as 8-byte words (bpf/sockets.bpf.c): the identity (inode, process, addresses) in
# the first 8, the six counts after it, then the generation marked in, the owner's start and the
# owner of a slot.
_WORDS_IDENTITY = _IDENTITY.size // 8
_WORDS_COUNTS = _WORDS_IDENTITY + len(_COUNTS)  # the end of the counts
_WORD_START = _WORDS_COUNTS + 1
_WORD_ID = _WORD_START + 1
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


def _slot_index(keys: np.ndarray, slots: int) -> np.ndarray:
    """The slot of each socket, by its key (its id: bpf/sockets.bpf.c's socket_id), as slot_of() there."""
    return ((keys * _SLOT_HASH) >> np.uint64(32) & np.uint64(slots - 1)).astype(np.intp)


def _addresses(words: np.ndarray) -> tuple[tuple[int, bytes, int], tuple[int, bytes, int]]:
    """(family, address, port) of a socket's two ends, from its value as 8-byte words, as
    sockdiag.lookup_tcp takes them."""
    _, _, _, family, _, _, lport, rport, _, _, laddr, raddr = _IDENTITY.unpack(words[:_WORDS_IDENTITY].tobytes())
    size = 4 if family == socket.AF_INET else 16
    return (family, laddr[:size], lport), (family, raddr[:size], rport)


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


class _Identity:
    """What the entries' identity words give: each socket's process, class, id and ports, and the
    processes that hold them. Made again only when an entry came, went or names another socket:
    between two scrapes of ten thousand idle sockets, as a rule none did."""

    def __init__(self, m: Matched):
        w = m.words
        self.keys = m.keys
        self.pids = (w[:, 1] & 0xFFFFFFFF).astype(np.int64)
        self.klass = (w[:, 3] >> 16) & 0xFFFF
        self.owners = distinct(self.pids).tolist()
        # Each socket by its inode; one without (it had no struct socket when first counted) by its
        # entry's key with the top bit set, which as an int64 is below 0 and so no inode.
        ino = w[:, 0].astype(np.int64)
        self.ids = np.where(ino != 0, ino, (m.keys | np.uint64(1 << 63)).astype(np.int64))
        self.dims = self.klass.astype(np.intp)
        self.ports = _ports(w)

    def holds(self, m: Matched) -> bool:
        """Whether these are the identities of m's entries: the same keys (the very array the entries
        kept, which a read of what changed hands back while no entry came or went) naming the same
        sockets."""
        return m.keys is self.keys and bool(m.same_head.all())

    def of(self, live: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ids, dims, pids, ports) of the entries under `live`: these arrays themselves when all are."""
        if live.all():
            return self.ids, self.dims, self.pids, self.ports
        return self.ids[live], self.dims[live], self.pids[live], self.ports[live]


class SocketsProbe(BpfProbe):
    name = "sockets"
    source = "sockets.bpf.c"
    maps = {"socket_traffic": (_U64, _SOCKET_VALUE), "socket_slots": (_U32, _SOCKET_VALUE),
            "closed_traffic": (_U32, _PROCESS_VALUE), **change_marks(_U64), **DROPPED}
    metrics = tuple(SOCKET.values()) + tuple(PROCESS.values())
    paths = (
        typed(_RAW),
        _RAW,
        AttachPath("fentry", (("fentry", "", ""),) + LIFECYCLE,
                   needs_all(needs_fentry, _NEEDS_LIFECYCLE),
                   "Linux 5.10 to 6.5 with BPF trampolines (Ubuntu 22.04): fexit on each family's sendmsg and recvmsg"),
        AttachPath("kprobe",
                   tuple((kind, fn, f"{side}_{fn}") for fn in FAMILY_CALLS + SPLICE_READS + SENDPAGES
                         for kind, side in (("kprobe", "enter"), ("kretprobe", "exit"))) + LIFECYCLE,
                   needs_all(needs_kprobes, _NEEDS_LIFECYCLE),
                   "Linux 5.10 to 6.5 without BPF trampolines: kprobes on each family's sendmsg and recvmsg, "
                   "loaded in the agent", optional=SENDPAGES),
    )

    def __init__(self, features, proctable: ProcessTable, proc_net_unix: str = "/proc/net/unix",
                 splice_tracepoints: bool = False, **kw):
        super().__init__(features, **kw)
        self.proctable = proctable
        self.splice_reads = splice_reads(features, splice_tracepoints)
        self.options = {"SPLICE_READS": self.splice_reads}
        self.proc_net_unix = proc_net_unix
        self._monotonic = Monotonic()
        self._named: dict[int, str] = {}  # the name of each process the last collect gave totals of
        self._fds_read_at: dict[int, float] = {}
        self._tcp_checked_at = float("-inf")
        self._netns: int | None = None  # this process's network namespace: the one sock_diag lists
        self._entries = Entries(_SOCKET_VALUE.size, _IDENTITY.size)
        self._live_totals: dict = {}  # _owned() of the live entries, as of the last collect
        self._entries_summed = False  # whether _live_totals is that of the entries the last collect kept
        self._labelled = Remembered()  # the labels the last collect's sockets were asked for
        self._waiting = np.empty(0, np.uint64)  # sockets whose slot was being taken or given up at the last look
        self._hashed: set[int] = set()  # sockets whose entry is in socket_traffic, for its fill
        self._identity: _Identity | None = None  # of the entries the last collect kept

    def caveat(self, path: AttachPath) -> str:
        return SPLICE_UNCOUNTED_WHY if path.name in TRACEPOINT_PATHS and self.splice_reads == SPLICE_UNCOUNTED else ""

    def attachments(self, path: AttachPath) -> list[tuple[str, str, str]]:
        if path.name in TRACEPOINT_PATHS:
            path = replace(path, attachments=path.attachments + _SPLICE_ATTACHMENTS[self.splice_reads])
        return super().attachments(path)

    def offsets(self, btf: Btf) -> dict[str, int]:
        d = offset_defines(btf, {**SOCK_ENDPOINT_FIELDS,
            "SK_STATE_OFF": ("sock", "__sk_common.skc_state"),
            "SK_PROTOCOL_OFF": ("sock", "sk_protocol"),
            "SK_SOCKET_OFF": ("sock", "sk_socket"),
            "SOCKET_SK_OFF": ("socket", "sk"),
            "SK_TYPE_OFF": ("sock", "sk_type"),
            # a task's file descriptor to its file (the splice counts)
            "TASK_FILES_OFF": ("task_struct", "files"),
            "FILES_FDT_OFF": ("files_struct", "fdt"),
            "FDTABLE_FD_OFF": ("fdtable", "fd"),
            "FDTABLE_MAX_FDS_OFF": ("fdtable", "max_fds"),
            "FILE_PRIVATE_OFF": ("file", "private_data"),
            "INODE_MODE_OFF": ("inode", "i_mode"),
            **TASK_IDENTITY_FIELDS,
        })
        # The socket's inode sits right after struct socket in struct socket_alloc; a tp_btf program
        # may only load fields of the struct it holds, and goes through the socket's file instead.
        d["SOCKET_INO_OFF"] = (btf.field("socket_alloc", "vfs_inode").offset
                               + btf.field("inode", "i_ino").offset)
        d.update(offset_defines(btf, {"SOCKET_FILE_OFF": ("socket", "file"), "FILE_INODE_OFF": ("file", "f_inode"),
                                      "INODE_INO_OFF": ("inode", "i_ino")}))
        d["SOCKET_SLOTS"] = SOCKET_SLOTS if self.features.bpf_atomics else 1  # slots are taken by compare-and-swap
        if btf.has_function(SENDPAGES[0]):
            d["HAS_SENDPAGE"] = 1
        return d

    def socket_entries(self) -> tuple[bytes, bytes]:
        """Every socket's entry, as (keys, values): those in slots read in place. One whose slot
        is being taken or given up (its owner shown, its owner's start not) waits for the next
        collect; a socket with an entry in its slot and one in socket_traffic (made at once by two
        CPUs) is read from its slot, which its calls count into."""
        keys, values, _ = self.read("socket_traffic")
        width = _SOCKET_VALUE.size // 8
        with self.opened["socket_slots"].mapped() as mapping:
            slots = np.frombuffer(mapping, np.uint64)
            slots = slots[:len(slots) // width * width].reshape(-1, width)  # the pages may hold more
            owned = slots[:, _WORD_ID] != 0
            made = owned & (slots[:, _WORD_START] != 0)
            taken = slots[made]  # a copy, now: they move on
            self._waiting = slots[owned & ~made, _WORD_ID]
            del slots, owned, made  # no view of the mapping outlives it (closing it needs none)
        hashed = np.frombuffer(keys, np.uint64)
        twice = within(hashed, np.sort(taken[:, _WORD_ID]))
        if twice.any():
            hashed = hashed[~twice]
            values = np.frombuffer(values, np.uint64).reshape(len(twice), -1)[~twice].tobytes()
        self._hashed = set(hashed.tolist())
        return np.concatenate((hashed, taken[:, _WORD_ID])).tobytes(), values + taken.tobytes()

    def _looked_up(self, keys: np.ndarray) -> list[tuple[bytes, bytes | None]]:
        """(key, its entry or None if it has none) of each socket: in its slot, else in socket_traffic.
        One whose slot is being taken or given up waits for the next collect, as in socket_entries().
        A lookup each (a few hundred at most: past that the map is read whole); mapping the slots
        would cost more, in page faults."""
        slots, hashed = self.opened["socket_slots"], self.opened["socket_traffic"]
        changes, waiting = [], []
        for key, slot in zip(keys.tolist(), _slot_index(keys, slots.max_entries).tolist()):
            value = slots.lookup(_U32.pack(slot))
            if value is not None and _U64.unpack_from(value, _WORD_ID * 8)[0] == key:
                if not _U64.unpack_from(value, _WORD_START * 8)[0]:
                    waiting.append(key)
                    continue
                self._hashed.discard(key)  # an entry there was another socket's, at this address before
            else:
                value = hashed.lookup(_U64.pack(key))
                (self._hashed.discard if value is None else self._hashed.add)(key)
            changes.append((_U64.pack(key), value))
        self._waiting = np.array(waiting, np.uint64)
        return changes

    def _read_sockets(self) -> Matched:
        """The sockets' entries matched against the last collect's: those the programs marked
        changed looked up, or all read when many were, when the last collect was not kept, or while
        another process reads the marks."""
        marks = self.marks("socket_traffic")
        marked = None if marks is None else marks.changed(len(self._entries), whole=not self._entries.kept)
        if marked is None:
            m = self._entries.read(*self.socket_entries())
        else:
            keys = np.frombuffer(b"".join(marked), np.uint64)  # each once: a set's
            if len(self._waiting):
                keys = distinct(np.concatenate((keys, self._waiting)))
            m = self._entries.update(self._looked_up(keys))
        self.status.map_fill["socket_traffic"] = len(self._hashed) / self.opened["socket_traffic"].max_entries
        return m

    def collect(self, snap: Snapshot) -> None:
        pt = self.proctable
        # First: a collect that fails leaves sums the next cannot bring up to date.
        summed, self._entries_summed = self._entries_summed, False
        # Before the sockets: an entry the kernel deletes between the two reads is then missing
        # from both for this collect (which Monotonic holds back), never counted twice.
        closed_keys, closed_values, _ = self.read("closed_traffic")
        m = self._read_sockets()
        words = m.words
        if self._identity is None or not self._identity.holds(m):
            self._identity = _Identity(m)
        ident = self._identity
        pids, klass = ident.pids, ident.klass
        # Per process, not per socket: which are gone, and the names of the others. One that started
        # after the table's listing is not gone: forgetting its sockets would lose what they counted.
        names, dead = {}, []
        for pid in ident.owners:
            if pt.alive(pid):
                names[pid] = pt.name(pid)
            elif pt.belongs(pid):
                names[pid] = comm(pt.proc, pid)
            else:
                dead.append(pid)
        stale = among(pids, dead) | self._closed(m, pids, klass)
        forgotten = self._forget(m, np.flatnonzero(stale)) if stale.any() else {}
        live = ~stale
        self._entries.keep(m, live)
        # The entries' own arrays as a rule (no socket went): a copy a scrape of ten thousand sockets'
        # words costs page faults more than it saves. The next collect writes over them in place,
        # so what a reader keeps of the columns it copies.
        w = words if live.all() else words[live]
        labels = _Labels(w, names, self.proc_net_unix, self._labelled.turn())
        ids, dims, owners, ports = ident.of(live)
        snap.groups[SOCKET_GROUP] = Columns(
            ids, w[:, _WORDS_IDENTITY:_WORDS_COUNTS].view(np.int64), dims, PROTOCOLS, owners, labels, ports,
            stamps=labels.stamps, told=m.told() if live.all() else None)
        # The owners' sums: brought up to date by what the sockets counted since the last collect
        # when no socket came or went, else summed anew.
        if (live & ~m.same_head).any() or stale.any() or len(m.gone) or not summed:
            self._live_totals = _owned(owners, w[:, _WORD_START], dims, w[:, _WORDS_IDENTITY:_WORDS_COUNTS])
        else:
            for now, was in zip(words[m.grown].tolist(), m.before.tolist()):
                _add(self._live_totals, _owner(now), [a - b for a, b in zip(now[_WORDS_IDENTITY:_WORDS_COUNTS],
                                                                            was[_WORDS_IDENTITY:_WORDS_COUNTS])])
        self._entries_summed = True
        self._process_totals(snap, closed_keys, closed_values, forgotten)
        self.read_dropped()

    def _process_totals(self, snap: Snapshot, closed_keys: bytes, closed_values: bytes, forgotten: dict) -> None:
        """Per process and protocol: its live sockets' counts (_live_totals), what its closed sockets
        left in closed_traffic, and what this collect forgot since it read that. A process that
        ended shows its final totals once: the kernel keeps its closed_traffic until it is read
        here after the process ended, and deleted (unless a socket it owned folded into it since:
        then it shows again, and goes at the next collect)."""
        pt = self.proctable
        totals = dict(self._live_totals)
        for key, row in forgotten.items():
            _add(totals, key, row)
        ended, comms = [], {}
        size = _PROCESS_VALUE.size
        for i, ((tgid,), (start, *flat, comm)) in enumerate(zip(_U32.iter_unpack(closed_keys),
                                                                 _PROCESS_VALUE.iter_unpack(closed_values))):
            if not pt.alive(tgid):
                if pt.belongs(tgid):  # one that started after the table's listing: the next collect's
                    continue
                ended.append((closed_keys[4 * i: 4 * i + 4], closed_values[size * i: size * (i + 1)]))
                comms[tgid] = comm_text(comm)
            for klass in range(len(PROTOCOLS)):
                _add(totals, (tgid, start, klass), flat[6 * klass: 6 * klass + 6])
        if ended:
            self.opened["closed_traffic"].delete_unchanged(ended)
        # A PID's counts are those of its latest process (the highest start): what an earlier one
        # left is gone with it.
        latest: dict[int, int] = {}
        for tgid, start, _ in totals:
            latest[tgid] = max(start, latest.get(tgid, start))
        m, named = self._monotonic, self._named
        self._named = {}
        for (tgid, start, klass), row in totals.items():
            if latest[tgid] != start:
                continue
            if pt.alive(tgid):
                name = pt.name(tgid)
            elif pt.belongs(tgid):
                continue  # started after the table's listing: the next collect's
            else:  # ended: named as it was, or as the kernel last knew it
                name = named.get(tgid) or pt.ended_name(tgid) or comms.get(tgid, "")
            self._named[tgid] = name
            labels = (str(tgid), name, PROTOCOLS[klass])
            for c, value in zip(_COUNTS, row):
                snap.add(PROCESS[c], labels, m((c, tgid, start, klass), value))
        m.next_collect()

    def _forget(self, m: Matched, stale: np.ndarray) -> dict:
        """Forget the sockets that are gone (their process ended, or it holds them no more) as the
        kernel forgets a closed TCP socket: by a program of bpf/sockets.bpf.c, which folds their
        counts into their owners' closed_traffic, if their entries are still theirs. What it folded,
        as _owned() gives it: the closed_traffic this collect read has it not."""
        run, forgotten = self.programs["forget_gone"], {}
        for key, w in zip(m.keys[stale].tolist(), m.words[stale].tolist()):
            if bpffs.run_program(run, key, w[0], w[1] & 0xFFFFFFFF, w[_WORD_START]):
                _add(forgotten, _owner(w), w[_WORDS_IDENTITY:_WORDS_COUNTS])
        return forgotten

    def _closed(self, m: Matched, pids: np.ndarray, klass: np.ndarray) -> np.ndarray:
        """Entries of sockets the kernel freed without the programs' seeing it. Any but TCP is freed
        without a tracepoint: the process no longer holds the inode. A TCP one's CLOSE finds no entry
        when the socket's first call made it on another CPU at that moment (rare; seen under load):
        its inode is no longer among the namespace's TCP sockets. Only sockets idle since the last
        collect are checked, each process's at most once per FD_CHECK_INTERVAL and the TCP ones
        once per TCP_CHECK_INTERVAL, which keeps the reads few."""
        closed = self._tcp_closed(m, klass)
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

    def _tcp_closed(self, m: Matched, klass: np.ndarray) -> np.ndarray:
        """The idle TCP entries of this network namespace whose socket is gone: a sock_diag dump of
        the full sockets does not list its inode, nor does a lookup of its addresses find it. A
        socket its process closed (an orphan finishing its FIN, listed with inode 0) counts nothing
        more, and goes too. Those of other namespaces, which sock_diag cannot see, stay, and so do
        those without an inode (a kernel's socket)."""
        now = time.monotonic()
        if now - self._tcp_checked_at < TCP_CHECK_INTERVAL:
            return np.zeros(len(klass), bool)
        try:
            if self._netns is None:
                self._netns = int(sockdiag.own_netns())
            w = m.words
            idle = m.same & (klass == _TCP) & ((w[:, 1] >> np.uint64(32)) == self._netns) & (w[:, 0] != 0)
            if not idle.any():
                return idle
            listed = np.sort(sockdiag.dump_tcp_table(sockdiag.FULL_STATES)["inode"].astype(np.uint64))
            gone = idle & ~within(w[:, 0], listed)
            # A dump is no snapshot: read while other sockets come and go, it may skip a live one
            # (its position in a hash bucket moved between two reads). Each it did not list is
            # looked up by its addresses, which finds it if it is there.
            missed = np.flatnonzero(gone).tolist()
            for i, found in zip(missed, sockdiag.lookup_tcp([_addresses(w[i]) for i in missed])):
                gone[i] = found is None or found.inode != int(w[i, 0])
        except KernelError:
            return np.zeros(len(klass), bool)  # no sock_diag here: such entries wait for their owner's end
        finally:
            self._tcp_checked_at = now
        return gone
