"""sockets: real TCP, UDP and unix traffic between this test and child processes, counted by
bpf/sockets.bpf.c and checked against the byte and call counts the processes made themselves."""
from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from drums.budget import Budget
from drums.kernel import bpffs
from drums.metrics import Columns, Snapshot
from drums.probes import sockets
from drums.probes.sockets import _SOCKET_VALUE
from tests.conftest import (TEST_PIN_ROOT, connected_pairs, eventually, offered_paths, series, spliced_from,
                            started_on_path, wait_until)


@pytest.fixture(scope="module", params=offered_paths(sockets.SocketsProbe))
def sockets_probe(request, features, proctable):
    yield from started_on_path(sockets.SocketsProbe(features, proctable), request.param)


COUNTS = ("sent_bytes", "send_calls", "received_bytes", "receive_calls", "send_errors", "receive_errors")
ZERO = dict.fromkeys(COUNTS, 0)
NETNS = str(os.stat("/proc/self/ns/net").st_ino)
LOOPBACK = {socket.AF_INET: "127.0.0.1", socket.AF_INET6: "::1"}

# Every child starts with these helpers. Children report on stdout (a pipe, never a socket, so it
# adds nothing to what the probe counts) and wait for commands on stdin.
PRELUDE = r"""
import json, os, socket, sys, threading

def report(**kw):
    print(json.dumps(kw), flush=True)

def command():
    return sys.stdin.readline().strip()

def send_in_calls(sock, size, chunk):
    '''Send `size` bytes in calls of at most `chunk` bytes; return how many calls it took.'''
    data, calls = memoryview(b"d" * size), 0
    while data:
        data = data[sock.send(data[:chunk]):]
        calls += 1
    return calls

def inode(sock):
    return os.fstat(sock.fileno()).st_ino

def name(address):
    host, port = address[:2]
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
"""


