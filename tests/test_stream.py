"""The ZeroMQ stream of job samples and the client library, against real agents."""
import json
import os
import subprocess
import sys
import time

import psutil
import pytest

from drums.client import AgentError, Client
from drums.exporters.stream import KEYFRAME
from tests.agentproc import free_port, running_agent
from tests.conftest import eventually, peer_namespace

CHEAP = ("--probe", "host", "--probe", "process", "--probe", "latency", "--graph", "auto")


@pytest.fixture(scope="module")
def agent():
    with running_agent(*CHEAP, "--latency-target", "127.0.0.1", "--latency-target", "localhost",
                       bpf=False) as url:
        yield url.rsplit("/", 1)[0]


def receive(client: Client, seconds: float, key: str, at_least: int = 0) -> list:
    """The samples of `key` that come within `seconds`, or until `at_least` came (up to 20 s: a
    loaded machine collects slowly)."""
    got, began = [], time.monotonic()
    while time.monotonic() - began < (seconds if len(got) >= at_least else 20):
        got += [s for s in client.poll(0.2) if s.key == key]
    return got


def zeromq_loaded(url: str) -> bool:
    """Whether the agent serving `url` has libzmq mapped."""
    port = url.rsplit(":", 1)[1].split("/")[0]
    pid, = [p.pid for p in psutil.process_iter(["cmdline"])
            if "agent" in (p.info["cmdline"] or []) and port in (p.info["cmdline"] or [])]
    with open(f"/proc/{pid}/maps") as f:
        return "libzmq" in f.read()


def test_zeromq_comes_with_the_first_sample_and_an_earlier_subscriber_gets_the_samples():
    with running_agent(*CHEAP, bpf=False) as url, Client([url.rsplit("/", 1)[0]]) as c:
        agent = c.agents[0]
        info = agent.info()
        c.subscribe({"address": info["stream"]["address"], "key": f"{info['host']}:host:", "curve_public_key": ""})
        time.sleep(0.5)  # connected to the socket that holds the port, which accepts nobody
        assert not zeromq_loaded(url)
        job = agent.start("host", interval=0.1)
        assert job["stream"]["key"] == f"{info['host']}:host:"
        got = receive(c, 0.5, job["stream"]["key"], at_least=3)
        assert zeromq_loaded(url)
    assert len(got) >= 3 and [s.seq for s in got] == list(range(got[0].seq, got[-1].seq + 1))


def test_samples_on_the_stream_are_the_samples_of_the_api(agent):
    with Client([agent]) as c:
        job, = c.start("host", interval=0.2)
        assert job["stream"]["address"].startswith("tcp://127.0.0.1:") and job["stream"]["curve_public_key"] == ""
        got = receive(c, 2.0, job["stream"]["key"], at_least=5)
        assert len(got) >= 5
        assert all(s.missed == 0 for s in got) and [s.seq for s in got] == list(range(got[0].seq, got[-1].seq + 1))
        latest = c.agents[0].job("host")["sample"]
        got += receive(c, 0.5, job["stream"]["key"])  # the sample GET saw may still be on its way
        c.agents[0].stop("host")
    same = [s for s in got if s.time == latest["time"]] or pytest.fail("the API's sample never came on the stream")
    assert same[0].series == {(r["name"], tuple(sorted(r["labels"].items()))): r["value"] for r in latest["series"]}


def test_a_late_or_interrupted_subscriber_can_tell_what_it_missed(agent):
    with Client([agent]) as c:
        pid = str(os.getpid())
        job = c.agents[0].start("pid", pid, interval=0.1)
        key = job["stream"]["key"]
        time.sleep(1.0)  # the job runs before anyone listens
        c.subscribe(job["stream"])
        got = receive(c, 1.5, key, at_least=1)
        assert got[0].late and got[0].seq > 1 and got[0].value("drums_process_threads", pid=pid) >= 1
        assert c.undecodable < KEYFRAME  # labels come again with every KEYFRAME-th message
        c.unsubscribe(job["stream"])  # as a subscriber cut off for a second
        time.sleep(1.0)
        c.subscribe(job["stream"])
        got += receive(c, 1.5, key)
        c.agents[0].stop("pid", pid)
    gaps = [s.missed for s in got if s.missed]
    assert len(gaps) == 1 and 7 <= gaps[0] <= 13, gaps  # 1 s at 10 samples/s
    assert len(got) + sum(gaps) + c.undecodable == got[-1].seq - got[0].seq + 1 + c.undecodable


