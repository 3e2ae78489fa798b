"""A fleet on an existing store: two robots (network namespaces), each with a Drums agent, ROS 2
nodes talking over UDP, and a Prometheus in agent mode run with deploy/fleet/prometheus-agent.yml,
remote-writing to a central VictoriaMetrics (Debian's, single node) in a third namespace that also
routes to the test. The centre answers for both robots; a robot whose link is cut for 20 s loses
no sample: its Prometheus keeps them in its write-ahead log and sends them once the link is back.
"""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
import urllib.parse
import urllib.request

import pytest
import yaml

from tests.agentproc import free_port, running_agent
from tests.conftest import eventually
from tests.graph.conftest import RosProcess
from tests.graph.test_hosts import named
from tests.graph.test_topics import UDP

pytestmark = pytest.mark.lane2  # a minute of its own network: make test runs it in a lane beside the rest

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
PREFIX = f"fl{os.getpid() % 10000}"
ROBOTS = (1, 2)
CENTRE = "10.79.9.2"  # the central store, as the test (and its operator) reaches it
TOKEN = "fleet-test-token"
VM_PORT = 8428
CUT = 20  # seconds robot1's link is down
SCRAPE = 1  # seconds between a robot's scrapes


def run(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True)


def robot_address(i: int) -> str:
    return f"10.79.{i}.2"


def in_ns(ns: str) -> tuple[str, ...]:
    return ("nsenter", f"--net=/run/netns/{ns}")


def on_robot(i: int) -> tuple[str, ...]:
    return (*in_ns(f"{PREFIX}r{i}"), *named(f"robot{i}"))


@pytest.fixture(scope="module")
def network():
    """The centre routes between the robots' links and the test's own."""
    centre = f"{PREFIX}c"
    try:
        run("ip", "netns", "add", centre)
        run("ip", "netns", "exec", centre, "sysctl", "-q", "-w", "net.ipv4.ip_forward=1")
        run("ip", "-n", centre, "link", "set", "lo", "up")
        for i in ROBOTS:
            robot, here, there = f"{PREFIX}r{i}", f"{PREFIX}e{i}", f"{PREFIX}c{i}"
            run("ip", "netns", "add", robot)
            run("ip", "link", "add", here, "netns", robot, "type", "veth", "peer", "name", there, "netns", centre)
            run("ip", "-n", robot, "addr", "add", f"{robot_address(i)}/24", "dev", here)
            run("ip", "-n", centre, "addr", "add", f"10.79.{i}.1/24", "dev", there)
            for ns, link in ((robot, here), (robot, "lo"), (centre, there)):
                run("ip", "-n", ns, "link", "set", link, "up")
            run("ip", "-n", robot, "route", "add", "default", "via", f"10.79.{i}.1")
        run("ip", "link", "add", f"{PREFIX}t", "type", "veth", "peer", "name", f"{PREFIX}ct", "netns", centre)
        run("ip", "addr", "add", "10.79.9.1/24", "dev", f"{PREFIX}t")
        run("ip", "link", "set", f"{PREFIX}t", "up")
        run("ip", "-n", centre, "addr", "add", f"{CENTRE}/24", "dev", f"{PREFIX}ct")
        run("ip", "-n", centre, "link", "set", f"{PREFIX}ct", "up")
        run("ip", "route", "add", "10.79.0.0/16", "via", CENTRE)
        yield centre
    finally:
        subprocess.run(["ip", "route", "del", "10.79.0.0/16"], capture_output=True)
        subprocess.run(["ip", "link", "del", f"{PREFIX}t"], capture_output=True)
        for ns in [centre] + [f"{PREFIX}r{i}" for i in ROBOTS]:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


@contextlib.contextmanager
def server(argv: list[str], what: str):
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode in (0, -15), f"{what}: {proc.stderr.read()[-2000:]}"


def shipped_config(targets: str) -> dict:
    """deploy/fleet/prometheus-agent.yml with this test's paths, centre and scrape interval."""
    with open(os.path.join(ROOT, "deploy", "fleet", "prometheus-agent.yml")) as f:
        config = yaml.safe_load(f)
    assert config["global"]["external_labels"] == {"robot": "${DRUMS_ROBOT}"}
    config["global"]["scrape_interval"] = f"{SCRAPE}s"
    config["scrape_configs"][0]["file_sd_configs"] = [{"files": [targets], "refresh_interval": "1s"}]
    (write,) = config["remote_write"]
    assert write["url"] == f"http://central:{VM_PORT}/api/v1/write"
    write["url"] = f"http://{CENTRE}:{VM_PORT}/api/v1/write"
    return config


def vm(path: str, **query) -> str:
    url = f"http://{CENTRE}:{VM_PORT}{path}?{urllib.parse.urlencode(query, doseq=True)}"
    with urllib.request.urlopen(url, timeout=10) as reply:
        return reply.read().decode()


def series(expr: str) -> list[dict]:
    return json.loads(vm("/api/v1/query", query=expr))["data"]["result"]


