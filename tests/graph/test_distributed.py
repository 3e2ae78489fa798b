"""Drums across hosts: three network namespaces stand for three robot computers, joined through a
fourth that routes between them (veth pairs); the test itself sits behind the router as an
operator's laptop would. Each host runs its own agent (in its own network and UTS namespace, so it
has its own addresses and host name) and its own ROS 2 nodes, which find each other over UDP
through the router (static peers: multicast does not cross a router). `drums detect` watches the
three agents from the operator's side, as the paper's detector watched its robots, and must name
the edge that a faulty router (a tc tbf throttle on one link) chokes.
"""
import contextlib
import json
import os
import subprocess
import sys
import time

import pytest
import zmq
from prometheus_client.parser import text_string_to_metric_families
from std_msgs.msg import String

from drums.client import Client
from tests.agentproc import running_agent, scrape
from tests.graph.conftest import RosProcess
from tests.graph.rosnodes import payload
from tests.graph.test_hosts import named

pytestmark = pytest.mark.lane2  # two minutes of its own lab: make test runs it beside the rest
PREFIX = f"dd{os.getpid() % 10000}"  # names of this session's namespaces and links
HOSTS = (1, 2, 3)
TOKEN = "distributed-test-token"
BURST = 40
IMAGE = 20_000  # bytes of each /image message, 10 a second: 1.6 Mbit/s to each viewer
THROTTLE = "400kbit"
GRACE = 30  # seconds the detector leaves a new node alone: the lab's nodes settle within it
PLACES = {"talker": "robot1", "producer": "robot1", "listener2": "robot2", "viewer2": "robot2",
          "listener3": "robot3", "viewer3": "robot3"}


def address(i: int) -> str:
    return f"10.78.{i}.2"


def run(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True)


def on_host(i: int) -> tuple[str, ...]:
    """A command prefix that runs a program on host i: its network namespace and its host name."""
    return ("nsenter", f"--net=/run/netns/{PREFIX}h{i}", *named(f"robot{i}"))


@pytest.fixture(scope="module")
def network():
    router = f"{PREFIX}r"
    try:
        run("ip", "netns", "add", router)
        run("ip", "netns", "exec", router, "sysctl", "-q", "-w", "net.ipv4.ip_forward=1")
        for i in HOSTS:
            host, here, there = f"{PREFIX}h{i}", f"{PREFIX}e{i}", f"{PREFIX}r{i}"
            run("ip", "netns", "add", host)
            run("ip", "link", "add", here, "netns", host, "type", "veth", "peer", "name", there, "netns", router)
            run("ip", "-n", host, "addr", "add", f"{address(i)}/24", "dev", here)
            run("ip", "-n", router, "addr", "add", f"10.78.{i}.1/24", "dev", there)
            for ns, link in ((host, here), (host, "lo"), (router, there)):
                run("ip", "-n", ns, "link", "set", link, "up")
            run("ip", "-n", host, "route", "add", "default", "via", f"10.78.{i}.1")
        # The operator's side: this test's own network namespace, behind the router.
        run("ip", "link", "add", f"{PREFIX}c", "type", "veth", "peer", "name", f"{PREFIX}rc", "netns", router)
        run("ip", "addr", "add", "10.78.9.2/24", "dev", f"{PREFIX}c")
        run("ip", "link", "set", f"{PREFIX}c", "up")
        run("ip", "-n", router, "addr", "add", "10.78.9.1/24", "dev", f"{PREFIX}rc")
        run("ip", "-n", router, "link", "set", f"{PREFIX}rc", "up")
        run("ip", "route", "add", "10.78.0.0/16", "via", "10.78.9.1")
        yield router
    finally:
        subprocess.run(["ip", "route", "del", "10.78.0.0/16"], capture_output=True)
        subprocess.run(["ip", "link", "del", f"{PREFIX}c"], capture_output=True)
        for ns in [router] + [f"{PREFIX}h{i}" for i in HOSTS]:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


