"""The static (YAML) and auto (processes and their TCP connections) adapters, with real
processes; and what the graph does with a reader that answers garbage or nothing."""
from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import textwrap

import networkx as nx
import psutil
import pytest

from drums.agent import Agent, Selection
from drums.budget import Budget
from drums.cli import main
from drums.errors import GraphError
from drums.graph.adapter import ChildAdapter, Follower
from drums.graph.auto import AutoAdapter
from drums.graph.model import Graph, Host
from drums.graph.static import StaticAdapter, parse
from tests.conftest import peer_namespace, wait_until
from tests.graph.test_draw import drawn_graph, texts

SLEEPER = "import time, sys; time.sleep(60)"


@pytest.fixture
def procs():
    started = []

    def start(*args):
        p = subprocess.Popen([sys.executable, "-c", *args], stdout=subprocess.PIPE, text=True)
        started.append(p)
        return p
    yield start
    for p in started:
        p.kill()
        p.wait()


def test_static_file_names_nodes_processes_and_edges(tmp_path, procs):
    planner, driver = procs(SLEEPER, "planner-7f3a"), procs(SLEEPER, "driver-7f3a")
    path = tmp_path / "robot.yaml"
    path.write_text(textwrap.dedent("""
        host: arm
        nodes:
          - {name: /planner, process: "planner-7f3a"}
          - {name: /driver, process: "driver-7f3a"}
          - {name: /camera, process: "no-such-process-7f3a"}
        topics:
          - {name: /cmd_vel, type: geometry_msgs/msg/Twist, publishers: [/planner], subscribers: [/driver]}
    """))
    graph = Graph()
    graph.update(StaticAdapter(str(path)).poll())
    assert {n.name: (n.pid, n.mapped_by) for n in graph.entities("node")} == {
        "/planner": (planner.pid, "static"), "/driver": (driver.pid, "static"), "/camera": (None, "unmapped")}
    assert [(c.topic, c.publisher, c.subscriber) for c in graph.connections()] == [("/cmd_vel", "/planner", "/driver")]
    assert {p.pid for p in graph.entities("process")} == {planner.pid, driver.pid}
    assert {"/planner", "/driver", "/camera", "/cmd_vel"} <= texts(drawn_graph(graph))  # Graphviz draws it


@pytest.mark.parametrize("text, error", [
    ("nodes: [", "not YAML"),
    ("- a\n- b", "a mapping with nodes and topics, not list"),
    ("nodes: {a: 1}", "nodes: a list, not dict"),
    ("nodes: [{name: planner}]", "nodes[0]: needs a name starting with /"),
    ("nodes: [{name: /p, process: '('}]", "nodes[0]: process is not a regular expression"),
    ("topics: [{name: /t, publishers: [/ghost]}]", "topics[0]: node '/ghost' is not among the nodes"),
    ("colour: blue", "unknown key 'colour'"),
    ("hosts: {arm: 10.0.0.2}", "hosts: a list, not dict"),
    ("hosts: [arm]", "hosts[0]: a mapping with name, address, agent_port, not str"),
    ("hosts: [{name: arm, address: 10.0.0.2, port: 9969}]", "hosts[0]: unknown key 'port' (name, address, agent_port)"),
    ("hosts: [{address: 10.0.0.2}]", "hosts[0]: needs a name (got None)"),
    ("hosts: [{name: arm}]", "hosts[0]: needs an address, an IP address or a DNS name (got None)"),
    ("hosts: [{name: arm, address: 'http://arm'}]", "needs an address, an IP address or a DNS name (got 'http://arm')"),
    ("hosts: [{name: arm, address: a}, {name: arm, address: b}]", "hosts[1]: host 'arm' is listed twice"),
    ("hosts: [{name: arm, address: a, agent_port: 65536}]", "hosts[0]: agent_port is a port, 1-65535 (got 65536)"),
    ("hosts: [{name: arm, address: a, agent_port: '9969'}]", "hosts[0]: agent_port is a port, 1-65535 (got '9969')"),
])
def test_bad_static_files_are_one_line_errors(text, error):
    with pytest.raises(GraphError, match=None) as e:
        parse(text, "robot.yaml")
    assert error in str(e.value) and str(e.value).startswith("robot.yaml: ") and "\n" not in str(e.value)


