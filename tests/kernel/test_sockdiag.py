"""sockdiag: decoding of hand-built replies, then real loopback connections against the kernel's counts."""
import errno
import os
import random
import socket
import struct
import threading
import time

import pytest

from drums.errors import KernelError
from drums.kernel import sockdiag
from drums.kernel.sockdiag import (ALL_STATES, FULL_STATES, NETLINK_SOCK_DIAG, TCP_STATES, TcpConnection, dump_tcp,
                                   dump_tcp_table, lookup_tcp, parse_messages)
from tests.conftest import eventually

ESTABLISHED, TIME_WAIT, LISTEN = 1, 6, 10


def _pad(data: bytes) -> bytes:
    return data + b"\0" * (-len(data) % 4)


def nlmsg(kind: int, payload: bytes) -> bytes:
    return _pad(struct.pack("=IHHII", 16 + len(payload), kind, 2, 1, 0) + payload)


def diag_msg(family, src, sport, dst, dport, *, state=ESTABLISHED, cookie=0, uid=0, inode=0, info=None):
    """A SOCK_DIAG_BY_FAMILY message: struct inet_diag_msg, then INET_DIAG_INFO if `info` is given."""
    def address(text):
        return socket.inet_pton(family, text).ljust(16, b"\0")

    body = (struct.pack("=BBBB", family, state, 0, 0) + struct.pack("!HH", sport, dport)
            + address(src) + address(dst)
            + struct.pack("=III", 0, cookie & 0xFFFFFFFF, cookie >> 32)
            + struct.pack("=IIIII", 0, 0, 0, uid, inode))
    if info is not None:
        body += _pad(struct.pack("=HH", 4 + len(info), 2) + info)
    return nlmsg(20, body)


def tcp_info(size: int, *, rtt=0, rttvar=0, total_retrans=0, bytes_acked=0, bytes_received=0,
             bytes_sent=0) -> bytes:
    """struct tcp_info cut to `size` bytes, as an older kernel would send it."""
    info = bytearray(232)
    info[0] = ESTABLISHED
    struct.pack_into("=II", info, 68, rtt, rttvar)  # tcpi_rtt, tcpi_rttvar
    struct.pack_into("=I", info, 100, total_retrans)  # tcpi_total_retrans
    struct.pack_into("=QQII", info, 120, bytes_acked, bytes_received, 7, 9)  # ..., segs_out, segs_in
    struct.pack_into("=Q", info, 200, bytes_sent)  # tcpi_bytes_sent
    return bytes(info[:size])


DONE = nlmsg(3, struct.pack("=i", 0))
V4 = diag_msg(socket.AF_INET, "10.1.2.3", 40000, "10.9.8.7", 11311, cookie=(5 << 32) | 6, uid=1000,
              inode=424242, info=tcp_info(232, rtt=250, rttvar=80, total_retrans=3, bytes_acked=1000,
                                          bytes_received=2000, bytes_sent=1100))
V6 = diag_msg(socket.AF_INET6, "fe80::1", 7400, "::", 0, state=LISTEN, inode=7)


def test_parses_several_messages_of_one_read_up_to_done():
    v4, v6 = parse_messages(V4 + V6 + DONE)
    assert v4 == TcpConnection(
        family=socket.AF_INET, state=ESTABLISHED, local_address="10.1.2.3", local_port=40000,
        remote_address="10.9.8.7", remote_port=11311, inode=424242, uid=1000, cookie=(5 << 32) | 6,
        bytes_sent=1100, bytes_acked=1000, bytes_received=2000, segs_out=7, segs_in=9, srtt_us=250,
        rttvar_us=80, total_retrans=3, retransmits=0)
    assert (v6.family, v6.state, v6.local_address, v6.local_port, v6.remote_address) == (
        socket.AF_INET6, LISTEN, "fe80::1", 7400, "::")
    assert v6.bytes_acked == v6.srtt_us == 0  # no INET_DIAG_INFO, as for TIME_WAIT sockets


def test_fields_past_an_older_kernels_tcp_info_are_zero():
    # 104 bytes is tcp_info up to tcpi_total_retrans (Linux 4.0); 160 lacks tcpi_bytes_sent (4.19).
    for size, acked, sent in ((104, 0, 0), (160, 1000, 0)):
        msg = diag_msg(socket.AF_INET, "127.0.0.1", 1, "127.0.0.1", 2,
                       info=tcp_info(size, rtt=99, total_retrans=1, bytes_acked=1000, bytes_sent=1100))
        (conn,) = parse_messages(msg + DONE)
        assert (conn.srtt_us, conn.total_retrans, conn.bytes_acked, conn.bytes_sent) == (99, 1, acked, sent)


def test_a_dump_split_over_reads_ends_only_at_done():
    assert len(parse_messages(V4)) == 1
    assert parse_messages(b"") == []
    assert len(parse_messages(V4 + DONE + V6)) == 1  # nothing after NLMSG_DONE belongs to this dump


