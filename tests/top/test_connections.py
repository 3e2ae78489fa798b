"""drums top's connections view of a real agent whose budget folds the sockets of two protocols
into `other`: one row each, by protocol."""
from __future__ import annotations

import contextlib
import socket

from tests.agentproc import running_agent
from tests.conftest import every
from tests.top.pilot import run, shown, until


@contextlib.contextmanager
def sending():
    """Two TCP connections and two UDP pairs in this process, each sending a few bytes every 20 ms
    until the block ends."""
    server = socket.create_server(("127.0.0.1", 0))
    tcp = [socket.create_connection(server.getsockname()) for _ in range(2)]
    accepted = [server.accept()[0] for _ in tcp]
    udp = []
    for _ in range(2):
        a, b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        a.bind(("127.0.0.1", 0))
        b.connect(a.getsockname())
        udp += [a, b]

    def step():
        for s, peer in zip(tcp, accepted):
            s.send(b"x" * 64)
            peer.recv(1 << 16)
        for a, b in zip(udp[::2], udp[1::2]):
            b.send(b"x" * 64)
            a.recv(1 << 16)
    try:
        with every(0.02, step):
            yield
    finally:
        for s in (server, *tcp, *accepted, *udp):
            s.close()


def test_sockets_folded_into_other_show_as_a_row_per_protocol():
    """With one socket of its own, the agent folds the rest into an `other` row per protocol; top
    shows each (one key for both made the table refuse the second row, and top stopped)."""
    with running_agent("--probe", "sockets", "--max-sockets", "1") as url, sending():
        async def scenario(app, pilot):
            await pilot.press("c")

            def folded():
                protocols = [r["PROTO"] for r in shown(app) if r["PROCESS"] == "other"]
                assert sorted(protocols) == sorted(set(protocols)) and {"tcp", "udp"} <= set(protocols), shown(app)
            await until(pilot, folded, timeout=20)
        run([url.rsplit("/", 1)[0]], 0.5, scenario, size=(120, 30))