class Child:
    """A Python child process running PRELUDE + code, with line-by-line JSON reports."""

    def __init__(self, code: str, *args, pass_fds=()):
        self.proc = subprocess.Popen([sys.executable, "-c", PRELUDE + code, *map(str, args)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, pass_fds=pass_fds)
        self.pid = self.proc.pid
        self._buffer = b""

    def read(self, timeout: float = 30.0) -> dict | None:
        """The next report, or None if none came within `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.proc.stdout], [], [], left)[0]:
                return None
            chunk = os.read(self.proc.stdout.fileno(), 65536)
            if not chunk:
                raise AssertionError(f"child {self.pid} ended (exit status {self.proc.wait()})")
            self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        return json.loads(line)

    def expect(self, timeout: float = 30.0) -> dict:
        report = self.read(timeout)
        assert report is not None, f"child {self.pid} reported nothing in {timeout} s"
        return report

    def tell(self, line: str = "") -> None:
        self.proc.stdin.write(line.encode() + b"\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        """Closing stdin ends the child; it is killed if it does not."""
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def spawn():
    """spawn(code, *args, pass_fds=()) -> Child; every child is ended when the test ends."""
    children = []

    def start(code, *args, pass_fds=()):
        children.append(Child(code, *args, pass_fds=pass_fds))
        return children[-1]

    yield start
    for child in children:
        child.close()


def name(address) -> str:
    """A socket address as the probe labels it: 127.0.0.1:5000, [::1]:5000."""
    host, port = address[:2]
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def comm(pid: int) -> str:
    with open(f"/proc/{pid}/comm") as f:
        return f.read().rstrip("\n")


def inode(sock: socket.socket) -> int:
    return os.fstat(sock.fileno()).st_ino


def socket_rows(snap, **labels) -> dict[tuple, dict[str, int]]:
    """Per-socket counts of the sockets whose labels match: label tuple -> {count: value}."""
    rows: dict[tuple, dict[str, int]] = {}
    for c in COUNTS:
        for lv, value in series(snap, f"drums_socket_{c}_total", **labels).items():
            rows.setdefault(lv, {})[c] = value
    return rows


def one_socket(snap, **labels) -> tuple[dict[str, str], dict[str, int]]:
    """The one socket matching `labels`: its labels by name, and its counts."""
    rows = socket_rows(snap, **labels)
    assert len(rows) == 1, f"expected one socket with {labels}, found {rows}"
    (lv, counts), = rows.items()
    keys = ("pid", "process", "protocol", "local", "remote", "netns", "inode")
    return dict(zip(keys, lv)), counts


def process_counts(snap, pid: int, protocol: str) -> dict[str, int]:
    """Process totals of one protocol; all zero if the process has none."""
    out = dict(ZERO)
    for c in COUNTS:
        rows = series(snap, f"drums_process_socket_{c}_total", pid=pid, protocol=protocol)
        assert len(rows) <= 1, rows
        out[c] = sum(rows.values())
    return out


def own_tcp_rows(snap) -> dict[int, dict[str, int]]:
    """Per-socket counts of this process's TCP sockets, by inode."""
    return {int(lv[-1]): counts for lv, counts in socket_rows(snap, pid=os.getpid(), protocol="tcp").items()}


def probe_entries(probe) -> dict[int, tuple]:
    """Socket id -> its entry, unpacked, of every entry the probe's maps hold."""
    keys, values = probe.socket_entries()
    return dict(zip((k for (k,) in struct.iter_unpack("<Q", keys)), _SOCKET_VALUE.iter_unpack(values)))


def recv_exactly(sock: socket.socket, size: int) -> int:
    """Receive `size` bytes; return the number of recv calls it took."""
    calls = 0
    while size > 0:
        got = len(sock.recv(min(size, 1 << 20)))
        assert got, "peer closed early"
        size -= got
        calls += 1
    return calls


def sent_over(pairs: list[tuple[socket.socket, socket.socket]]) -> dict[int, dict[str, int]]:
    """Send i bytes over the i-th connection (from 1): what each socket then counted, by inode."""
    expected = {}
    for i, (client, server) in enumerate(pairs, 1):
        client.sendall(b"s" * i)
        expected[inode(client)] = dict(ZERO, sent_bytes=i, send_calls=1)
        expected[inode(server)] = dict(ZERO, received_bytes=i, receive_calls=recv_exactly(server, i))
    return expected


def recv_to_eof(sock: socket.socket) -> tuple[int, int]:
    """Receive until the peer closes; return (bytes, calls), the final empty read included."""
    total = calls = 0
    while True:
        got = len(sock.recv(1 << 20))
        calls += 1
        total += got
        if not got:
            return total, calls




def tcp_listener(family=socket.AF_INET) -> socket.socket:
    lst = socket.socket(family, socket.SOCK_STREAM)
    lst.bind((LOOPBACK[family], 0))
    lst.listen(128)
    return lst


def reset(sock: socket.socket) -> None:
    """Close with SO_LINGER (on, 0): the kernel sends a reset instead of a FIN."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


# ---- exact bytes and calls, per socket and per process --------------------------------------

TCP_SENDER = r"""
s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
calls = send_in_calls(s, int(sys.argv[2]), int(sys.argv[3]))
report(calls=calls, local=name(s.getsockname()), remote=name(s.getpeername()), inode=inode(s))
command()
"""


@pytest.mark.kernel
def test_tcp_bytes_and_calls_of_both_ends(sockets_probe, collect, spawn):
    size, chunk = 1_000_003, 65_537
    with tcp_listener() as lst:
        child = spawn(TCP_SENDER, lst.getsockname()[1], size, chunk)
        conn, _ = lst.accept()
    with conn:
        recv_calls = recv_exactly(conn, size)
        sent = child.expect()
        assert sent["calls"] >= -(-size // chunk)
        snap = collect(sockets_probe)

        labels, counts = one_socket(snap, pid=child.pid, protocol="tcp")
        assert labels == {"pid": str(child.pid), "process": comm(child.pid), "protocol": "tcp",
                          "local": sent["local"], "remote": sent["remote"], "netns": NETNS,
                          "inode": str(sent["inode"])}
        assert counts == dict(ZERO, sent_bytes=size, send_calls=sent["calls"])

        labels, counts = one_socket(snap, pid=os.getpid(), inode=inode(conn))
        assert (labels["protocol"], labels["local"], labels["remote"], labels["netns"]) == (
            "tcp", name(conn.getsockname()), name(conn.getpeername()), NETNS)
        assert (labels["local"], labels["remote"]) == (sent["remote"], sent["local"])
        assert counts == dict(ZERO, received_bytes=size, receive_calls=recv_calls)

        assert process_counts(snap, child.pid, "tcp") == dict(ZERO, sent_bytes=size, send_calls=sent["calls"])


UDP_SENDER = r"""
family = socket.AF_INET6 if ":" in sys.argv[1] else socket.AF_INET
s = socket.socket(family, socket.SOCK_DGRAM)
s.bind((sys.argv[1], 0))
s.connect((sys.argv[1], int(sys.argv[2])))
report(local=name(s.getsockname()), remote=name(s.getpeername()), inode=inode(s))
command()
sizes = json.loads(sys.argv[3])
report(sent=[s.send(b"u" * n) for n in sizes])
command()
"""
DATAGRAMS = [1, 7, 512, 1399, 1472, 1473, 4097, 8191, 9001, 30_001]  # sums to 56,154: fits rmem


@pytest.mark.kernel
@pytest.mark.parametrize("family", [socket.AF_INET, socket.AF_INET6], ids=["ipv4", "ipv6"])
def test_connected_udp_datagrams(sockets_probe, collect, spawn, family):
    with socket.socket(family, socket.SOCK_DGRAM) as rx:
        rx.bind((LOOPBACK[family], 0))
        child = spawn(UDP_SENDER, LOOPBACK[family], rx.getsockname()[1], json.dumps(DATAGRAMS))
        peer = child.expect()
        rx.connect((LOOPBACK[family], int(peer["local"].rsplit(":", 1)[1])))
        assert name(rx.getpeername()) == peer["local"]
        child.tell("go")
        assert child.expect()["sent"] == DATAGRAMS
        rx.settimeout(5)
        assert [len(rx.recv(65536)) for _ in DATAGRAMS] == DATAGRAMS
        snap = collect(sockets_probe)
        total = sum(DATAGRAMS)

        labels, counts = one_socket(snap, pid=child.pid, protocol="udp")
        assert labels == {"pid": str(child.pid), "process": comm(child.pid), "protocol": "udp",
                          "local": peer["local"], "remote": peer["remote"], "netns": NETNS,
                          "inode": str(peer["inode"])}
        assert counts == dict(ZERO, sent_bytes=total, send_calls=len(DATAGRAMS))

        labels, counts = one_socket(snap, pid=os.getpid(), inode=inode(rx))
        assert (labels["protocol"], labels["local"], labels["remote"], labels["netns"]) == (
            "udp", name(rx.getsockname()), name(rx.getpeername()), NETNS)
        assert counts == dict(ZERO, received_bytes=total, receive_calls=len(DATAGRAMS))

        assert process_counts(snap, child.pid, "udp") == dict(ZERO, sent_bytes=total, send_calls=len(DATAGRAMS))


# Six threads pinned to CPU 1 send argv[1] datagrams each on one shared UDP socket while a
# SCHED_FIFO thread on that CPU wakes every half millisecond to send one too, preempting them. The
# child says what it sent once all have done.
PREEMPTED_SENDERS = r"""
import time
rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
rx.bind(("127.0.0.1", 0))
tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
tx.connect(rx.getsockname())
report(inode=inode(tx))
command()
each, sent, done = int(sys.argv[1]), [], threading.Event()
def sender(i):
    os.sched_setaffinity(0, {1})
    sent.append(sum(tx.send(b"s" * (1 + (i * 131 + n * 17) % 1400)) for n in range(each)))
def realtime():
    os.sched_setaffinity(0, {1})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    n = 0
    while not done.is_set():
        n += tx.send(b"r" * 9)
        time.sleep(0.0005)
    sent.append(n)
rt = threading.Thread(target=realtime)
rt.start()
senders = [threading.Thread(target=sender, args=(i,)) for i in range(6)]
for t in senders: t.start()
for t in senders: t.join()
done.set()
rt.join()
report(bytes=sum(sent), calls=6 * each + sent[-1] // 9)
command()
"""


@pytest.mark.kernel
@pytest.mark.skipif(1 not in os.sched_getaffinity(0), reason="needs CPU 1")
def test_threads_preempted_on_one_cpu_by_a_realtime_thread_are_counted_exactly(sockets_probe, collect, spawn):
    """Under PREEMPT_RT a program runs with migration, not preemption, disabled: a thread's call can
    be preempted amid its program by another thread's call on the same CPU and socket. Every add to a
    socket's entry is atomic, so none is lost (a plain add loses them there: tests/kernel/test_preemption.py)."""
    child = spawn(PREEMPTED_SENDERS, 2000)
    ino = child.expect()["inode"]
    child.tell("go")
    truth = child.expect(timeout=120)
    snap = collect(sockets_probe)
    _, counts = one_socket(snap, pid=child.pid, inode=ino)
    assert counts == dict(ZERO, sent_bytes=truth["bytes"], send_calls=truth["calls"]), truth
    assert process_counts(snap, child.pid, "udp") == counts


UNIX_SENDER = r"""
s = socket.socket(fileno=int(sys.argv[1]))
report(calls=send_in_calls(s, int(sys.argv[2]), int(sys.argv[3])))
command()
"""


@pytest.mark.kernel
def test_unix_stream_socketpair(sockets_probe, collect, spawn):
    size, chunk = 1_000_003, 100_003
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with mine, theirs:
        child = spawn(UNIX_SENDER, theirs.fileno(), size, chunk, pass_fds=(theirs.fileno(),))
        recv_calls = recv_exactly(mine, size)
        calls = child.expect()["calls"]
        snap = collect(sockets_probe)

        labels, counts = one_socket(snap, pid=child.pid, protocol="unix")
        assert labels == {"pid": str(child.pid), "process": comm(child.pid), "protocol": "unix",
                          "local": "", "remote": "", "netns": NETNS, "inode": str(inode(theirs))}
        assert counts == dict(ZERO, sent_bytes=size, send_calls=calls)

        labels, counts = one_socket(snap, pid=os.getpid(), inode=inode(mine))
        assert (labels["protocol"], labels["local"], labels["remote"]) == ("unix", "", "")
        assert counts == dict(ZERO, received_bytes=size, receive_calls=recv_calls)

        assert process_counts(snap, child.pid, "unix") == dict(ZERO, sent_bytes=size, send_calls=calls)


# ---- every way bytes cross a socket, and what a call is -------------------------------------------

class _Iovec(ctypes.Structure):
    _fields_ = [("base", ctypes.c_void_p), ("len", ctypes.c_size_t)]


class _Msghdr(ctypes.Structure):
    _fields_ = [("name", ctypes.c_void_p), ("namelen", ctypes.c_uint32), ("iov", ctypes.POINTER(_Iovec)),
                ("iovlen", ctypes.c_size_t), ("control", ctypes.c_void_p), ("controllen", ctypes.c_size_t),
                ("flags", ctypes.c_int)]


class _Mmsghdr(ctypes.Structure):
    _fields_ = [("hdr", _Msghdr), ("len", ctypes.c_uint)]


def mmsg(call: str, sock: socket.socket, count: int, size: int) -> int:
    """sendmmsg or recvmmsg of `count` datagrams of `size` bytes in one call; the datagrams it moved."""
    libc = ctypes.CDLL(None, use_errno=True)
    buffers = [ctypes.create_string_buffer(b"m" * size, size) for _ in range(count)]
    iovs = [_Iovec(ctypes.cast(b, ctypes.c_void_p), size) for b in buffers]
    msgs = (_Mmsghdr * count)(*(_Mmsghdr(_Msghdr(None, 0, ctypes.pointer(iov), 1, None, 0, 0), 0) for iov in iovs))
    n = libc.sendmmsg(sock.fileno(), msgs, count, 0) if call == "send" else \
        libc.recvmmsg(sock.fileno(), msgs, count, 0, None)
    assert n >= 0, os.strerror(ctypes.get_errno())
    return n


def received_in_thread(sock: socket.socket, size: int) -> threading.Thread:
    thread = threading.Thread(target=recv_exactly, args=(sock, size), daemon=True)
    thread.start()
    return thread


@pytest.mark.kernel
def test_each_way_of_sending_and_receiving_counts_its_bytes_once_and_its_calls_as_documented(
        sockets_probe, collect, tmp_path):
    """send, writev, sendmsg and a peek; sendfile; splice from and into a socket; sendmmsg and
    recvmmsg: bytes exact on every socket, and calls as the metrics' help says: one per call that
    moved data, one per datagram of sendmmsg and recvmmsg, and one per batch of pages that sendfile
    and splice hand the socket (the kernel's batches: at least one per system call, at most one a page)."""
    page, big = os.sysconf("SC_PAGE_SIZE"), 8 << 20
    data = tmp_path / "data"
    data.write_bytes(os.urandom(big))
    with contextlib.ExitStack() as stack, connected_pairs(4) as pairs:
        (plain, plain_rx), (sf, sf_rx), (sp, sp_rx), (into, into_rx) = pairs
        # One call each: send, writev of three buffers, sendmsg of two; a peek moves nothing.
        plain.send(b"s" * 1000)
        os.writev(plain.fileno(), [b"a" * 100, b"b" * 200, b"c" * 300])
        plain.sendmsg([b"d" * 400, b"e" * 500])
        assert len(plain_rx.recv(10, socket.MSG_PEEK)) == 10
        plain_calls = recv_exactly(plain_rx, 2500)
        # sendfile of 8 MiB from a file.
        reader = received_in_thread(sf_rx, big)
        f = stack.enter_context(open(data, "rb"))
        sent = sendfiles = 0
        while sent < big:
            sent += os.sendfile(sf.fileno(), f.fileno(), sent, big - sent)
            sendfiles += 1
        reader.join(30)
        # splice from a socket into a pipe, 4 MiB, and from a pipe into a socket, 1 MiB.
        r, w = os.pipe()
        stack.callback(os.close, r)
        stack.callback(os.close, w)
        splices = spliced_from(sp, sp_rx, 4 << 20, (r, w))
        reader = received_in_thread(into_rx, 1 << 20)
        spliced_in = splices_in = 0
        while spliced_in < 1 << 20:
            os.write(w, b"i" * 65536)
            left = 65536
            while left:
                left -= os.splice(r, into.fileno(), left)
                splices_in += 1
            spliced_in += 65536
        reader.join(30)
        # sendmmsg and recvmmsg of 32 datagrams each.
        udp_tx = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        udp_rx = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        udp_rx.bind(("127.0.0.1", 0))
        udp_tx.connect(udp_rx.getsockname())
        assert mmsg("send", udp_tx, 32, 100) == 32
        assert mmsg("recv", udp_rx, 32, 100) == 32
        snap = collect(sockets_probe)

        named = {"plain": plain, "plain_rx": plain_rx, "sendfile": sf, "sendfile_rx": sf_rx, "splice_tx": sp,
                 "splice_rx": sp_rx, "splice_into": into, "splice_into_rx": into_rx, "udp_tx": udp_tx, "udp_rx": udp_rx}
        if sockets_probe.caveat(sockets_probe.paths[0]):  # uncounted here: the socket has no other calls, no row
            assert not socket_rows(snap, pid=os.getpid(), inode=inode(sp_rx))
            del named["splice_rx"]
        found = {n: socket_rows(snap, pid=os.getpid(), inode=inode(s)) for n, s in named.items()}
        assert all(len(r) == 1 for r in found.values()), f"sockets without one row: {[n for n, r in found.items() if len(r) != 1]}"
        rows = {named[n]: next(iter(r.values())) for n, r in found.items()}
        assert rows[plain] == dict(ZERO, sent_bytes=2500, send_calls=3)
        assert rows[plain_rx] == dict(ZERO, received_bytes=2500, receive_calls=plain_calls)
        assert rows[sf]["sent_bytes"] == big and sendfiles <= rows[sf]["send_calls"] <= big // page
        if sp_rx in rows:
            assert rows[sp_rx] == dict(ZERO, received_bytes=4 << 20, receive_calls=splices)
        assert rows[into]["sent_bytes"] == 1 << 20 and splices_in <= rows[into]["send_calls"] <= (1 << 20) // page
        assert rows[udp_tx] == dict(ZERO, sent_bytes=3200, send_calls=32)
        assert rows[udp_rx] == dict(ZERO, received_bytes=3200, receive_calls=32)


@pytest.mark.kernel
def test_splice_reads_are_counted_where_asked_for_at_the_cost_said(sockets_probe, features, proctable, collect):
    """splice(2) from a TCP and a unix stream socket counted exactly: by each path's own programs
    (kprobes on the tracepoint paths where the kernel has them), and on the tracepoint paths of a
    kernel without kprobes, where it is not counted (doctor and the agent's log say so), by the
    syscall tracepoints of `drums agent --splice-tracepoints`."""
    from drums.probes.registry import held_to
    path, probe = sockets_probe.status.attach_type, sockets_probe
    uncounted = path in sockets.TRACEPOINT_PATHS and not features.kprobes
    assert bool(probe.caveat(probe.paths[0])) == uncounted
    if uncounted:
        probe = held_to(sockets.SocketsProbe(features, proctable, splice_tracepoints=True,
                                             pin_root=f"{TEST_PIN_ROOT}_splice_{path}"), path)
        assert probe.splice_reads == sockets.SPLICE_BY_SYSCALLS and not probe.caveat(probe.paths[0])
        probe.start()
    r, w = os.pipe()
    try:
        with connected_pairs(1) as [(tcp_tx, tcp_rx)]:
            unix_tx, unix_rx = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
            with unix_tx, unix_rx:
                splices = {tcp_rx: spliced_from(tcp_tx, tcp_rx, 3 << 20, (r, w)),
                           unix_rx: spliced_from(unix_tx, unix_rx, 1 << 20, (r, w))}
                snap = collect(probe)
                for rx, size in ((tcp_rx, 3 << 20), (unix_rx, 1 << 20)):
                    (row,) = socket_rows(snap, pid=os.getpid(), inode=inode(rx)).values()
                    assert row == dict(ZERO, received_bytes=size, receive_calls=splices[rx])
    finally:
        os.close(r)
        os.close(w)
        if probe is not sockets_probe:
            probe.unload()


# ---- closed sockets fold into the process totals ----------------------------------------------

MANY_SENDER = r"""
port, count, size, chunk = map(int, sys.argv[1:5])
calls, locals_ = 0, []
for _ in range(count):
    with socket.create_connection(("127.0.0.1", port)) as s:
        calls += send_in_calls(s, size, chunk)
        locals_.append(name(s.getsockname()))
report(calls=calls, local=locals_)
command()
"""


def many_sent(spawn, count: int, size: int, chunk: int) -> tuple[Child, dict]:
    """A child that sent `size` bytes over each of `count` connections, one after the other, all
    closed now by both ends; and what it said it sent."""
    with tcp_listener() as lst:
        child = spawn(MANY_SENDER, lst.getsockname()[1], count, size, chunk)
        for _ in range(count):
            conn, _ = lst.accept()
            with conn:
                assert recv_to_eof(conn)[0] == size
    return child, child.expect()


@pytest.mark.kernel
def test_closed_connections_fold_into_process_totals(sockets_probe, collect, spawn):
    count, size, chunk = 7, 200_003, 40_009
    child, sent = many_sent(spawn, count, size, chunk)
    assert len(set(sent["local"])) == count

    def folded():
        snap = collect(sockets_probe)
        assert socket_rows(snap, pid=child.pid) == {}
        assert {lv: c for lv, c in socket_rows(snap, pid=os.getpid(), protocol="tcp").items()
                if lv[4] in sent["local"]} == {}
        return snap

    snap = eventually(folded)
    assert process_counts(snap, child.pid, "tcp") == dict(ZERO, sent_bytes=count * size, send_calls=sent["calls"])


def test_a_process_that_started_after_the_listing_keeps_what_its_closed_sockets_counted(sockets_probe, collect,
                                                                                         spawn, proctable):
    """The agent lists the processes, then reads the sockets: one that started in between is not in
    the table, yet alive. What its closed sockets left in closed_traffic is not deleted as a dead
    process's: the next collect, which knows the process, has every byte."""
    count, size = 3, 100_003
    proctable.refresh()
    child, sent = many_sent(spawn, count, size, size)

    def folded():  # by the kernel: the child's sockets have no entries left
        assert [v for v in probe_entries(sockets_probe).values() if v[1] == child.pid] == []
    eventually(folded)
    assert not proctable.alive(child.pid)
    sockets_probe.collect(Snapshot())  # against the listing made before the child started
    assert process_counts(collect(sockets_probe), child.pid, "tcp") == dict(
        ZERO, sent_bytes=count * size, send_calls=sent["calls"])


CLOSING_SENDER = r"""
port, rounds = int(sys.argv[1]), int(sys.argv[2])
sent = {"udp": [0, 0], "unix": [0, 0]}  # bytes, calls
for i in range(rounds):
    # Each socket is closed at once: the next one is likely to get its struct sock.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
        sent["udp"][0] += u.sendto(b"u" * (100 + i), ("127.0.0.1", port))
        sent["udp"][1] += 1
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    with a, b:
        sent["unix"][0] += a.send(b"x" * (200 + i))
        sent["unix"][1] += 1
        b.recv(1000)
report(sent=sent)
command()
"""


def test_closed_udp_and_unix_sockets_stay_in_their_process_totals(sockets_probe, collect, spawn, monkeypatch):
    """Such sockets are freed without a tracepoint: the kernel folds an entry when the next socket
    gets its struct sock, and the probe folds those it finds closed (their process holds the inode
    no more). Either way the process's totals keep them, from the first collect on."""
    monkeypatch.setattr(sockets, "FD_CHECK_INTERVAL", 0.0)  # the probe looks for closed sockets at each collect
    rounds = 40
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        child = spawn(CLOSING_SENDER, rx.getsockname()[1], rounds)
        sent = child.expect()["sent"]
    (udp_bytes, udp_calls), (unix_bytes, unix_calls) = sent["udp"], sent["unix"]
    assert udp_bytes == sum(100 + i for i in range(rounds))
    unix = dict(ZERO, sent_bytes=unix_bytes, send_calls=unix_calls, received_bytes=unix_bytes,
                receive_calls=unix_calls)
    for _ in range(3):
        snap = collect(sockets_probe)
        assert process_counts(snap, child.pid, "udp") == dict(ZERO, sent_bytes=udp_bytes, send_calls=udp_calls)
        assert process_counts(snap, child.pid, "unix") == unix
    assert socket_rows(snap, pid=child.pid) == {}  # all found closed


STEADY_SENDER = r"""
port = int(sys.argv[1])
udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
tcp = socket.create_connection(("127.0.0.1", port))
report(ready=True)
while (line := command()):
    size = int(line)
    udp.sendto(b"u" * size, ("127.0.0.1", port))
    report(calls=send_in_calls(tcp, 3 * size, 65_536))
"""


def test_process_totals_follow_sockets_that_keep_counting(sockets_probe, collect, spawn):
    """Between two collects most sockets of a process only count further: its totals are brought up
    to date by what those grew, and stay exact step after step."""
    with tcp_listener() as lst, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", lst.getsockname()[1]))
        child = spawn(STEADY_SENDER, lst.getsockname()[1])
        conn, _ = lst.accept()
        with conn:
            assert child.expect() == {"ready": True}
            udp, tcp = dict(ZERO), dict(ZERO)
            for step in range(1, 9):
                size = 1_000 * step + 7
                child.tell(str(size))
                calls = child.expect()["calls"]
                recv_exactly(conn, 3 * size)
                rx.recv(65_536)
                udp = dict(udp, sent_bytes=udp["sent_bytes"] + size, send_calls=udp["send_calls"] + 1)
                tcp = dict(tcp, sent_bytes=tcp["sent_bytes"] + 3 * size, send_calls=tcp["send_calls"] + calls)
                snap = collect(sockets_probe)
                assert (process_counts(snap, child.pid, "udp"), process_counts(snap, child.pid, "tcp")) == (udp, tcp)


HANDED_ON = r"""
s = socket.socket(fileno=int(sys.argv[1]))
report(calls=send_in_calls(s, int(sys.argv[2]), 10_007))
command()
"""


def test_a_socket_handed_to_another_process_counts_for_the_one_that_used_it_first(sockets_probe, collect, spawn):
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with mine, theirs:
        theirs.send(b"f" * 1_000)  # this process uses it first
        recv_exactly(mine, 1_000)
        child = spawn(HANDED_ON, theirs.fileno(), 50_000, pass_fds=(theirs.fileno(),))
        recv_exactly(mine, 50_000)
        calls = child.expect()["calls"]
        snap = collect(sockets_probe)
        _, counts = one_socket(snap, pid=os.getpid(), inode=inode(theirs))
    assert counts == dict(ZERO, sent_bytes=51_000, send_calls=1 + calls)
    assert process_counts(snap, child.pid, "unix") == ZERO


# ---- 10,000 short connections: totals never go backwards, the map does not grow ---------------

CHURN_SERVER = r"""
lst = socket.socket()
lst.bind(("127.0.0.1", 0))
lst.listen(1024)
report(port=lst.getsockname()[1])
count = int(sys.argv[1])
received = calls = 0
for _ in range(count):
    conn, _ = lst.accept()
    while True:
        got = len(conn.recv(65536))
        calls += 1
        received += got
        if not got:
            break
    conn.close()
report(received=received, calls=calls)
command()
"""
CHURN_CLIENT = r"""
port, count, size = map(int, sys.argv[1:4])
calls = 0
for _ in range(count):
    s = socket.create_connection(("127.0.0.1", port))
    calls += send_in_calls(s, size, size)
    s.close()
report(calls=calls)
command()
"""


def process_totals(snap, pids) -> dict[tuple, int]:
    """(metric, pid, protocol) -> value, for every process total of these processes."""
    out = {}
    for c in COUNTS:
        for pid in pids:
            for lv, value in series(snap, f"drums_process_socket_{c}_total", pid=pid).items():
                out[(c, pid, lv[2])] = value
    return out


def test_ten_thousand_short_connections(sockets_probe, collect, spawn, monkeypatch):
    monkeypatch.setattr(sockets, "TCP_CHECK_INTERVAL", 0.0)  # drained() below: see there
    count, size = 10_000, 1_001
    server = spawn(CHURN_SERVER, count)
    client = spawn(CHURN_CLIENT, server.expect()["port"], count, size)
    pids = (client.pid, server.pid)
    samples = [process_totals(collect(sockets_probe), pids)]
    done = None
    while done is None:
        done = client.read(timeout=0.05)
        samples.append(process_totals(collect(sockets_probe), pids))
    served = server.expect()
    samples.append(process_totals(collect(sockets_probe), pids))

    assert len(samples) >= 5, "the run ended before the probe could be sampled during it"
    for before, after in zip(samples, samples[1:]):
        went_back = {k: (before[k], after.get(k)) for k in before if after.get(k, -1) < before[k]}
        assert went_back == {}
    assert served["received"] == count * size

    # Exact once the sockets closed: a collect that comes while some move from the live map to their
    # process's closed_traffic misses them (held back, never counted twice); the next has them
    # (a fresh-clone run missed 18 of 10,000 at the collect right after the server was done).
    def exact():
        final = process_totals(collect(sockets_probe), pids)
        assert (final[("sent_bytes", client.pid, "tcp")], final[("send_calls", client.pid, "tcp")]) == (
            count * size, done["calls"])
        assert (final[("received_bytes", server.pid, "tcp")], final[("receive_calls", server.pid, "tcp")]) == (
            count * size, served["calls"])
        assert final[("received_bytes", client.pid, "tcp")] == final[("sent_bytes", server.pid, "tcp")] == 0
    eventually(exact, timeout=30)

    # Every connection closed, so the map holds no entry of either process: not one of the 20,000
    # sockets is left behind. (Counted per process: the whole map's size also moves with whatever
    # else runs on the host.) A socket leaves the map when the kernel frees it, after its FIN is
    # acknowledged: on a host busy with the whole suite, 102 of them were still closing after 3 s
    # (one way: a FIN dropped from a full loopback backlog is sent again after 0.2, 0.4, 0.8 s...).
    def drained():
        collect(sockets_probe)  # which forgets any entry whose CLOSE the programs missed
        assert [v for v in probe_entries(sockets_probe).values() if v[1] in pids] == []  # v[1]: the process
    eventually(drained, timeout=30)


# ---- threads ---------------------------------------------------------------------------------

THREADS_SENDER = r"""
port = int(sys.argv[1])
sizes = list(map(int, sys.argv[2:4]))
stops = [threading.Event() for _ in sizes]
lock = threading.Lock()

def work(i):
    s = socket.create_connection(("127.0.0.1", port))
    calls = send_in_calls(s, sizes[i], 30_011)
    with lock:
        report(thread=i, tid=threading.get_native_id(), calls=calls)
    stops[i].wait()
    s.close()

threads = [threading.Thread(target=work, args=(i,)) for i in range(len(sizes))]
for t in threads:
    t.start()
while (line := command()):
    i = int(line)
    stops[i].set()
    threads[i].join()
    report(joined=i)
for stop in stops:  # stdin closed: end
    stop.set()
"""


def drain(conns: list[socket.socket], total: int) -> None:
    """Read from several connections at once until `total` bytes arrived over all of them."""
    while total:
        for conn in select.select(conns, [], [], 10)[0]:
            got = len(conn.recv(1 << 20))
            assert got, "peer closed early"
            total -= got


@pytest.mark.kernel
def test_the_sockets_of_every_thread_count_for_the_process_and_stay_when_it_exits(sockets_probe, collect, spawn):
    sizes = (300_007, 700_001)
    with tcp_listener() as lst:
        child = spawn(THREADS_SENDER, lst.getsockname()[1], *sizes)
        conns = [lst.accept()[0], lst.accept()[0]]
    try:
        drain(conns, sum(sizes))
        reports = sorted((child.expect(), child.expect()), key=lambda r: r["thread"])
        tids = [r["tid"] for r in reports]
        assert child.pid not in tids and len(set(tids)) == 2

        snap = collect(sockets_probe)
        assert sorted(c["sent_bytes"] for c in socket_rows(snap, pid=child.pid, protocol="tcp").values()) == sorted(sizes)
        calls = sum(r["calls"] for r in reports)
        assert process_counts(snap, child.pid, "tcp") == dict(ZERO, sent_bytes=sum(sizes), send_calls=calls)

        # The first thread exits: its bytes stay in the process totals.
        child.tell("0")
        assert child.expect() == {"joined": 0}
        # join() returns before the kernel thread is through do_exit; its /proc entry goes after.
        wait_until(lambda: not os.path.exists(f"/proc/{child.pid}/task/{tids[0]}"), "the thread to exit")
        snap = collect(sockets_probe)
        assert process_counts(snap, child.pid, "tcp") == dict(ZERO, sent_bytes=sum(sizes), send_calls=calls)
    finally:
        for conn in conns:
            conn.close()


# ---- errors ----------------------------------------------------------------------------------

ERRORS_CHILD = r"""
port = int(sys.argv[1])
failed = {"udp": [], "tcp": []}
would_block = 0

def attempt(kind, call, *args):
    global would_block
    try:
        call(*args)
    except BlockingIOError:
        would_block += 1
    except OSError as e:
        failed[kind].append(e.errno)
    else:
        raise SystemExit(f"{call} succeeded")

udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
for _ in range(3):
    attempt("udp", udp.send, b"no address")  # EDESTADDRREQ
attempt("udp", udp.sendto, b"port 0", ("127.0.0.1", 0))  # EINVAL
udp.setblocking(False)
for _ in range(4):
    attempt("udp", udp.recv, 100)  # EAGAIN

doomed = socket.create_connection(("127.0.0.1", port))
idle = socket.create_connection(("127.0.0.1", port))
report(doomed=inode(doomed), idle=inode(idle), udp=inode(udp))
command()  # the parent has reset `doomed`
for _ in range(3):
    attempt("tcp", doomed.send, b"too late")  # ECONNRESET, then EPIPE
idle.setblocking(False)
for _ in range(5):
    attempt("tcp", idle.recv, 100)  # EAGAIN
report(failed=failed, would_block=would_block)
command()
"""


@pytest.mark.kernel
def test_failed_calls_are_errors_and_eagain_is_not(sockets_probe, collect, spawn):
    with tcp_listener() as lst:
        child = spawn(ERRORS_CHILD, lst.getsockname()[1])
        doomed, _ = lst.accept()
        idle, _ = lst.accept()
    with idle:
        inodes = child.expect()
        reset(doomed)
        child.tell("go")
        result = child.expect()
        assert result["failed"] == {"udp": [errno.EDESTADDRREQ] * 3 + [errno.EINVAL],
                                    "tcp": [errno.ECONNRESET, errno.EPIPE, errno.EPIPE]}
        assert result["would_block"] == 4 + 5
        snap = collect(sockets_probe)

        assert process_counts(snap, child.pid, "udp") == dict(ZERO, send_errors=4)
        assert process_counts(snap, child.pid, "tcp") == dict(ZERO, send_errors=3)
        _, counts = one_socket(snap, pid=child.pid, inode=inodes["udp"])
        assert counts == dict(ZERO, send_errors=4)
        # Only EAGAIN ever happened on the idle connection: nothing to count, so no series.
        assert socket_rows(snap, pid=child.pid, inode=inodes["idle"]) == {}


# A UDP receiver and a TCP sender, each blocked in its call while the test stops and continues it
# and interrupts it with a handled signal (SA_RESTART): the kernel restarts each call, and the
# application sees no error. It counts its own successful calls.
BLOCKED_CHILD = r"""
import signal
signal.signal(signal.SIGUSR1, lambda *_: None)
signal.siginterrupt(signal.SIGUSR1, False)
u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
u.bind(("127.0.0.1", 0))
t = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
t.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
report(port=u.getsockname()[1], udp=inode(u), tcp=inode(t))
got = u.recv(100)
report(received=len(got))
data, calls = memoryview(b"b" * int(sys.argv[2])), 0
while data:
    data = data[t.send(data):]
    calls += 1
report(calls=calls)
command()
"""


def blocked(pid: int) -> bool:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0] == "S"


def stop_and_interrupt(pid: int) -> None:
    """Three stops and continues, then three handled signals, each while the process is blocked."""
    for sig in [signal.SIGSTOP] * 3 + [signal.SIGUSR1] * 3:
        wait_until(lambda: blocked(pid), "the child to block in its call", timeout=30)
        time.sleep(0.05)
        os.kill(pid, sig)
        if sig == signal.SIGSTOP:
            wait_until(lambda: not blocked(pid), "the child to stop", timeout=30)
            os.kill(pid, signal.SIGCONT)


@pytest.mark.kernel
def test_calls_that_the_kernel_restarts_after_a_signal_are_no_errors(sockets_probe, collect, spawn):
    size = 4 << 20
    with tcp_listener() as lst:
        lst.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        child = spawn(BLOCKED_CHILD, lst.getsockname()[1], size)
        peer, _ = lst.accept()
    with peer:
        where = child.expect()
        stop_and_interrupt(child.pid)  # blocked in recv
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
            u.sendto(b"0123456789", ("127.0.0.1", where["port"]))
        assert child.expect() == {"received": 10}
        stop_and_interrupt(child.pid)  # blocked in send: the test has not read yet
        got = 0
        while got < size:
            got += len(peer.recv(1 << 20))
        calls = child.expect()["calls"]
        snap = collect(sockets_probe)
        assert one_socket(snap, pid=child.pid, inode=where["udp"])[1] == dict(ZERO, received_bytes=10, receive_calls=1)
        assert one_socket(snap, pid=child.pid, inode=where["tcp"])[1] == dict(ZERO, sent_bytes=size, send_calls=calls)


# ---- a TCP socket used after the kernel closed it -------------------------------------------------

def use_after_reset(lst: socket.socket) -> int:
    """Connect, have the peer reset, fail to send twice, close; return the socket's inode.

    The reset moves the socket to TCP_CLOSE, which deletes its entry; the failed sends then come
    from a socket in CLOSE, as they do in every program before it notices the reset."""
    c = socket.create_connection(lst.getsockname())
    reset(lst.accept()[0])
    with c:
        for _ in range(2):
            with pytest.raises(OSError):
                c.send(b"x")
        return inode(c)


def test_socket_used_after_a_reset_is_forgotten_when_closed(sockets_probe, collect):
    with tcp_listener() as lst:
        gone = use_after_reset(lst)
    assert socket_rows(collect(sockets_probe), pid=os.getpid(), inode=gone) == {}


def test_next_socket_does_not_inherit_a_socket_used_after_reset(sockets_probe, collect):
    with tcp_listener() as lst:
        use_after_reset(lst)
        for _ in range(5):  # the freed struct sock is usually the next TCP socket's
            with socket.create_connection(lst.getsockname()) as c, lst.accept()[0]:
                c.sendall(b"y" * 1234)
                rows = socket_rows(collect(sockets_probe), pid=os.getpid(), protocol="tcp")
                carrying = {(lv[3], lv[6]) for lv, counts in rows.items() if counts["sent_bytes"] == 1234}
                assert carrying == {(name(c.getsockname()), str(inode(c)))}


def lose_a_mark(probe) -> None:
    """Count a mark lost to a full set, as the programs do: the probe's next collect reads the maps
    whole, and so sees what a test changed in them behind the programs' backs."""
    generation, lost = probe.opened["generation"], struct.pack("<I", 1)
    generation.update(lost, struct.pack("<Q", struct.unpack("<Q", generation.lookup(lost))[0] + 1))


@contextlib.contextmanager
def planted_where_sockets_closed(probe, n: int):
    """Entries planted in socket_traffic at the addresses of the 2n sockets of n connections of this
    process that closed (and whose entries went): each as its socket's entry was, counting one send
    of 777 bytes. Yields them by id. After, those left are forgotten as the agent forgets a socket
    (their counts to their owner, whose totals stay monotonic for the tests that follow)."""
    with connected_pairs(n) as pairs:
        for client, server in pairs:
            client.sendall(b"p")
            recv_exactly(server, 1)
        inodes = {inode(sock) for pair in pairs for sock in pair}
        old = {key: v for key, v in probe_entries(probe).items() if v[0] in inodes}
    assert len(old) == 2 * n

    def closed():
        assert old.keys() & probe_entries(probe).keys() == set()
    eventually(closed, timeout=30)
    planted = {key: v[:12] + (777, 1, 0, 0, 0, 0, 0, v[19], 0) for key, v in old.items()}  # identity, counts, start
    hashed = probe.opened["socket_traffic"]
    for key, v in planted.items():
        hashed.update(struct.pack("<Q", key), _SOCKET_VALUE.pack(*v))
    lose_a_mark(probe)
    try:
        yield planted
    finally:
        for key, v in planted.items():
            bpffs.run_program(probe.programs["forget_gone"], key, v[0], v[1], v[19])
        lose_a_mark(probe)


def test_a_new_connection_does_not_take_the_entry_an_earlier_socket_left_at_its_address(sockets_probe, collect):
    """A TCP socket's calls count into the entry at its address, its inode unchecked: an entry that
    lost its CLOSE (its socket's first call raced with it) would take the counts of the next socket
    there. Every socket that connects, listens or is accepted forgets what is at its address first.
    Here entries are planted where closed sockets were: the new sockets that get those addresses
    count for themselves, and each planted entry is either still as planted or gone (to its owner)."""
    with planted_where_sockets_closed(sockets_probe, 20) as planted, connected_pairs(20) as pairs:
        expected = sent_over(pairs)
        rows = own_tcp_rows(collect(sockets_probe))
        assert {ino: rows.get(ino) for ino in expected} == expected
        now = probe_entries(sockets_probe)
        assert {key for key, v in now.items() if v[0] in expected} & planted.keys(), \
            "no new socket got the address of a planted entry: nothing was tested"
        assert {key: now[key] for key in planted.keys() & now.keys() if now[key] != planted[key]
                and now[key][0] not in expected} == {}


def test_a_tcp_entry_whose_close_went_unseen_goes_and_its_counts_stay_with_its_owner(sockets_probe, collect, monkeypatch):
    """A TCP entry goes when its socket reaches CLOSE; one made by a call that raced with the CLOSE
    on another CPU is not found then (a few in 10,000 connections on a loaded host). The probe finds
    such an entry, once idle, by its inode missing from the namespace's TCP sockets, and forgets it:
    what it held stays in its owner's totals. Here each entry of 20 idle sockets of this process is
    made one of an earlier socket (an inode no socket has) that sent 777 bytes more: at addresses
    these sockets hold, no other socket can take them while the test runs."""
    monkeypatch.setattr(sockets, "TCP_CHECK_INTERVAL", 0.0)  # checked at each collect
    before = process_counts(collect(sockets_probe), os.getpid(), "tcp")
    slots, hashed = sockets_probe.opened["socket_slots"], sockets_probe.opened["socket_traffic"]
    with connected_pairs(10) as pairs:
        for client, server in pairs:
            client.sendall(b"p")
            recv_exactly(server, 1)
        inodes = {inode(sock) for pair in pairs for sock in pair}
        made = {key: v for key, v in probe_entries(sockets_probe).items() if v[0] in inodes}
        assert len(made) == 20
        earlier = {}
        for i, (key, v) in enumerate(made.items()):
            earlier[key] = (1 << 40) + i, *v[1:12], v[12] + 777, v[13] + 1, *v[14:]  # inode, ..., sent bytes, calls
            if v[-1]:  # v[-1]: the slot's owner
                slot = int(sockets._slot_index(np.array([key], np.uint64), slots.max_entries)[0])
                slots.update(struct.pack("<I", slot), _SOCKET_VALUE.pack(*earlier[key]))
            else:
                hashed.update(struct.pack("<Q", key), _SOCKET_VALUE.pack(*earlier[key]))
        lose_a_mark(sockets_probe)  # written behind the programs' backs: the next collect reads all
        collect(sockets_probe)  # finds them: changed, so not yet checked
        assert {key: probe_entries(sockets_probe).get(key) for key in earlier} == earlier
        after = process_counts(collect(sockets_probe), os.getpid(), "tcp")
        assert earlier.keys() & probe_entries(sockets_probe).keys() == set()
    # The connections' ten 1-byte sends and receives, and the twenty earlier sockets' sends.
    assert after == dict(before, sent_bytes=before["sent_bytes"] + 10 + 20 * 777, send_calls=before["send_calls"] + 30,
                         received_bytes=before["received_bytes"] + 10, receive_calls=before["receive_calls"] + 10)


def test_a_live_tcp_socket_that_the_dump_missed_keeps_its_entry(sockets_probe, collect, monkeypatch):
    """A sock_diag dump read while sockets come and go may skip a live one: the check of TCP entries
    looks up each socket the dump did not list before forgetting it. Here the dump lists none, and
    the idle sockets of 10 live connections keep their entries and series."""
    monkeypatch.setattr(sockets, "TCP_CHECK_INTERVAL", 0.0)  # checked at each collect
    monkeypatch.setattr(sockets.sockdiag, "dump_tcp_table", lambda states: np.empty(0, sockets.sockdiag.DIAG_RECORD))
    with connected_pairs(10) as pairs:
        expected = sent_over(pairs)
        collect(sockets_probe)
        rows = own_tcp_rows(collect(sockets_probe))  # idle since the last: checked
        assert {ino: rows.get(ino) for ino in expected} == expected
        assert {v[0] for v in probe_entries(sockets_probe).values()} >= expected.keys()


# ---- a thread that execs ------------------------------------------------------------------------

EXEC_FROM_THREAD = r"""
import time
s = socket.socket(fileno=int(sys.argv[1]))
def sender():
    report(tid=threading.get_native_id(), calls=send_in_calls(s, int(sys.argv[2]), 4096))
    command()
    # The kernel gives the leader's PID to this thread, and ends every other thread.
    os.execv(sys.executable, [sys.executable, "-c", "import sys; print('{}', flush=True); sys.stdin.read()"])
threading.Thread(target=sender).start()
while True:
    time.sleep(1)
"""


def test_thread_that_execs_keeps_its_bytes_in_the_process(sockets_probe, collect, spawn):
    size = 300_007
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with mine, theirs:
        child = spawn(EXEC_FROM_THREAD, theirs.fileno(), size, pass_fds=(theirs.fileno(),))
        recv_exactly(mine, size)
        sender = child.expect()
        sent = dict(ZERO, sent_bytes=size, send_calls=sender["calls"])
        assert process_counts(collect(sockets_probe), child.pid, "unix") == sent
        child.tell("exec")
        assert child.expect() == {}  # the new program runs under the same PID, its start time unchanged
        assert process_counts(collect(sockets_probe), child.pid, "unix") == sent


# ---- unix socket names ----------------------------------------------------------------------------

UNIX_NAMED_SENDER = r"""
s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
s.bind(sys.argv[1] if sys.argv[1][0] != "@" else "\0" + sys.argv[1][1:])
s.connect(sys.argv[2])
s.send(b"n" * int(sys.argv[3]))
report(inode=inode(s))
command()
"""


@pytest.mark.parametrize("kind", ["path", "abstract"])
def test_unix_sockets_are_named_by_their_bound_path(sockets_probe, collect, spawn, tmp_path, kind):
    size = 4_321
    receiver_path = str(tmp_path / "receiver")
    sender_name = str(tmp_path / "sender") if kind == "path" else f"@drums-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as receiver:
        receiver.bind(receiver_path)
        child = spawn(UNIX_NAMED_SENDER, sender_name, receiver_path, size)
        assert len(receiver.recv(65536)) == size
        sent = child.expect()
        snap = collect(sockets_probe)
        labels, counts = one_socket(snap, pid=child.pid, inode=sent["inode"])
        assert (labels["protocol"], labels["local"]) == ("unix", sender_name)
        assert counts == dict(ZERO, sent_bytes=size, send_calls=1)
        labels, counts = one_socket(snap, pid=os.getpid(), inode=inode(receiver))
        assert labels["local"] == receiver_path and counts["received_bytes"] == size


def test_a_collect_looks_up_the_sockets_that_changed_and_keeps_the_idle_ones(sockets_probe, collect):
    """bpf/sockets.bpf.c marks each socket it counts into or deletes; a collect looks up those, and
    the rows of the idle ones stand as they were. 300 connections of this process each send once;
    then, step after step, one sends and one closes. Each step's rows are exact; other tests'
    traffic on the host may tip a collect into reading the map whole, so steps are taken until
    enough of them were looked up."""
    with connected_pairs(300) as pairs:
        for client, server in pairs:
            client.sendall(b"x")
            recv_exactly(server, 1)
        collect(sockets_probe)  # 600 sockets new to the map: looked up, or the map read whole
        expected = {inode(s): counts for s, counts in
                    [(c, dict(ZERO, sent_bytes=1, send_calls=1)) for c, _ in pairs]
                    + [(s, dict(ZERO, received_bytes=1, receive_calls=1)) for _, s in pairs]}

        def rows() -> dict[int, dict]:
            return {int(labels[-1]): counts for labels, counts in
                    socket_rows(collect(sockets_probe), pid=os.getpid(), protocol="tcp").items()
                    if int(labels[-1]) in inodes}
        inodes = set(expected)
        assert rows() == expected
        traffic, looked_up = sockets_probe._marked["socket_traffic"], 0
        for step in range(1, 60):
            client, server = pairs[step]
            client.sendall(b"y" * step)
            calls = recv_exactly(server, step)
            expected[inode(client)] = dict(ZERO, sent_bytes=1 + step, send_calls=2)
            expected[inode(server)] = dict(ZERO, received_bytes=1 + step, receive_calls=1 + calls)
            closing = pairs[-step]
            for sock in closing:
                del expected[inode(sock)]
                sock.close()
            whole = traffic.whole_reads

            def exact() -> None:  # a closed connection's entries go as the kernel finishes closing it
                assert rows() == expected, step
            eventually(exact, timeout=5)
            looked_up += traffic.whole_reads == whole
            if looked_up >= 20:
                break
        assert looked_up >= 20


def test_sockets_in_their_slots_and_those_whose_slot_was_taken_count_alike(sockets_probe, collect, monkeypatch):
    """A socket's entry is in its slot of an array (by a hash of its id) when that is free, else in
    socket_traffic: of 2,000 connections' 4,000 sockets, hundreds find their slot taken (16,384
    slots), so both kinds are here. Each counts exactly what it sent and received; each entry goes
    when its socket closes."""
    monkeypatch.setattr(sockets, "TCP_CHECK_INTERVAL", 0.0)  # gone() below: see there
    count = 2_000
    with connected_pairs(count) as pairs:
        expected = sent_over(pairs)
        rows = own_tcp_rows(collect(sockets_probe))
        assert {ino: rows.get(ino) for ino in expected} == expected
        in_slot = [v[-1] != 0 for v in probe_entries(sockets_probe).values() if v[0] in expected]  # v[-1]: the slot's owner
        assert len(in_slot) == 2 * count
        assert 0 < in_slot.count(False) < in_slot.count(True)

    def gone():
        collect(sockets_probe)  # which forgets any entry whose CLOSE the programs missed
        assert [v for v in probe_entries(sockets_probe).values() if v[0] in expected] == []
    eventually(gone, timeout=30)


def test_sockets_come_as_columns_and_only_those_kept_get_labels(sockets_probe, collect):
    """The sockets reach the budget as arrays, one row each: label values are made for the
    sockets given series of their own (5 here, of 200 and more), and the rest are summed into
    `other` per protocol as arrays."""
    with connected_pairs(100) as pairs:
        for client, server in pairs:
            client.sendall(b"x")
            recv_exactly(server, 1)
        snap = collect(sockets_probe)
    cols = snap.groups[sockets.SOCKET_GROUP]
    assert isinstance(cols, Columns) and len(set(cols.ids.tolist())) == len(cols.ids) >= 200
    made, labels = [], cols.labels
    cols.labels = lambda at: made.extend(at) or labels(at)
    rows = Budget({"socket": 5}).apply(snap).groups[sockets.SOCKET_GROUP]
    own = [(labels, values) for labels, values in rows if labels[0] != "other"]
    assert len(own) == 5 and len(made) == 5
    for i, protocol in enumerate(sockets.PROTOCOLS):
        total = cols.values[cols.dims == i].sum(axis=0).tolist()
        others = [values for labels, values in rows if labels[0] == "other" and labels[2] == protocol]
        kept = [values for labels, values in own if labels[2] == protocol]
        # The kept series begin at zero: what every socket counted so far is in `other`, which has a
        # row where any socket of the protocol counted
        assert kept == [(0,) * 6] * len(kept) and others == [tuple(total)] * any(total), protocol


def test_labels_asked_for_again_are_the_last_collects_until_the_process_is_renamed(sockets_probe, collect,
                                                                                   proctable):
    """The labels of a socket asked for at two collects in a row are made once (the very tuple the
    second time); when its process is renamed, they are made again with the new name."""
    libc = ctypes.CDLL(None)
    was = open("/proc/self/comm").read().rstrip("\n")
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    with a, b:
        a.bind(("127.0.0.1", 0))
        b.connect(a.getsockname())
        inode = os.fstat(b.fileno()).st_ino

        def labels() -> tuple:
            b.send(b"x")
            a.recv(1)
            cols = collect(sockets_probe).groups[sockets.SOCKET_GROUP]
            (at,) = np.flatnonzero(cols.ids == inode).tolist()
            return cols.labels([at])[0]
        first = labels()
        assert first[1] == was and labels() is first
        try:
            libc.prctl(15, b"drums-renamed", 0, 0, 0)  # PR_SET_NAME
            proctable.refresh(renamed={os.getpid()})
            renamed = labels()
        finally:
            libc.prctl(15, was.encode(), 0, 0, 0)
            proctable.refresh(renamed={os.getpid()})
    assert renamed[1] == "drums-renamed" and renamed[:1] + renamed[2:] == first[:1] + first[2:]