def test_kernel_errors_become_one_line_kernel_errors():
    ack = nlmsg(2, struct.pack("=i", 0) + b"\0" * 16)
    assert len(parse_messages(ack + V4 + DONE)) == 1
    with pytest.raises(KernelError, match="Operation not permitted") as refused:
        parse_messages(nlmsg(2, struct.pack("=i", -errno.EPERM) + b"\0" * 16))
    with pytest.raises(KernelError, match="tcp_diag"):
        parse_messages(nlmsg(2, struct.pack("=i", -errno.ENOENT)))
    with pytest.raises(KernelError, match="Interrupted"):
        parse_messages(V4 + nlmsg(3, struct.pack("=i", -errno.EINTR)))
    assert "\n" not in str(refused.value)


def test_truncated_reads_raise_instead_of_returning_part_of_a_dump():
    # A connection missing from a dump would look closed, so a cut message is an error, never skipped.
    data = V4 + V6 + DONE
    boundaries = {len(V4), len(V4) + len(V6)}
    for cut in range(1, len(data)):
        if cut in boundaries:
            assert len(parse_messages(data[:cut])) == (1 if cut == len(V4) else 2)
        else:
            with pytest.raises(KernelError):
                parse_messages(data[:cut])


def test_garbage_raises_kernel_error_and_nothing_else():
    rng = random.Random(1)
    cases = [struct.pack("=IHHII", 0, 20, 0, 0, 0),  # a zero length must not loop forever
             nlmsg(20, V4[16:16 + 72] + struct.pack("=HH", 0, 2))]  # nor a zero-length attribute
    for _ in range(2000):
        body = bytes(rng.getrandbits(8) for _ in range(rng.randrange(120)))
        cases.append(rng.choice([body, nlmsg(20, body), V4[:16 + 72] + body]))
    for data in cases:
        try:
            parse_messages(data)
        except KernelError:
            pass


def _can_use(family: int, address: str) -> bool:
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((address, 0))
        socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, NETLINK_SOCK_DIAG).close()
    except OSError:
        return False
    return True


@pytest.mark.parametrize("family,address", [(socket.AF_INET, "127.0.0.1"), (socket.AF_INET6, "::1")])
def test_counts_of_real_loopback_connections(family, address):
    if not _can_use(family, address):
        pytest.skip(f"no {address} or no NETLINK_SOCK_DIAG here")
    sent, replied = 123457, 54321
    with socket.socket(family, socket.SOCK_STREAM) as listener, socket.socket(family) as client:
        listener.bind((address, 0))
        listener.listen()
        client.settimeout(5)
        client.connect(listener.getsockname()[:2])
        server, _ = listener.accept()
        with server:
            server.settimeout(5)
            received = bytearray()

            def serve():
                while len(received) < sent:
                    received.extend(server.recv(65536))
                server.sendall(b"r" * replied)

            thread = threading.Thread(target=serve)
            thread.start()
            client.sendall(b"s" * sent)
            answer = bytearray()
            while len(answer) < replied:
                answer.extend(client.recv(65536))
            thread.join(5)
            assert (len(received), len(answer)) == (sent, replied)

            syn = 1  # the kernel counts the connecting end's SYN in its bytes_acked
            client_port, server_port = client.getsockname()[1], listener.getsockname()[1]
            deadline = time.monotonic() + 1
            while True:  # the last ACKs may still be on their way
                by_ends = {(c.family, c.local_port, c.remote_port): c for c in dump_tcp()}
                ours = by_ends[family, client_port, server_port]
                theirs = by_ends[family, server_port, client_port]
                acked = (ours.bytes_acked, theirs.bytes_acked) == (syn + sent, replied)
                if acked or time.monotonic() > deadline:
                    break
                time.sleep(0.01)
            listening = by_ends[family, server_port, 0]

            assert (ours.bytes_acked, ours.bytes_received) == (syn + sent, replied)
            assert (theirs.bytes_acked, theirs.bytes_received) == (replied, sent)
            assert ours.bytes_sent >= sent and theirs.bytes_sent >= replied  # retransmits count too
            for conn, sock in ((ours, client), (theirs, server), (listening, listener)):
                assert conn.inode == os.fstat(sock.fileno()).st_ino
                assert conn.uid == os.geteuid()
                assert conn.local_address == address
            for conn in (ours, theirs):
                assert TCP_STATES[conn.state] == "ESTABLISHED"
                assert conn.remote_address == address
                assert conn.srtt_us > 0 and conn.segs_out > 0 and conn.segs_in > 0
            assert TCP_STATES[listening.state] == "LISTEN"
            assert len({ours.cookie, theirs.cookie, listening.cookie}) == 3

            established_only = dump_tcp(1 << ESTABLISHED)
            assert {c.state for c in established_only} == {ESTABLISHED}
            assert ALL_STATES & (1 << LISTEN)


