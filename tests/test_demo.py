"""`make demo` and `make demo-stop` as a user runs them (without a terminal, so `drums top` is not
started): Prometheus scrapes the demo's agent and has the demo robot's node series within 90 s;
after the stop no process, BPF pin, namespace or listening port of the demo is left."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import time
import urllib.parse
import urllib.request

import pytest

from tests.agentproc import reserved_port
from tests.conftest import eventually

pytestmark = pytest.mark.demo

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def query(port: int, expr: str) -> list[dict]:
    url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
    try:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return json.loads(reply.read())["data"]["result"]
    except OSError as e:
        raise AssertionError(f"Prometheus does not answer: {e}") from None


def demo_processes() -> list[str]:
    out = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmdline = f.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if "demo/robot.py" in cmdline or ".demo/prometheus" in cmdline or "drums-demo" in cmdline:
            out.append(cmdline)
    return out


def free(port: int) -> bool:
    try:
        socket.create_server(("127.0.0.1", port)).close()
        return True
    except OSError:
        return False


def make(target: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "-s", target], cwd=ROOT, env=env, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=300)


def demo_env() -> tuple[dict, dict]:
    """(ports, environment) of a demo on free ports of its own."""
    ports = {name: reserved_port() for name in ("AGENT", "STREAM", "PROMETHEUS")}
    return ports, {**os.environ, **{f"DRUMS_DEMO_{name}_PORT": str(port) for name, port in ports.items()}}


def test_make_demo_then_demo_stop_leaves_nothing_behind():
    ports, env = demo_env()
    try:
        done = make("demo", env)
        assert done.returncode == 0, done.stderr[-2000:]
        assert f"http://127.0.0.1:{ports['PROMETHEUS']}/alerts" in done.stderr

        def watched():
            assert [r["value"][1] for r in query(ports["PROMETHEUS"], 'up{job="drums"}')] == ["1"]
            cpu = query(ports["PROMETHEUS"], "drums_node_cpu_seconds_total")
            assert {r["metric"]["node"] for r in cpu} == {"/processor", "/controller", "/logger"}
            images = query(ports["PROMETHEUS"], 'drums_topic_messages_published_total{topic="/camera/image"} > 0')
            assert [r["metric"]["node"] for r in images] == ["/camera"]
        # A CI run beside the whole suite once did not see /camera within 60 s: its DDS discovery
        # crosses the veth link to the camera computer's namespace, on a host with both cores busy.
        eventually(watched, timeout=90)
    finally:
        stopped = make("demo-stop", env)
    assert (stopped.returncode, stopped.stderr) == (0, ""), stopped.stderr
    assert demo_processes() == []
    assert not os.path.exists("/sys/fs/bpf/drums-demo") and not os.path.exists(os.path.join(ROOT, ".demo"))
    assert "drums-demo-camera" not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert all(free(port) for port in ports.values())


# Each fault of `make demo FAULT=...`, the alert the README says it fires within two minutes of
# the fault (20 s in; the throttle at 60 s, once the link carried a minute of images), and where.
FAULTS = {
    "leak": (20, "DrumsNodeMemoryLeak", {"node": "/processor"}),
    "flood": (20, "DrumsTopicFlooding", {"node": "/logger", "topic": "/rosout"}),
    "throttle": (60, "DrumsEdgeRetransmitsHigh",
                 {"topic": "/camera/image", "publisher": "/camera", "subscriber": "/processor"}),
}


# The leak and the flood in one demo (its minutes once); the throttle in one of its own: beside the
# two, whose load slows the processor, its retransmits stayed under the alert's ratio.
@pytest.mark.parametrize("faults", ["leak,flood", "throttle"])
def test_each_fault_of_make_demo_fires_its_alert_on_the_entity_at_fault(faults):
    ports, env = demo_env()
    try:
        done = make("demo", {**env, "FAULT": faults})
        assert done.returncode == 0, done.stderr[-2000:]
        begun = time.monotonic()
        for fault in faults.split(","):
            after, name, where = FAULTS[fault]

            def fired():
                alerts = query(ports["PROMETHEUS"], f'ALERTS{{alertstate="firing", alertname="{name}"}}')
                assert [{k: a["metric"].get(k) for k in where} for a in alerts] == [where], (fault, alerts)
            eventually(fired, timeout=max(1.0, begun + after + 120 - time.monotonic()))
    finally:
        assert make("demo-stop", env).returncode == 0