@pytest.fixture(scope="module")
def lab(network, tmp_path_factory):
    """An agent on each host, then the nodes: a talker (a burst of BURST messages) and a producer
    (IMAGE bytes at 10 Hz) on robot1, a listener and a viewer on robot2 and on robot3."""
    token = tmp_path_factory.mktemp("token") / "token"
    token.write_text(TOKEN)
    token.chmod(0o600)
    env = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
           "ROS_STATIC_PEERS": ";".join(address(i) for i in HOSTS)}
    saved = dict(os.environ)
    os.environ.update(env)  # the agents' graph readers discover through the router too
    try:
        with contextlib.ExitStack() as stack:
            urls = {i: stack.enter_context(running_agent(
                "--token-file", str(token), "--own-netns", "--graph", "ros2", "--latency-mesh",
                "--probe", "sockets", "--probe", "process", "--probe", "rtps", "--probe", "rcl",
                "--probe", "latency", under=on_host(i), address=address(i))).rsplit("/", 1)[0] for i in HOSTS}
            nodes = {}
            for role, name, i, extra in (("talker", "talker", 1, {"DRUMS_TEST_BURST": str(BURST),
                                                                       "DRUMS_TEST_BURST_SUBSCRIBERS": "2"}),
                                         ("producer", "producer", 1, {"DRUMS_TEST_IMAGE_BYTES": str(IMAGE)}),
                                         ("listener", "listener2", 2, {}), ("listener", "listener3", 3, {}),
                                         ("viewer", "viewer2", 2, {}), ("viewer", "viewer3", 3, {})):
                nodes[name] = RosProcess(role, name, env=extra, under=on_host(i))
                stack.callback(nodes[name].stop)
            client = stack.enter_context(Client(list(urls.values()), token=TOKEN))
            detections = tmp_path_factory.mktemp("detect") / "events.jsonl"
            detector = subprocess.Popen(
                [sys.executable, "-m", "drums", "detect", *(a for url in urls.values() for a in ("--agent", url)),
                 "--token-file", str(token), "--port", "0", "--log", str(detections), "--grace", str(GRACE),
                 "--ignore", "host", "--ignore", "process", "--ignore", "connection", "--ignore", "link"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            stack.callback(detector.wait, 10)
            stack.callback(detector.terminate)
            yield urls, nodes, client, (time.monotonic(), detections)
    finally:
        os.environ.clear()
        os.environ.update(saved)


def hosts_of_nodes(graph) -> dict[str, str]:
    return {d["name"]: d.get("host", "") for _, d in graph.nodes(data=True) if d["kind"] == "node"}


def edge(graph, topic: str, publisher: str, subscriber: str) -> dict:
    return graph.edges[f"node:/{publisher}", f"node:/{subscriber}", topic]


def wait_for(what: str, check, within: float = 30, seen: dict | None = None):
    """check()'s first true value; `seen` is what the failure shows if none comes."""
    deadline = time.monotonic() + within
    while True:
        value = check()
        if value:
            return value
        assert time.monotonic() < deadline, f"{what} within {within} s; last seen: {seen}"
        time.sleep(0.5)


def test_the_client_sees_every_node_on_its_host_and_every_edge_with_its_bytes(lab):
    urls, nodes, client, _ = lab

    seen = {}

    def placed():
        g = client.graph()
        seen.update(nodes=hosts_of_nodes(g), edges=sorted(g.edges(keys=True)))
        ok = {f"/{n}": h for n, h in PLACES.items()}.items() <= seen["nodes"].items()
        return ok and all(g.has_edge("node:/talker", f"node:/listener{i}", "/chatter") for i in (2, 3)) and g
    graph = wait_for("every node on its host and both /chatter edges", placed, within=90, seen=seen)
    assert {d["name"] for _, d in graph.nodes(data=True) if d["kind"] == "host"} == {"robot1", "robot2", "robot3"}
    assert {d["name"]: d["address"] for _, d in graph.nodes(data=True) if d["kind"] == "host"} == {
        f"robot{i}": address(i) for i in HOSTS}
    time.sleep(2)  # every agent has collected since the nodes started: their datagrams are parsed
    nodes["talker"].go()
    counts = {}

    def heard():
        counts.update({i: nodes[f"listener{i}"].count() for i in (2, 3)})
        return all(n == BURST for n in counts.values())
    wait_for(f"both listeners got the burst of {BURST}", heard, seen=counts)
    published = nodes["talker"].count()  # the publisher's own count
    assert published == BURST
    sent = published * payload(String(data="hello"))
    graph = client.graph()
    for i in (2, 3):
        got = edge(graph, "/chatter", "talker", f"listener{i}")
        assert got["samples_received_total"] == BURST
        assert abs(got["received_bytes_total"] - sent) <= 0.02 * sent, (got, sent)


def test_the_client_follows_every_node_on_its_own_host_in_one_stream(lab):
    _, nodes, client, _ = lab
    jobs = client.watch_nodes(interval=0.5)
    ours = {f"/{name}": f"robot{PLACES[name][-1]}:pid:{n.pid}" for name, n in nodes.items()}
    assert {name: job["stream"]["key"] for name, job in jobs.items() if name in ours} == ours
    seen = {}
    wait_for("a sample of every node's process, from its own host's agent",
             lambda: seen.update({s.key: s for s in client.poll(0.5)}) or set(ours.values()) <= set(seen))
    for name, key in ours.items():
        pid = key.rsplit(":", 1)[1]
        assert seen[key].value("drums_process_threads", pid=pid) >= 1, name
    for job in jobs.values():
        host, _, pid = job["stream"]["key"].split(":")
        next(a for a in client.agents if a.info()["host"] == host).stop("pid", pid)


def test_each_agent_reports_only_its_own_host(lab):
    urls, nodes, _, _ = lab
    for i in HOSTS:
        inode = os.stat(f"/run/netns/{PREFIX}h{i}").st_ino
        pids = set()
        for family in text_string_to_metric_families(scrape(urls[i] + "/metrics")):
            pids |= {int(s.labels["pid"]) for s in family.samples if "pid" in s.labels and s.labels["pid"].isdigit()}

        def netns(pid):
            try:
                return os.stat(f"/proc/{pid}/ns/net").st_ino
            except OSError:
                return None  # gone since the scrape
        assert {p for p in pids if netns(p) not in (inode, None)} == set(), f"robot{i} reports others' processes"
        mine = {n.pid for name, n in nodes.items() if PLACES[name] == f"robot{i}"}
        assert len(mine) == 2 and mine <= pids


def test_the_api_off_loopback_needs_the_token_and_the_stream_is_encrypted(lab):
    urls, _, client, _ = lab
    agent = client.agents[0]
    with pytest.raises(Exception, match="401 a valid token is needed"):
        type(agent)(agent.url).start("host")  # the same agent without the token
    mesh = wait_for("robot1's latency mesh to both other hosts",
                    lambda: {j["target"] for j in agent.jobs() if j["kind"] == "latency"} == {address(2), address(3)})
    assert mesh
    job = agent.job("latency", address(2))
    assert job["mesh"] and job["stream"]["address"].startswith(f"tcp://{address(1)}:")
    assert len(job["stream"]["curve_public_key"]) == 40  # Z85 of a CURVE public key
    assert agent.info()["stream"]["curve_public_key"] == job["stream"]["curve_public_key"]
    stranger = type(agent)(agent.url)  # without the token: no key
    assert stranger.info()["stream"]["curve_public_key"] == ""
    assert {j["stream"]["curve_public_key"] for j in stranger.jobs()} == {""}
    plain = zmq.Context.instance().socket(zmq.SUB)  # no CURVE: the agent must not talk to it
    # CURVE to the agent's key, but with a key pair of its own rather than the token's: refused.
    keyless = zmq.Context.instance().socket(zmq.SUB)
    keyless.curve_publickey, keyless.curve_secretkey = zmq.curve_keypair()
    keyless.curve_serverkey = job["stream"]["curve_public_key"].encode()
    for sock in (plain, keyless):
        sock.linger = 0
        sock.connect(job["stream"]["address"])
        sock.subscribe(b"")
    client.subscribe(job["stream"])
    samples = wait_for("a decoded latency sample over CURVE",
                       lambda: [s for s in client.poll(0.5) if s.key == job["stream"]["key"]])
    rtt = samples[-1].value("drums_latency_rtt_mean_seconds", target=address(2))
    assert 0 < rtt < 0.05
    # robot2's agent said its time at its own port (from its announcement): one kernel, one clock.
    offset, uncertainty = (samples[-1].value(f"drums_latency_clock_offset{part}_seconds", target=address(2))
                           for part in ("", "_uncertainty"))
    assert 0 < uncertainty < 0.05 and abs(offset) <= uncertainty + 1e-6, (offset, uncertainty)
    assert plain.poll(500) == 0 and keyless.poll(500) == 0
    plain.close()
    keyless.close()


def test_a_host_that_ignores_ping_is_measured_by_tcp_connects(lab):
    _, _, client, _ = lab
    agent = client.agents[0]  # robot1, whose mesh probes robot2

    def last_round(method):
        series = (agent.job("latency", address(2))["sample"] or {}).get("series", [])
        return {r["name"]: r["value"] for r in series if r["labels"].get("method") == method}  # not the clock's
    assert wait_for("an ICMP round to robot2", lambda: last_round("icmp").get("drums_latency_loss_ratio") == 0.0)
    run("ip", "netns", "exec", f"{PREFIX}h2", "sysctl", "-q", "-w", "net.ipv4.icmp_echo_ignore_all=1")
    try:
        tcp = wait_for("robot2 measured by TCP", lambda: last_round("tcp").get("drums_latency_rtt_mean_seconds"), 10)
        assert 0 < tcp < 0.05
        assert last_round("tcp")["drums_latency_loss_ratio"] == 0.0
    finally:
        run("ip", "netns", "exec", f"{PREFIX}h2", "sysctl", "-q", "-w", "net.ipv4.icmp_echo_ignore_all=0")


def test_throttling_one_link_shows_on_exactly_the_edges_that_cross_it(lab, network):
    urls, nodes, client, (detecting_since, detections) = lab
    wait_for("both viewers receiving", lambda: nodes["viewer2"].count() > 20 and nodes["viewer3"].count() > 20)
    # The detector's warm-up (30 points) and the nodes' grace are over before the router fails.
    time.sleep(max(0.0, detecting_since + 35 + GRACE - time.monotonic()))
    names = [("/image", "producer", "viewer2"), ("/image", "producer", "viewer3"),
             ("/chatter", "talker", "listener2"), ("/chatter", "talker", "listener3")]

    def totals():
        g = client.graph()
        return time.monotonic(), {e: edge(g, *e).get("received_bytes_total", 0) for e in names}
    readings = [totals()]

    def interval():  # bytes per second of each edge over the last second
        time.sleep(max(0.0, 1.0 - (time.monotonic() - readings[-1][0])))
        readings.append(totals())
        (t0, a), (t1, b) = readings[-2:]
        return {e: (b[e] - a[e]) / (t1 - t0) for e in names}
    before = [interval() for _ in range(3)]
    run("ip", "netns", "exec", network, "tc", "qdisc", "add", "dev", f"{PREFIX}r3", "root", "tbf",
        "rate", THROTTLE, "burst", "16kb", "latency", "100ms")
    throttled_at = time.time()
    after = [interval() for _ in range(2)]
    usual = {e: sorted(b[e] for b in before)[1] for e in names}  # the median: one slow second is no rule
    # 10 messages of IMAGE bytes a second, to each viewer, before: within 20%.
    for e in names[:2]:
        assert 0.8 * 10 * IMAGE <= usual[e] <= 1.2 * 10 * IMAGE, (e, before)
    # Within two intervals: the edge through the throttled link carries at most what the link lets
    # through (400 kbit/s = 50 kB/s); no other edge with traffic falls below half its rate.
    dropped = {e for e in names if usual[e] > 0 and after[1][e] < 0.5 * usual[e]}
    assert dropped == {("/image", "producer", "viewer3")}, (before, after)
    assert after[1][names[1]] <= 50_000 * 1.2
    # The edge to viewer2 keeps most of its rate in one of the two seconds: the publisher now also
    # repairs what the throttled link loses, which cost viewer2 up to 28% for a second in one run of
    # five, and 47% in the second second once on a loaded CI host.
    assert max(a[names[0]] for a in after) >= 0.6 * usual[names[0]], (before, after)

    # drums detect names the choked edge within 10 s, on the host that receives it, and flags little
    # else around it: the fault's incident aside, at most 10 series.
    def named():
        events = [json.loads(line) for line in detections.read_text().splitlines()] if detections.exists() else []
        anomalies = [e for e in events if e["event"] == "anomaly" and e["start"] >= throttled_at - 1]
        own = [e for e in anomalies if (e["entity"]["kind"], e["entity"]["name"]) == (
            "edge", "/producer -> /viewer3 on /image") and e["start"] <= throttled_at + 10]
        return own and (own, anomalies)
    own, anomalies = wait_for("the detector to name the throttled edge", named, within=15,
                              seen={"log": detections.read_text() if detections.exists() else ""})
    # On the host that receives it, as a fall of what the edge carries (the age of its messages,
    # which rises too, is watched with --detail).
    assert own[0]["entity"]["host"] == "robot3" and own[0]["change"].startswith("-"), own
    time.sleep(max(0.0, throttled_at + 30 - time.time()))
    events = [json.loads(line) for line in detections.read_text().splitlines()]
    window = {e["series"] for e in events if e["event"] == "anomaly"
              and throttled_at - 1 <= e["start"] <= throttled_at + 30 and e["incident"] != own[0]["incident"]}
    assert len(window) <= 10, sorted(window)
