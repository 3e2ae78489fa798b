"""`drums detect` as a process, as the README starts it: over a real Prometheus that scrapes a real
agent it names a process whose sending jumps, in its log, in `drums top`'s Anomalies view and on
the ROS 2 topic /drums/anomalies; and it stands bad flags and an agent that is down."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from contextlib import contextmanager

import pytest

from tests.agentproc import running_agent
from tests.conftest import ros_domain_id
from tests.deploy.promproc import running_prometheus

pytestmark = pytest.mark.lane2  # a minute and a half of its own: make test runs it in a lane beside the rest

QUIET = 45.0  # seconds the sender trickles before it sends in earnest: the detector's history by then
TRICKLE = 1024  # bytes a second, so that its series exist before the jump
BURST = 4 << 20  # bytes a second after


# A DDS domain of this module's own, apart from the graph tests' and /diagnostics' domains.
ROS_ENV = {**os.environ, "ROS_DOMAIN_ID": str(ros_domain_id(1)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
LISTENER = r"""
import json, sys, threading, rclpy
from diagnostic_msgs.msg import DiagnosticArray
rclpy.init(args=[])
node = rclpy.create_node("anomaly_listener")
def heard(array):
    print(json.dumps([{"name": s.name, "level": s.level[0], "message": s.message, "hardware_id": s.hardware_id,
                       "values": {v.key: v.value for v in s.values}} for s in array.status]), flush=True)
node.create_subscription(DiagnosticArray, "/drums/anomalies", heard, 10)
threading.Thread(target=rclpy.spin, args=(node,), daemon=True).start()
sys.stdin.read()
"""


@contextmanager
def detector(*argv):
    """`drums detect` running; yields (process, the URL of its own pages)."""
    proc = subprocess.Popen([sys.executable, "-m", "drums", "detect", "--port", "0", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ROS_ENV)
    line = proc.stderr.readline()
    port = re.search(r"on port (\d+)", line)
    assert port, line + proc.stderr.read() if proc.poll() is not None else line
    try:
        yield proc, f"http://127.0.0.1:{port[1]}"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)


SENDER = r"""
import socket, sys, time
quiet, trickle, burst = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
server = socket.create_server(("127.0.0.1", 0))
out = socket.create_connection(server.getsockname())
peer, _ = server.accept()
peer.setblocking(False)
begin = time.time()
print(f"burst from {begin + quiet:.3f}", flush=True)
chunk = bytes(65536)
while time.time() < begin + quiet + 20:
    rate = trickle if time.time() < begin + quiet else burst
    second = time.time()
    sent = 0
    while sent < rate:
        sent += out.send(chunk[:min(len(chunk), rate - sent)])
        try:
            while peer.recv(1 << 20):
                pass
        except BlockingIOError:
            pass
    time.sleep(max(0.0, second + 1 - time.time()))
"""


def test_a_process_whose_sending_jumps_is_named_through_prometheus_within_ten_seconds(tmp_path):
    log = tmp_path / "events.jsonl"
    with running_agent() as metrics_url, \
            running_prometheus("drums", metrics_url.split("/")[2], {"host": "robot1"}, []) as prometheus:
        listener = subprocess.Popen([sys.executable, "-c", LISTENER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                    text=True, env=ROS_ENV)
        arrays = []
        threading.Thread(target=lambda: arrays.extend(json.loads(line) for line in listener.stdout), daemon=True).start()
        with detector("--prometheus", prometheus, "--log", str(log), "--ignore", "host", "--ros") as (proc, url):
            sender = subprocess.Popen([sys.executable, "-c", SENDER, str(QUIET), str(TRICKLE), str(BURST)],
                                      stdout=subprocess.PIPE, text=True)
            burst_at = float(sender.stdout.readline().split()[-1])
            assert sender.wait(timeout=QUIET + 40) == 0
            # drums top's Anomalies view lists it while it lasts (30 s after it was last flagged).
            top = subprocess.run([sys.executable, "-m", "drums", "top", "--agent", metrics_url.removesuffix("/metrics"),
                                  "--detector", url, "--view", "anomalies", "--json"],
                                 capture_output=True, text=True, timeout=60)
            assert top.returncode == 0, top.stderr
        listener.stdin.close()
        listener.wait(timeout=10)
        assert proc.returncode == 0
        assert "Traceback" not in proc.stderr.read()
    events = [json.loads(line) for line in log.read_text().splitlines()]
    own = [e for e in events if e["event"] == "anomaly" and e["entity"]["kind"] == "process"
           and e["entity"]["name"].endswith(f"({sender.pid})") and e["entity"]["host"] == "robot1"
           and "sent bytes" in e["what"]]
    assert own, [e["text"] for e in events]
    assert burst_at - 1 <= own[0]["start"] <= burst_at + 10, (own[0]["start"] - burst_at, own[0]["text"])
    assert own[0]["category"] == "network" and own[0]["change"].startswith("+")
    statuses = [s for array in arrays for s in array if s["name"] == f"drums: process python ({sender.pid})"]
    assert statuses and {s["hardware_id"] for s in statuses} == {"robot1"} and {s["level"] for s in statuses} == {1}
    assert any("sent bytes" in s["message"] and s["values"]["category"] == "network" for s in statuses), statuses
    assert [] in arrays  # calm before the burst: an empty array, so a controller knows all is well
    rows = json.loads(top.stdout)["rows"]
    assert any(r["entity"].endswith(f"process python ({sender.pid})") and "sent bytes" in r["what"]
               and r["host"] == "robot1" and r["checks"] >= 3 for r in rows), rows


# A process that leaks 5 MiB a second from its first, and one that takes 200 MiB at once and keeps it.
LEAKER = r"""
import sys, time
kept = []
print(f"{time.time():.3f}", flush=True)
while True:
    kept.append(b"\x01" * (5 << 20))
    time.sleep(1)