def test_latency_jobs_measure_targets_they_are_allowed_to(agent):
    with Client([agent]) as c:
        c.start("latency", "127.0.0.1", interval=0.3, count=4)
        c.start("latency", "localhost", interval=0.3, count=2, method="tcp", port=free_port())  # refused
        time.sleep(3.5)
        here = c.agents[0].job("latency", "127.0.0.1")["sample"]["series"]
        closed = c.agents[0].job("latency", "localhost")["sample"]["series"]
        sent_before = next(r["value"] for r in here if r["name"] == "drums_latency_probes_sent_total")
        c.start("latency", "127.0.0.1", interval=0.2, count=4)  # new settings: the totals go on
        time.sleep(1.0)
        again = c.agents[0].job("latency", "127.0.0.1")
        assert again["interval"] == 0.2
        assert next(r["value"] for r in again["sample"]["series"]
                    if r["name"] == "drums_latency_probes_sent_total") > sent_before
        with pytest.raises(AgentError, match="403 latency to '10.1.2.3': only to hosts of the graph or named by"):
            c.start("latency", "10.1.2.3")
        with pytest.raises(AgentError, match="400 count: a whole number of probes per round, 1-100, not 0"):
            c.start("latency", "127.0.0.1", count=0)
        c.agents[0].stop("latency", "127.0.0.1")
        c.agents[0].stop("latency", "localhost")
    values = {r["name"]: (r["labels"], r["value"]) for r in here}
    labels = {"target": "127.0.0.1", "method": "icmp"}
    sent = values["drums_latency_probes_sent_total"]
    assert sent[0] == labels and sent[1] > 0 and sent[1] % 4 == 0  # whole rounds of 4 echoes
    assert values["drums_latency_probes_lost_total"] == (labels, 0)
    assert values["drums_latency_loss_ratio"] == (labels, 0.0)
    low, mean, high = (values[f"drums_latency_rtt_{s}_seconds"][1] for s in ("min", "mean", "max"))
    assert 0 < low <= mean <= high < 0.01  # loopback
    values = {r["name"]: (r["labels"], r["value"]) for r in closed}
    labels = {"target": "localhost", "method": "tcp"}
    assert values["drums_latency_loss_ratio"] == (labels, 0.0)  # a reset answers as well as a SYN-ACK
    assert values["drums_latency_probes_sent_total"][1] % 2 == 0
    assert 0 < values["drums_latency_rtt_mean_seconds"][1] < 0.01


# In the target's namespace: a listener that tells the probes' connects (closed at once) from the
# agent's asks for its time (an HTTP request, which it does not answer), and says how many connects
# it accepted on each line it is sent.
TARGET = r"""
import socket, sys, threading
server = socket.create_server((sys.argv[1], 0))
print(server.getsockname()[1], flush=True)
connects = [0]
def serve():
    while True:
        conn, _ = server.accept()
        conn.settimeout(5)
        try:
            if not conn.recv(64):
                connects[0] += 1
        except OSError:
            pass
        conn.close()
threading.Thread(target=serve, daemon=True).start()
for _ in sys.stdin:
    print(connects[0], flush=True)
"""


def icmp_echoes_received(ns: str) -> int:
    """Echo requests the namespace's kernel took in, answered or not (/proc/net/snmp IcmpMsg InType8)."""
    text = subprocess.run(["ip", "netns", "exec", ns, "cat", "/proc/net/snmp"], capture_output=True, text=True,
                          check=True).stdout
    rows = [line.split()[1:] for line in text.splitlines() if line.startswith("IcmpMsg:")]
    return int(dict(zip(*rows)).get("InType8", 0)) if rows else 0


def test_a_target_that_ignores_icmp_echoes_is_probed_by_tcp_and_every_probe_is_counted():
    """ICMP filtered on the way, the host there: the first round's echoes go unanswered, one TCP
    connect is answered, and from the next round on the target is probed by TCP. The agent's counts
    are the echoes the target's kernel took in and the connects its listener accepted."""
    with peer_namespace(7) as (ns, _, _, remote, _):
        subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-q", "-w", "net.ipv4.icmp_echo_ignore_all=1"],
                       check=True)
        target = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-c", TARGET, remote],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            port = int(target.stdout.readline())
            with running_agent(*CHEAP, "--latency-target", remote, bpf=False) as url, \
                    Client([url.rsplit("/", 1)[0]]) as c:
                c.start("latency", remote, interval=0.5, count=3, method="auto", port=port)

                def probed_by_tcp() -> list:  # the first round waits a second for each echo
                    sample = c.agents[0].job("latency", remote)["sample"]
                    assert sample, "no sample yet"
                    series = sample["series"]
                    sent = {(r["name"], r["labels"].get("method")): r["value"] for r in series}
                    assert sent.get(("drums_latency_probes_sent_total", "tcp"), 0) >= 4, sent
                    return series
                series = eventually(probed_by_tcp, timeout=20)
                target.stdin.write("\n")
                target.stdin.flush()
                connects = int(target.stdout.readline())
                echoes = icmp_echoes_received(ns)
        finally:
            target.kill()
            target.wait()
    values = {(r["name"], r["labels"].get("method")): r["value"] for r in series}
    # The first round: three echoes, all lost, and one connect, answered. Then rounds of three connects.
    assert values.get(("drums_latency_probes_sent_total", "icmp")) == values.get(("drums_latency_probes_lost_total", "icmp")) \
        == echoes == 3, (values, echoes)
    sent = values["drums_latency_probes_sent_total", "tcp"]
    assert values["drums_latency_probes_lost_total", "tcp"] == 0 and sent >= 4 and (sent - 1) % 3 == 0, values
    assert sent <= connects <= sent + 3, (sent, connects)  # a round may be under way as the job is read
    assert ("drums_latency_rtt_mean_seconds", "tcp") in values and ("drums_latency_rtt_mean_seconds", "icmp") not in values


