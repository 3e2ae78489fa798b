"""`drums top`'s app (Textual, driven by its Pilot) on a live `drums agent --graph ros2` with real
rclpy nodes in processes of their own: what each view shows against what the nodes, and a TCP
sender and receiver, count themselves; sort and filter; nodes that start, restart and die."""
from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import threading
import time

import pytest
from std_msgs.msg import String

from tests.agentproc import running_agent, scrape
from tests.graph.rosnodes import payload
from tests.graph.test_topics import UDP
from tests.top.pilot import number, row, run, shown, until

pytestmark = pytest.mark.lane2  # a minute of its own ROS 2 domain and agents: make test runs it beside the rest

# Room for every busy socket of the host to have series of its own: beside the other lanes (the demo
# robot's DDS sockets above all), the default 100 were taken, the view showed an `other` row of
# folded sockets, and the test's TCP sender was not among those shown (two fresh-clone runs).
ARGS = ("--graph", "ros2", "--max-sockets", "2000",
        *(a for p in ("rcl", "rtps", "loads", "process", "sched", "host", "sockets") for a in ("--probe", p)))
CHUNK, PERIOD = 10240, 0.1  # the TCP sender's pace: 100 KiB/s
SENDER = f"""
import socket, sys, time
sock = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
due = time.monotonic()
while True:
    sock.sendall(b"x" * {CHUNK})
    due += {PERIOD}
    time.sleep(max(0.0, due - time.monotonic()))
"""


@pytest.fixture(scope="module")
def agent():
    with running_agent(*ARGS) as url:
        yield url.rsplit("/", 1)[0]


@contextlib.contextmanager
def tcp_flow():
    """A process that sends 100 KiB/s over TCP to this one, which counts what arrives; yields
    (the sender's PID, the port it sends to, a function that says how many bytes arrived so far)."""
    server = socket.create_server(("127.0.0.1", 0))
    received = [0]
    sender = subprocess.Popen([sys.executable, "-c", SENDER, str(server.getsockname()[1])])
    conn, _ = server.accept()

    def sink():
        while data := conn.recv(1 << 16):
            received[0] += len(data)
    thread = threading.Thread(target=sink, daemon=True)
    thread.start()
    try:
        yield sender.pid, server.getsockname()[1], lambda: received[0]
    finally:
        sender.kill()
        sender.wait()
        thread.join(5)
        conn.close()
        server.close()


def close(shown_value: float | None, truth: float, what: str) -> None:
    assert shown_value is not None and abs(shown_value - truth) <= 0.1 * truth, (what, shown_value, truth)


def test_each_view_shows_what_the_nodes_count(agent, ros_nodes):
    talker = ros_nodes("talker", "top_talker", env=UDP)
    listener = ros_nodes("listener", "top_listener", env=UDP)
    size = payload(String(data="hello"))
    with tcp_flow() as (sender, port, arrived):
        async def scenario(app, pilot):
            def flowing():
                assert number(row(app, NAME="/top_talker")["PUB"]) and number(row(app, NAME="/top_listener")["TAKE"])
            await until(pilot, flowing, timeout=30)
            began, counts = time.monotonic(), (talker.count(), listener.count(), arrived())
            await pilot.pause(5)
            seen = {"talker": row(app, NAME="/top_talker"), "listener": row(app, NAME="/top_listener"),
                    "sender": row(app, PID=str(sender))}  # a process without a node
            for key, view in (("t", "topics"), ("e", "edges"), ("c", "connections"), ("h", "hosts")):
                await pilot.press(key)
                await pilot.pause(0.3)
                seen[view] = shown(app)
            took = time.monotonic() - began
            published, taken, sent = ((b - a) / took for a, b in zip(counts, (talker.count(), listener.count(), arrived())))
            close(number(seen["talker"]["PUB"]), published, "node published")
            close(number(seen["talker"]["TX"]), published * size, "node bytes sent")
            close(number(seen["listener"]["TAKE"]), taken, "node taken")
            close(number(seen["listener"]["RX"]), taken * size, "node bytes received")
            assert seen["sender"]["NAME"] == "python" and seen["sender"]["PUB"] == "-", seen["sender"]
            close(number(seen["sender"]["TX"]), sent, "process bytes sent")
            chatter, = [r for r in seen["topics"] if r["TOPIC"] == "/chatter"]
            assert (chatter["PUBS"], chatter["SUBS"], chatter["LOST"]) == ("1", "1", "0")
            # A 10 Hz timer: its late messages come a few ms late, not a period (the quantiles
            # themselves are checked against a publisher's own clock in test_topic_timing).
            assert 0 <= number(chatter["JITTER"]) < 0.02, chatter
            close(number(chatter["RATE"]), published, "topic rate")
            close(number(chatter["BANDWIDTH"]), published * size, "topic bandwidth")
            edge, = [r for r in seen["edges"] if r["TOPIC"] == "/chatter"]
            assert (edge["FROM"], edge["TO"], edge["QOS"]) == ("/top_talker", "/top_listener", "ok")
            close(number(edge["RATE"]), taken, "edge rate")
            close(number(edge["BANDWIDTH"]), taken * size, "edge bandwidth")
            # Over UDP on one host, taken by an idle executor: well under a 10 Hz period (the figure
            # itself is checked against the subscriber's own clock in test_topic_timing).
            assert 0 < number(edge["AGE"]) < 0.05, edge
            out = [r for r in seen["connections"] if r["PID"] == str(sender) and r["REMOTE"].endswith(f":{port}")]
            into = [r for r in seen["connections"] if r["PID"] == str(os.getpid()) and r["LOCAL"].endswith(f":{port}")]
            assert len(out) == len(into) == 1, seen["connections"]
            (out,), (into,) = out, into
            close(number(out["TX"]), sent, "sender's socket")
            close(number(into["RX"]), sent, "receiver's socket")
            host = seen["hosts"][0]
            cpu = number(host["CPU"])
            assert host["STATE"] == "up" and cpu is not None and 0 <= cpu <= 100, seen["hosts"]
            loopback, = [r for r in seen["hosts"] if r["IFACE"] == "lo"]
            assert number(loopback["RX"]) >= 0.9 * sent, (loopback, sent)  # the flow, and the agent's answers
        # 120 columns: at 80, a busy host's wide figures leave the names too little room, and
        # /top_listener shows as /to…listener
        run([agent], 2.0, scenario, size=(120, 30))