"""
LOADER = r"""
import sys, time
kept = b"\x01" * (200 << 20)
print(f"{time.time():.3f}", flush=True)
time.sleep(3600)
"""
BIRTH = "drums-birth-test"  # on their command lines, for the agent's --process-name


def test_a_process_that_leaks_from_birth_is_named_within_twenty_seconds_and_one_that_allocates_once_never(tmp_path):
    log = tmp_path / "events.jsonl"
    with running_agent("--process-name", BIRTH) as metrics_url, \
            detector("--agent", metrics_url.removesuffix("/metrics"), "--log", str(log)) as (proc, _):
        children = [subprocess.Popen([sys.executable, "-c", code, BIRTH], stdout=subprocess.PIPE, text=True)
                    for code in (LEAKER, LOADER)]
        try:
            leaker, loader = children
            born = float(leaker.stdout.readline())
            loader.stdout.readline()
            time.sleep(40)
        finally:
            for child in children:
                child.kill()
                child.wait()
    events = [json.loads(line) for line in log.read_text().splitlines()]
    named = {pid: [e for e in events if e["event"] == "anomaly" and e["entity"]["name"].endswith(f"({pid})")]
             for pid in (leaker.pid, loader.pid)}
    assert named[leaker.pid] and "resident memory" in named[leaker.pid][0]["what"], [e["text"] for e in events]
    assert named[leaker.pid][0]["start"] - born <= 20, named[leaker.pid][0]["text"]
    assert named[leaker.pid][0]["checks"] == ["growth"]
    assert not named[loader.pid], [e["text"] for e in named[loader.pid]]


def test_bad_flags_are_one_line_and_an_agent_that_is_down_is_said_once(tmp_path):
    for argv, message in ((["--interval", "0"], "--interval: 0 s is outside 0.1-3600 s"),
                          (["--log", str(tmp_path / "no" / "such.jsonl")], "--log"),
                          (["--ignore", "edge"], "argument --ignore: invalid choice")):
        done = subprocess.run([sys.executable, "-m", "drums", "detect", "--port", "0", *argv],
                              capture_output=True, text=True, timeout=30)
        assert done.returncode == 2 and len(done.stderr.splitlines()) == 1 and message in done.stderr, done.stderr
    with detector("--agent", "http://127.0.0.1:9", "--interval", "0.2") as (proc, url):
        time.sleep(2)
        page = urllib.request.urlopen(f"{url}/metrics", timeout=5).read().decode()
        anomalies = json.load(urllib.request.urlopen(f"{url}/anomalies", timeout=5))
        checked = subprocess.run(["promtool", "check", "metrics"], input=page, capture_output=True, text=True)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert 'drums_detect_source_up{source="127.0.0.1:9"} 0' in page
    failures = float(re.search(r'drums_detect_source_failures_total\{source="127.0.0.1:9"\} (\S+)', page)[1])
    assert failures >= 5
    assert anomalies == {"watched": 0, "flagged": 0, "incidents": []}
    said = proc.stderr.read()
    assert proc.returncode == 0 and "Traceback" not in said
    assert len([line for line in said.splitlines() if "127.0.0.1:9" in line]) == 1, said