def test_a_latency_job_to_a_drums_agent_measures_how_far_its_clock_is_from_ours(agent):
    """The agent itself (the same clock) and a peer whose clock is 5 s ahead: a stand-in HTTP server
    that answers /drums/v1/info as an agent does, as no clock of this host can be set apart."""
    import http.server
    import threading

    class Ahead(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            body = json.dumps({"host": "ahead", "time": time.time() + 5.0}).encode()
            self.send_response(200 if self.path == "/drums/v1/info" else 404)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_):
            pass
    peer = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Ahead)
    threading.Thread(target=peer.serve_forever, daemon=True).start()
    own_port = int(agent.rsplit(":", 1)[1])

    def clock(c, target) -> tuple:
        rows = {r["name"]: r["value"] for r in (c.agents[0].job("latency", target)["sample"] or {}).get("series", [])}
        return rows.get("drums_latency_clock_offset_seconds"), rows.get("drums_latency_clock_offset_uncertainty_seconds")
    try:
        with Client([agent]) as c:
            c.start("latency", "127.0.0.1", interval=0.3, count=1, method="tcp", port=own_port)
            c.start("latency", "localhost", interval=0.3, count=1, method="tcp", port=peer.server_address[1])
            time.sleep(1.5)
            same, ahead = clock(c, "127.0.0.1"), clock(c, "localhost")
            c.start("latency", "localhost", interval=0.3, count=1, method="tcp", port=free_port())  # no agent there
            time.sleep(1.5)
            nobody = clock(c, "localhost")
            c.agents[0].stop("latency", "127.0.0.1")
            c.agents[0].stop("latency", "localhost")
    finally:
        peer.shutdown()
    assert 0 < same[1] < 0.05 and abs(same[0]) <= same[1] + 1e-6, same
    assert 0 < ahead[1] < 0.05 and abs(ahead[0] - 5.0) <= ahead[1] + 1e-6, ahead
    assert nobody == (None, None)


# One latency probe to this host's loopback for a second, run as `nobody`: its rows as JSON.
UNPRIVILEGED = r'''
import json, time
from drums.metrics import Snapshot
from drums.probes.latency import LatencyProbe
probe = LatencyProbe()
probe.start()
probe.watch("127.0.0.1", 0.2, count=3)
time.sleep(1.0)
snap = Snapshot()
probe.collect(snap)
probe.stop()
print(json.dumps({m.name: [[list(labels), v] for labels, v in rows] for m, rows in snap.series.items()}))
'''


@pytest.mark.parametrize("ping_group_range, method", [("0 2147483647", "icmp"), ("1 0", "tcp")])
def test_without_root_latency_uses_icmp_sockets_where_allowed_else_tcp(ping_group_range, method, tmp_path):
    """ping_group_range (per network namespace) says which groups may open ICMP datagram sockets;
    this machine's "1 0" allows none, so a namespace of the test's own sets it."""
    out = subprocess.run(
        ["unshare", "--net", "sh", "-c", f"ip link set lo up && sysctl -q -w net.ipv4.ping_group_range='{ping_group_range}' "
         f'&& exec setpriv --reuid=65534 --regid=65534 --clear-groups "$@"', "sh", sys.executable, "-c", UNPRIVILEGED],
        capture_output=True, text=True, timeout=30, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert rows["drums_latency_loss_ratio"] == [[["127.0.0.1", method], 0.0]]
    assert [labels for labels, _ in rows["drums_latency_probes_sent_total"]] == [["127.0.0.1", method]]
    assert 0 < rows["drums_latency_rtt_mean_seconds"][0][1] < 0.01