def test_listed_hosts_carry_their_addresses_into_the_graph_and_its_exports(tmp_path, capsys):
    path = tmp_path / "robot.yaml"
    path.write_text(textwrap.dedent("""
        host: arm
        hosts:
          - {name: base, address: base.local}
          - {name: arm, address: 10.0.0.2, agent_port: 9970}
        nodes: [{name: /planner, process: no-such-process-3b8e}]
    """))
    graph = Graph()
    graph.update(StaticAdapter(str(path)).poll())
    assert sorted(graph.entities("host"), key=lambda h: h.name) == [
        Host("arm", "10.0.0.2", "http://10.0.0.2:9970"), Host("base", "base.local")]
    assert main(["graph", "--graph", "static", "--graph-file", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[:2] == [
        "host arm (address 10.0.0.2, agent http://10.0.0.2:9970)", "host base (address base.local)"]
    assert main(["graph", "--graph", "static", "--graph-file", str(path), "--format", "json"]) == 0
    vertices = {v["id"]: v for v in json.loads(capsys.readouterr().out)["nodes"]}
    assert vertices["host:arm"] == {"id": "host:arm", "kind": "host", "name": "arm", "address": "10.0.0.2",
                                    "agent": "http://10.0.0.2:9970"}
    assert main(["graph", "--graph", "static", "--graph-file", str(path), "--format", "graphml"]) == 0
    assert nx.parse_graphml(capsys.readouterr().out).nodes["host:base"]["address"] == "base.local"
    # A file without hosts: its one host by name, as before.
    path.write_text("nodes: [{name: /planner}]\n")
    assert StaticAdapter(str(path)).poll().hosts == [Host(socket.gethostname())]


def test_drums_graph_with_a_bad_file_says_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("nodes: [")
    assert main(["graph", "--graph", "static", "--graph-file", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"drums: {bad}: not YAML") and err.count("\n") == 1


def test_auto_graph_has_an_edge_from_client_to_server(procs):
    server = procs(textwrap.dedent("""
        import socket, time
        s = socket.socket(); s.bind(("127.0.0.1", 0)); s.listen(); print(s.getsockname()[1], flush=True)
        c, _ = s.accept(); time.sleep(60)
    """))
    port = int(server.stdout.readline())
    client = procs(textwrap.dedent(f"""
        import socket, time
        c = socket.create_connection(("127.0.0.1", {port})); print("ok", flush=True); time.sleep(60)
    """))
    client.stdout.readline()
    graph = Graph()
    graph.update(AutoAdapter().poll())
    names = {n.pid: n.name for n in graph.entities("node")}
    assert (f"tcp:{port}", names[client.pid], names[server.pid]) in {
        (c.topic, c.publisher, c.subscriber) for c in graph.connections()}
    assert names[server.pid] == f"/python3/{server.pid}" or names[server.pid].endswith(f"/{server.pid}")
    assert {names[client.pid], names[server.pid], f"tcp:{port}"} <= texts(drawn_graph(graph))  # Graphviz draws it


def test_auto_graph_names_a_peer_on_another_host_by_its_address(procs):
    """A peer namespace stands for another host, whose sockets the dump does not see. Our client of
    a server there: an edge to that server's address and port. Our server's client from there: an
    edge from that client's address, on our server's port. And an IPv6 connection between two
    processes here. Three clients each, so that the reduced ends are each one edge."""
    with peer_namespace(7) as (ns, _, local, remote, _):
        far = subprocess.Popen(("ip", "netns", "exec", ns, sys.executable, "-c", textwrap.dedent(f"""
            import socket, time
            s = socket.socket(); s.bind(("{remote}", 0)); s.listen(); print(s.getsockname()[1], flush=True)
            held = [s.accept() for _ in range(3)]; time.sleep(60)
        """)), stdout=subprocess.PIPE, text=True)
        far_client = None
        try:
            far_port = int(far.stdout.readline())
            client = procs(f"import socket, time\nheld = [socket.create_connection(('{remote}', {far_port})) "
                           "for _ in range(3)]\nprint('ok', flush=True); time.sleep(60)")
            server = procs(textwrap.dedent(f"""
                import socket, time
                s = socket.socket(); s.bind(("{local}", 0)); s.listen(); print(s.getsockname()[1], flush=True)
                held = [s.accept() for _ in range(3)]; print("ok", flush=True); time.sleep(60)
            """))
            port = int(server.stdout.readline())
            far_client = subprocess.Popen(("ip", "netns", "exec", ns, sys.executable, "-c",
                                           f"import socket, time\nheld = [socket.create_connection(('{local}', "
                                           f"{port})) for _ in range(3)]\ntime.sleep(60)"))
            six = procs(textwrap.dedent("""
                import socket, time
                s = socket.create_server(("::1", 0), family=socket.AF_INET6); print(s.getsockname()[1], flush=True)
                held = [s.accept() for _ in range(3)]; time.sleep(60)
            """))
            six_port = int(six.stdout.readline())
            six_client = procs(f"import socket, time\nheld = [socket.create_connection(('::1', {six_port})) "
                               "for _ in range(3)]\nprint('ok', flush=True); time.sleep(60)")
            for p in (client, server, six_client):
                assert p.stdout.readline() == "ok\n"
            state = AutoAdapter().poll()
            names = {n.pid: n.name for n in state.nodes}
            edges = {(c.publisher, c.subscriber, c.topic) for c in state.connections}
            assert {(names[client.pid], f"/remote/{remote}:{far_port}", f"tcp:{far_port}"),
                    (f"/remote/{remote}", names[server.pid], f"tcp:{port}"),
                    (names[six_client.pid], names[six.pid], f"tcp:{six_port}")} <= edges
            ours = {names[p.pid] for p in (client, server, six, six_client)}
            assert len([e for e in edges if {e[0], e[1]} & ours]) == 3  # one edge each, whatever the clients
            assert {n.name: n.pid for n in state.nodes if n.name.startswith(f"/remote/{remote}")} == {
                f"/remote/{remote}:{far_port}": None, f"/remote/{remote}": None}
        finally:
            for p in (far, far_client):
                if p is not None:
                    p.kill()
                    p.wait()


# Accepts a connection for each line of its stdin, from a client it makes itself: a new edge.
SERVER_OF_LINES = textwrap.dedent("""
    import socket, sys
    s = socket.socket(); s.bind(("127.0.0.1", 0)); s.listen(); print(s.getsockname()[1], flush=True)
    held = []
    for line in sys.stdin:
        held.append(socket.create_connection(s.getsockname())); held.append(s.accept()[0])
        print("connected", flush=True)
""")


def test_the_auto_graph_dumps_the_connections_again_only_when_a_tcp_socket_changed_state(procs, tcp_probe):
    """With the tcp probe's count of TCP state changes, a poll while it holds still gives the last
    dump's graph without dumping (other tests may connect meanwhile: only quiet polls are checked);
    a new connection or a process that ended is in the next poll's graph."""
    adapter = AutoAdapter(tcp_changes=tcp_probe.transitions)
    dumps = []
    dump = adapter._dump
    adapter._dump = lambda: (dumps.append(1), dump())[1]  # the real dump, counted
    server = subprocess.Popen([sys.executable, "-c", SERVER_OF_LINES], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        port = int(server.stdout.readline())
        start = tcp_probe.transitions()
        nodes = {n.pid: n.name for n in adapter.poll().nodes}  # listening, no connection yet
        node = nodes[server.pid]
        quiet = 0
        for _ in range(50):
            # Quiet: the count held still from before the last poll (which read it) to after this one.
            done, last_start, start = len(dumps), start, tcp_probe.transitions()
            adapter.poll()
            if tcp_probe.transitions() == last_start:
                quiet += 1
                assert len(dumps) == done
        assert quiet >= 10
        server.stdin.write("connect\n")
        server.stdin.flush()
        assert server.stdout.readline() == "connected\n"
        # The server connected to itself: an edge from its own node to its own node.
        assert (node, f"tcp:{port}") in {(c.subscriber, c.topic) for c in adapter.poll().connections
                                         if c.publisher == node}
        server.kill()
        server.wait()
        assert server.pid not in {n.pid for n in adapter.poll().nodes}
    finally:
        server.kill()
        server.wait()


# Connects to its own listener; on "give", hands its client socket to the taker at the unix path
# given and closes its own copy; on "connect", connects once more; on "ping", only answers.
GIVER = textwrap.dedent("""
    import socket, sys
    s = socket.socket(); s.bind(("127.0.0.1", 0)); s.listen(); print(s.getsockname()[1], flush=True)
    client = socket.create_connection(s.getsockname()); held = [s.accept()[0]]
    for line in sys.stdin:
        if line == "give\\n":
            u = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM); u.connect(sys.argv[1])
            socket.send_fds(u, [b"x"], [client.fileno()])
            client.close()
        elif line == "connect\\n":
            held += [socket.create_connection(s.getsockname()), s.accept()[0]]
        print("done", flush=True)
""")
TAKER = textwrap.dedent("""
    import socket, sys, time
    u = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM); u.bind(sys.argv[1]); print("ready", flush=True)
    _, fds, _, _ = socket.recv_fds(u, 1, 1); print("taken", flush=True); time.sleep(60)
""")


def test_the_auto_graph_reads_again_the_open_files_of_the_processes_that_ran_and_no_others(
        tmp_path, monkeypatch, sched_probe, proctable):
    """With the sched probe's CPU counts, a re-read of open files reads those of the processes that
    ran since their last read: a connection handed to another process is seen in its hands, and a
    process that slept holding sockets is not read again. A socket whose holder ran after the
    probe's last count is looked for in every process."""
    import drums.graph.auto as auto
    monkeypatch.setattr(auto, "OWNERS_REREAD", 0.0)  # each poll re-reads
    agent = Agent([sched_probe], proctable, Selection.parse(), Budget({"process": 1000, "thread": 1000}))
    adapter = AutoAdapter(ran=proctable.cpu_seconds)
    read = []
    socket_inodes = adapter.scan.table.socket_inodes
    adapter.scan.table.socket_inodes = lambda pid: (read.append(pid), socket_inodes(pid))[1]
    path = str(tmp_path / "taker")
    taker = subprocess.Popen([sys.executable, "-c", TAKER, path], stdout=subprocess.PIPE, text=True)
    giver = subprocess.Popen([sys.executable, "-c", GIVER, path], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)
    idle = subprocess.Popen([sys.executable, "-c", SERVER_OF_LINES], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    try:
        port, idle_port = int(giver.stdout.readline()), int(idle.stdout.readline())
        idle.stdin.write("connect\n")
        idle.stdin.flush()
        assert taker.stdout.readline() == "ready\n" and idle.stdout.readline() == "connected\n"

        def tell(line: str) -> None:
            giver.stdin.write(line)
            giver.stdin.flush()
            assert giver.stdout.readline() == "done\n"

        def poll() -> set[tuple[str, str]]:  # the edges of the giver's port
            read.clear()
            return {(c.publisher, c.subscriber) for c in adapter.poll().connections if c.topic == f"tcp:{port}"}

        given, taken = f"/python/{giver.pid}", f"/python/{taker.pid}"
        # Counted once the idle server waits for its next line: from then on it does not run.
        wait_until(lambda: psutil.Process(idle.pid).status() == psutil.STATUS_SLEEPING, "the idle server to wait")
        agent.collect()
        assert poll() == {(given, given)}
        assert {giver.pid, taker.pid, idle.pid} <= set(read)  # each read a first time
        tell("give\n")
        assert taker.stdout.readline() == "taken\n"
        agent.collect()  # the giver and the taker ran; the idle server slept
        assert poll() == {(taken, given)}
        assert {giver.pid, taker.pid} <= set(read)
        # A process that ran is read again and the idle server is not, in a poll that read only the
        # processes that ran: a socket another process opened after the probe's count sends a poll
        # to every process's files (other tests' processes may), so such polls are passed over.
        for _ in range(20):
            tell("ping\n")
            agent.collect()
            poll()
            if len(set(read)) < len(adapter.scan.table.pids()):
                break
        assert len(set(read)) < len(adapter.scan.table.pids()), "every poll read every process's files"
        assert giver.pid in read and idle.pid not in read
        # A new connection of the giver, after the probe's last count: found by reading every process.
        tell("connect\n")
        assert poll() == {(taken, given), (given, given)}
        assert idle.pid in read
        assert (f"/python/{idle.pid}", f"/python/{idle.pid}", f"tcp:{idle_port}") in {
            (c.publisher, c.subscriber, c.topic) for c in adapter.poll().connections}
    finally:
        for p in (giver, taker, idle):
            p.kill()
            p.wait()


class FakeReader(ChildAdapter):
    """A reader child that describes one node, then answers garbage, then nothing."""
    name = "fake"
    module = "tests.graph.fake_reader"


def test_garbage_then_silence_keeps_the_last_good_graph_marked_stale(caplog):
    graph = Graph()
    adapter = FakeReader(interval=0.1, timeout=1.0)
    follower = Follower(adapter, graph)
    follower.start(wait=True)
    try:
        wait_until(lambda: [n.name for n in graph.entities("node")] == ["/only"], "the good graph")
        wait_until(lambda: "unreadable line" in graph.error, "the garbage to be noticed")
        assert graph.stale() and [n.name for n in graph.entities("node")] == ["/only"]
        wait_until(lambda: "said nothing" in graph.error, "the silence to be noticed", timeout=5)
        assert [n.name for n in graph.entities("node")] == ["/only"]
    finally:
        follower.stop()
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 2 and all("keeping the last good graph" in w for w in warnings), warnings


def test_agent_keeps_exporting_kernel_data_under_a_stale_graph(tmp_path, procs, proctable, sched_probe):
    from drums.agent import GRAPH_STALE, Agent
    from drums.graph import join

    planner = procs("while True: pass", "planner-9c1d")  # burns CPU: its node's counter must move
    path = tmp_path / "robot.yaml"
    path.write_text('nodes: [{name: /planner, process: "planner-9c1d"}]\n')
    graph = Graph()
    follower = Follower(StaticAdapter(str(path)), graph)
    follower.start(wait=True)
    agent = Agent([sched_probe], proctable, graph=graph, graph_adapter="static")
    try:
        wait_until(lambda: [n.pid for n in graph.entities("node")] == [planner.pid], "the planner mapped")
        first = agent.collect()
        assert first.values(GRAPH_STALE) == {("static",): 0}
        path.write_text("nodes: [")  # the file goes bad: the last good graph stays, marked stale
        wait_until(lambda: "not YAML" in graph.error, "the bad file to be noticed")
        planner.send_signal(signal.SIGSTOP)  # off the CPU: its time is all counted, and holds still
        wait_until(lambda: psutil.Process(planner.pid).status() == psutil.STATUS_STOPPED, "the planner stopped")
        second = agent.collect()
        assert second.values(GRAPH_STALE) == {("static",): 1}
        # The kernel data goes on under the old names: the node's CPU is its process's, as /proc
        # tells it (in clock ticks, hence the margin).
        cpu = second.values(join.NODE_CPU)[("/planner",)]
        assert cpu > first.values(join.NODE_CPU)[("/planner",)]
        assert abs(cpu - sum(psutil.Process(planner.pid).cpu_times()[:2])) <= 0.03
    finally:
        follower.stop()