def test_sort_and_filter_change_the_rows(agent, ros_nodes):
    ros_nodes("idle", "top_sorted_a", "top_sorted_b")

    def column(app, title: str) -> list:
        return [r[title] for r in shown(app)]

    def ordered(values: list, descending: bool) -> bool:
        """Known values in order, unknown ones ("-") after them."""
        known = [v for v in values if v is not None]
        return known == sorted(known, reverse=descending) and values[len(known):] == [None] * (len(values) - len(known))

    def filtered(app):
        assert column(app, "NAME") == ["/top_sorted_a", "/top_sorted_b"]

    def sorted_by(app, title: str) -> list:
        header = [c.label.plain.strip() for c in app.query_one("#rows").ordered_columns]
        assert f"{title}▼" in header or f"{title}▲" in header, header
        return [number(v) for v in column(app, title)]

    async def scenario(app, pilot):
        await until(pilot, lambda: row(app, NAME="/top_sorted_b"), timeout=20)

        def everything() -> int:
            """The rows of the view as last drawn, filtered or not (the host's processes come and go)."""
            return len(app.table.rows)
        await pilot.press("slash", *"top", "underscore", *"sorted", "enter")
        await until(pilot, lambda: filtered(app), timeout=5)
        await pilot.press("escape")
        await until(pilot, lambda: len(shown(app)) == everything(), timeout=5)

        assert ordered(sorted_by(app, "CPU"), descending=True)  # the default
        await pilot.press("greater_than_sign")  # the next column: MEM
        memory = await until(pilot, lambda: sorted_by(app, "MEM"), timeout=5)
        assert ordered(memory, descending=True) and len(set(memory)) > 2, memory
        await pilot.press("r")
        await pilot.pause(0.3)
        assert ordered(sorted_by(app, "MEM"), descending=False)

        table = app.query_one("#rows")
        x = table.ordered_columns[0].width  # HOST is left of NAME
        await pilot.click("#rows", offset=(x + 1, 0))  # NAME's title: A to Z
        await pilot.pause(0.3)
        names = [n.lower() for n in column(app, "NAME")]
        assert names == sorted(names) and len(names) == everything()
        await pilot.click("#rows", offset=(x + 1, 0))  # again: Z to A
        await pilot.pause(0.3)
        names = [n.lower() for n in column(app, "NAME")]
        assert names == sorted(names, reverse=True)
    run([agent], 1.0, scenario, size=(120, 30))


ABSENT = object()


def listed(base: str, node: str):
    """The PID the agent's graph gives the node (None: it lists it without one), ABSENT while it
    does not list it: top shows a node the graph lists without a PID too (one it could not place
    stays listed so until DDS forgets it)."""
    graph = json.loads(scrape(base + "/graph?format=json"))
    return next((v.get("pid") for v in graph["nodes"] if v.get("kind") == "node" and v["name"] == node), ABSENT)


def test_nodes_that_start_restart_and_die_come_and_go_within_two_intervals(agent, ros_nodes):
    """Timed from when the agent's graph has the change (DDS discovery takes it 0.5-4 s here)."""
    interval, lags = 1.0, {}

    async def lag(pilot, agent_has, top_shows, what: str) -> None:
        """Seconds from the agent's graph having the change to top showing it."""
        deadline, since = time.monotonic() + 30, None
        while not top_shows():
            since = since or (time.monotonic() if agent_has() else None)
            assert time.monotonic() < deadline, f"{what}: not shown in 30 s"
            await pilot.pause(0.05)
        lags[what] = time.monotonic() - (since or time.monotonic())

    async def scenario(app, pilot):
        await until(pilot, lambda: shown(app), timeout=10)
        for round in ("start", "restart"):
            node = ros_nodes("idle", "top_newcomer")
            await lag(pilot, lambda: listed(agent, "/top_newcomer") == node.pid,
                      lambda: [r for r in shown(app) if (r["NAME"], r["PID"]) == ("/top_newcomer", str(node.pid))],
                      f"{round}: appears")
            node.kill()
            await lag(pilot, lambda: listed(agent, "/top_newcomer") is ABSENT,
                      lambda: not [r for r in shown(app) if r["NAME"] == "/top_newcomer"], f"{round}: killed, leaves")
    run([agent], interval, scenario, size=(120, 30))
    assert all(t <= 2 * interval for t in lags.values()), lags