def test_a_dump_longer_than_one_read_is_complete():
    if not _can_use(socket.AF_INET, "127.0.0.1"):
        pytest.skip("no NETLINK_SOCK_DIAG here")
    # About 330 bytes a socket with tcp_info, so 300 listeners take several 32 KiB reads.
    listeners = [socket.create_server(("127.0.0.1", 0)) for _ in range(300)]
    try:
        inodes = {os.fstat(s.fileno()).st_ino for s in listeners}
        assert inodes <= {c.inode for c in dump_tcp(1 << LISTEN)}
    finally:
        for s in listeners:
            s.close()


def test_a_dump_as_a_table_holds_what_a_dump_of_connections_does():
    """The graph's dump, read in bulk into an array: the same sockets (IPv4 and IPv6, listening and
    connected), with the same states, ports, addresses and inodes, as the dump parsed one by one."""
    servers = [socket.create_server(("127.0.0.1", 0)), socket.create_server(("::1", 0), family=socket.AF_INET6)]
    held = []
    try:
        for srv in servers:
            held += [socket.create_connection(srv.getsockname()[:2]) for _ in range(3)]
            held += [srv.accept()[0] for _ in range(3)]
        # By inode: a port of ours may be another process's ephemeral port on another address.
        inodes = {os.fstat(s.fileno()).st_ino for s in held + servers}
        states = (1 << ESTABLISHED) | (1 << LISTEN)
        table = dump_tcp_table(states)
        parsed = {(c.family, c.state, c.local_port, c.remote_port, c.local_address, c.remote_address, c.inode)
                  for c in dump_tcp(states, info=False)}
        def text(family, raw) -> str:
            return socket.inet_ntop(family, bytes(raw)[:4 if family == socket.AF_INET else 16])
        read = {(f, st, sp, dp, text(f, src), text(f, dst), ino) for f, st, sp, dp, src, dst, ino in table.tolist()}
        ours = {row for row in parsed if row[6] in inodes}
        assert len(ours) == 14 and ours == {row for row in read if row[6] in inodes}
    finally:
        for s in held + servers:
            s.close()


def test_a_dump_of_full_sockets_leaves_out_a_connection_in_time_wait():
    """The sockets a process may hold (what the sockets probe checks its TCP entries against): a
    connection whose client closed first ends in TIME_WAIT on the client's side, which a dump of
    every state lists and a dump of the full sockets does not."""
    with socket.create_server(("127.0.0.1", 0)) as srv:
        client = socket.create_connection(srv.getsockname())
        server, _ = srv.accept()
        port = client.getsockname()[1]
        client.close()
        assert server.recv(1) == b""
        server.close()

    def listed(states: int) -> set[tuple[int, int]]:
        return {(state, sport) for _, state, sport, *_ in dump_tcp_table(states).tolist() if sport == port}

    def closing():
        assert listed(ALL_STATES) == {(TIME_WAIT, port)}
    eventually(closing)
    assert listed(FULL_STATES) == set()


def _diag_sockets(tid: int) -> set[int]:
    """Inodes of the sock_diag sockets open in this process (seen from thread `tid`)."""
    with open(f"/proc/{os.getpid()}/task/{tid}/net/netlink") as f:
        diag = {int(fields[-1]) for fields in (line.split() for line in list(f)[1:])
                if int(fields[1]) == NETLINK_SOCK_DIAG}
    open_sockets = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except FileNotFoundError:  # the listing's own
            continue
        if link.startswith("socket:["):
            open_sockets.add(int(link[8:-1]))
    return open_sockets & diag


def test_each_thread_keeps_one_sock_diag_socket_and_one_whose_request_failed_is_closed(monkeypatch):
    """One made and closed at each request would be a socket of the agent that comes and goes at
    every poll of its graph and of the connections' RTT, which its sockets probe counts."""
    if not _can_use(socket.AF_INET, "127.0.0.1"):
        pytest.skip("no NETLINK_SOCK_DIAG here")
    me = threading.get_native_id()

    def in_a_thread(work):  # a thread of its own: this one may keep a socket from the tests before
        done = []
        thread = threading.Thread(target=lambda: done.append(work()))
        thread.start()
        thread.join()
        return done[0]

    before = _diag_sockets(me)
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]
        address = (socket.AF_INET, socket.inet_aton("127.0.0.1"), port)

        def three_requests():
            dump_tcp_table()
            kept = _diag_sockets(me) - before
            dump_tcp()
            assert lookup_tcp([(address, (socket.AF_INET, bytes(4), 0))])[0].local_port == port
            return kept, _diag_sockets(me) - before
        kept, after = in_a_thread(three_requests)
        assert len(kept) == 1 and after == kept

        def failed_then_another():
            dump_tcp_table()
            kept = _diag_sockets(me) - before
            with pytest.raises(KernelError):
                with monkeypatch.context() as patched:
                    patched.setattr(sockdiag, "_messages", refuse)
                    dump_tcp_table()
            closed = _diag_sockets(me) - before
            dump_tcp_table()
            return kept, closed, _diag_sockets(me) - before
        kept, closed, another = in_a_thread(failed_then_another)
        assert len(kept) == 1 and closed == set() and len(another) == 1 and another != kept


def refuse(data):
    raise KernelError("a reply that cannot be read")