@pytest.fixture(scope="module")
def fleet(network, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fleet")
    token = tmp / "token"
    token.write_text(TOKEN)
    token.chmod(0o600)
    with contextlib.ExitStack() as stack:
        stack.enter_context(server(
            [*in_ns(network), "victoria-metrics", f"-storageDataPath={tmp / 'vm'}", f"-httpListenAddr=:{VM_PORT}",
             "-search.latencyOffset=1s", "-retentionPeriod=1d", "-loggerLevel=ERROR"], "victoria-metrics"))
        for i in ROBOTS:
            url = stack.enter_context(running_agent(
                "--own-netns", "--graph", "ros2", "--token-file", str(token), "--probe", "rtps", "--probe", "rcl",
                "--probe", "loads", "--probe", "sched", "--probe", "process",
                address=robot_address(i), under=on_robot(i)))
            for role, name in (("listener", f"listener_r{i}"), ("talker", f"talker_r{i}")):
                node = RosProcess(role, name, env=UDP, under=on_robot(i))
                stack.callback(node.stop)
            # `drums sd --watch` keeps the robot's target file as the agent's graph has it.
            targets = tmp / f"drums-{i}.json"
            stack.enter_context(server([*on_robot(i), sys.executable, "-m", "drums", "sd", "--agent",
                                        url.rsplit("/", 1)[0], "--output", str(targets), "--watch"], "drums sd"))
            config = tmp / f"prometheus-{i}.yml"
            config.write_text(yaml.safe_dump(shipped_config(str(targets))))
            # In the robot's network, under the machine's own host name: Prometheus looks its host
            # name up, and a made-up one would wait on a DNS server no namespace here reaches.
            stack.enter_context(server(
                [*in_ns(f"{PREFIX}r{i}"), "env", f"DRUMS_ROBOT=robot{i}", "prometheus", "--enable-feature=agent,expand-external-labels",
                 f"--config.file={config}", f"--storage.agent.path={tmp / f'agent-{i}'}",
                 f"--web.listen-address=127.0.0.1:{free_port()}"], f"prometheus agent robot{i}"))

        def both_robots_report():
            for i in ROBOTS:
                nodes = {r["metric"]["node"] for r in series(f'drums_node_cpu_seconds_total{{robot="robot{i}"}}')}
                assert {f"/talker_r{i}", f"/listener_r{i}"} <= nodes, nodes
                edges = series(f'drums_edge_samples_received_total{{robot="robot{i}"}} > 0')
                assert {(e["metric"]["publisher"], e["metric"]["subscriber"]) for e in edges} == \
                    {(f"/talker_r{i}", f"/listener_r{i}")}, edges
        eventually(both_robots_report, timeout=60)
        yield network


def timestamps(robot: str, start: float, end: float) -> list[float]:
    """When the centre holds samples of the robot's agent's CPU counter, in seconds."""
    text = vm("/api/v1/export", **{"match[]": f'drums_agent_cpu_seconds_total{{robot="{robot}", role="agent"}}',
                                     "start": f"{start:.3f}", "end": f"{end:.3f}"})
    (line,) = text.splitlines()
    return [t / 1000 for t in json.loads(line)["timestamps"]]


def test_the_centre_answers_for_both_robots(fleet):
    for i in ROBOTS:
        up = series(f'up{{robot="robot{i}", job="drums"}}')
        assert [(r["metric"]["host"], r["value"][1]) for r in up] == [(f"robot{i}", "1")]
        hosts = {r["metric"]["host"] for r in series(f'drums_node_info{{robot="robot{i}"}}')}
        assert hosts == {f"robot{i}"}


def test_a_link_cut_for_20_s_loses_no_sample(fleet):
    link = f"{PREFIX}c1"
    began = time.time()
    run("ip", "-n", fleet, "link", "set", link, "down")
    try:
        time.sleep(CUT)
        # While the link is down robot1 sends nothing: the centre's newest sample is from before the cut.
        assert max(timestamps("robot1", began - 30, time.time())) < began + 2 * SCRAPE
    finally:
        run("ip", "-n", fleet, "link", "set", link, "up")
    ended = time.time()

    def caught_up():  # every scrape of the cut, and on: no gap longer than one scrape and a half
        seen = timestamps("robot1", began - 5, ended + 5)
        assert seen[0] <= began - 3 and seen[-1] >= ended + 3, (seen[0] - began, seen[-1] - ended)
        gaps = [b - a for a, b in zip(seen, seen[1:])]
        assert max(gaps) <= 1.5 * SCRAPE, max(gaps)
        assert len(seen) >= (ended - began + 8) / SCRAPE - 2
    eventually(caught_up, timeout=30)
    # robot2 was never cut off: the same holds for it, as a control.
    seen = timestamps("robot2", began - 5, ended + 5)
    assert max(b - a for a, b in zip(seen, seen[1:])) <= 1.5 * SCRAPE
