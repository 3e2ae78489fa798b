"""Every panel of the shipped dashboards returns series from a live system: Debian's Prometheus
(started here, scraping every second, with the shipped rules) scraping a `drums agent` process
that watches rclpy nodes in processes of their own, over UDP: a talker with a Deadline QoS and a
listener, a producer -> processor -> sink pipeline, a node that leaks memory and one that floods
/rosout.

No Grafana server is installable here, so the panels are run the way Grafana runs them: each
query of the checked-in JSON, its template variables replaced by real values ($robot and $host,
the scrape config's target labels; $node /processor; $topic /chatter; $__rate_interval 1m),
through the Prometheus HTTP API; the variables' own queries (label_values) through the label
values API. Expressions that need an hour of history are not panels: those read recording rules
or data of the last minute."""
import json
import os
import re
import socket
import subprocess
import sys
import threading
import urllib.request

import pytest

from deploy.mixin import build
from tests.agentproc import free_port, running_agent
from tests.conftest import eventually
from tests.deploy.promproc import api, instant, running_prometheus
from tests.graph.conftest import RosProcess
from tests.graph.test_topics import UDP

ROBOT, HOST = "testbot", socket.gethostname()
VALUES = {"robot": ROBOT, "host": HOST, "node": "/processor", "topic": "/chatter", "__rate_interval": "1m"}
SMALL_IMAGES = {"DRUMS_TEST_IMAGE_BYTES": "1000"}  # the pipeline's shape without its megabytes
NODES = (("talker", ("talker",), {"DRUMS_TEST_DEADLINE_MS": "200"}),
         ("listener", ("listener",), {"DRUMS_TEST_DEADLINE_MS": "200"}),
         ("producer", ("producer",), SMALL_IMAGES),
         ("processor", ("processor",), SMALL_IMAGES),
         ("sink", ("sink",), SMALL_IMAGES),
         ("leaker", ("leaker",), {}),
         ("flooder", ("flooder", "--ros-args", "--disable-stdout-logs"), {}),
         # a best-effort talker and a listener that asks for reliable messages: they cannot connect
         ("talker", ("hasty", "--ros-args", "-r", "chatter:=hasty_chatter"), {"DRUMS_TEST_BEST_EFFORT": "1"}),
         ("listener", ("strict", "--ros-args", "-r", "chatter:=hasty_chatter"), {}))
OUR_NODES = sorted(f"/{names[0]}" for _, names, _ in NODES)  # (role, node names and ROS arguments, env)


def dashboards() -> dict[str, dict]:
    out = {}
    for path in sorted(os.listdir(os.path.join(build.OUT, "dashboards"))):
        with open(os.path.join(build.OUT, "dashboards", path)) as f:
            out[path.removesuffix(".json")] = json.load(f)
    return out


def panel_queries() -> list[tuple[str, str]]:
    """(dashboard / panel / refId, expression) of every query of every panel."""
    return [(f"{uid} / {panel['title']} / {target['refId']}", target["expr"])
            for uid, board in dashboards().items() for panel in board["panels"] for target in panel.get("targets", ())]


def substituted(expr: str) -> str:
    """The query as Grafana sends it with these variable values (only names it knows are used)."""
    return re.sub(r"\$\{?(\w+)\}?", lambda m: VALUES[m.group(1)], expr)


def start_nodes() -> list[RosProcess]:
    """All test nodes at once (each takes a second of CPU to start), over UDP so edges are counted."""
    started, errors = [], []

    def start(role, argv, env):
        try:
            started.append(RosProcess(role, *argv, env={**UDP, **env}))
        except RuntimeError as e:
            errors.append(e)
    threads = [threading.Thread(target=start, args=node) for node in NODES]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        for p in started:
            p.stop()
        pytest.fail(f"test nodes did not start: {errors}")
    return started


@pytest.fixture(scope="module")
def prometheus():
    nodes = []
    starter = threading.Thread(target=lambda: nodes.extend(start_nodes()))
    starter.start()  # while the agent compiles its probes
    try:
        with running_agent("--graph", "ros2", "--latency-target", "127.0.0.1") as metrics:
            starter.join()
            agent = metrics.removesuffix("/metrics")
            request = urllib.request.Request(f"{agent}/drums/v1/monitor/latency/127.0.0.1", data=b'{"interval": 1}',
                                             method="POST")
            urllib.request.urlopen(request, timeout=10).read()
            rules = [os.path.join(build.OUT, name) for name in ("prometheus_rules.yaml", "prometheus_alerts.yaml")]
            detector_port = free_port()  # `drums detect` on the agent: the fleet board's anomaly panel
            detector = subprocess.Popen([sys.executable, "-m", "drums", "detect", "--agent", agent,
                                         "--port", str(detector_port)], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL)
            try:
                with running_prometheus("drums", agent.removeprefix("http://"), {"robot": ROBOT, "host": HOST},
                                        rules, [("drums-detect", f"127.0.0.1:{detector_port}", {"robot": ROBOT})]) as url:
                    yield url
            finally:
                detector.terminate()
                detector.wait(timeout=10)
    finally:
        starter.join()
        for p in nodes:
            p.stop()


@pytest.fixture(scope="module")
def live(prometheus):
    """Prometheus once the slowest data is in: edges and topic rates, the pipeline's edges and the
    leaker's and flooder's alerts."""
    def ready():
        missing = [expr for expr in ('drums:edge_retransmitted_bytes:ratio_rate1m{topic="/chatter"}',
                                     'drums:edge_received_bytes:rate1m{topic="/processed"}',
                                     'drums:topic_messages_lost:ratio_rate1m{topic="/image"}',
                                     'ALERTS{alertname="DrumsTopicFlooding",node="/flooder"}',
                                     'ALERTS{alertname="DrumsNodeMemoryLeak",node="/leaker"}',
                                     "drums_latency_rtt_mean_seconds") if not instant(prometheus, expr)]
        assert missing == [], (f"alerts: {[a['metric'] for a in instant(prometheus, 'ALERTS')]}; "
                               f"nodes: {[n['metric'] for n in instant(prometheus, 'drums_node_info')]}")
    eventually(ready, timeout=60)
    return prometheus


def test_the_dashboards_have_the_panels_the_mixin_promises():
    boards = dashboards()
    assert sorted(boards) == ["drums-agent", "drums-fleet", "drums-host", "drums-node", "drums-topic"]
    assert [sorted(v["name"] for v in board["templating"]["list"]) for board in boards.values()] == [
        ["datasource", "host", "robot"], ["datasource", "robot"], ["datasource", "host", "robot"],
        ["datasource", "host", "node", "robot"], ["datasource", "robot", "topic"]]
    assert len(panel_queries()) == 87


def test_template_variables_list_the_live_robot_host_nodes_and_topics(live):
    found = {}
    for board in dashboards().values():
        for variable in board["templating"]["list"]:
            if variable["type"] == "query":
                selector, label = re.fullmatch(r"label_values\((.*), (\w+)\)", variable["query"]).groups()
                found[variable["name"]] = set(api(live, f"label/{label}/values", **{"match[]": substituted(selector)}))
    assert found["robot"] == {ROBOT}
    assert found["host"] == {HOST}
    assert sorted(found["node"]) == OUR_NODES
    # The agent counts every process of the host: topics of processes outside this test's ROS
    # domain (other tests, a demo) are there too, under node "unknown".
    unnamed = 'drums_topic_messages_published_total{node="unknown"}'
    strangers = set(api(live, "label/topic/values", **{"match[]": unnamed}))
    # A node publishes /parameter_events as it starts, which may be before the agent's probes are
    # in: it may be missing.
    ours = {"/chatter", "/image", "/processed", "/rosout", "/hasty_chatter"}
    assert found["topic"] - {"/parameter_events"} == (ours | strangers) - {"/parameter_events"}


@pytest.mark.parametrize("where, expr", panel_queries(), ids=[where for where, _ in panel_queries()])
def test_every_panel_query_returns_series(live, where, expr):
    query = substituted(expr)
    assert "$" not in query
    assert instant(live, query), f"{where}: {query} returned nothing"


def test_every_rule_evaluates_without_error_on_live_data(live):
    # A rule that fails (e.g. many-to-many matching) records nothing and only says so here.
    rules = [rule for group in api(live, "rules")["groups"] for rule in group["rules"]]
    assert [(r["name"], r.get("lastError")) for r in rules if r["health"] != "ok"] == []
    assert len(rules) == 51


def test_the_leaker_and_the_flooder_trip_their_alerts(live):
    def alerting(name: str) -> list[tuple]:
        """This alert's nodes of ours (the host may run other ROS 2 software), topics and states."""
        return sorted((a["metric"]["node"], a["metric"].get("topic"), a["metric"]["alertstate"])
                      for a in instant(live, f'ALERTS{{alertname="{name}",node=~"{"|".join(OUR_NODES)}"}}'))
    # pending: each alert wants its condition for minutes before it fires
    assert alerting("DrumsTopicFlooding") == [("/flooder", "/rosout", "pending")]
    leaking = alerting("DrumsNodeMemoryLeak")
    assert ("/leaker", None, "pending") in leaking, leaking
    # Over the minute or two of this lab, a node still filling its heap may pass the 10 KiB/s of the
    # rule too (seen: /sink, on a busy host); its `for: 30m` keeps it from firing. Never near the
    # leaker's 1 MB/s.
    growth = {r["metric"]["node"]: float(r["value"][1])
              for r in instant(live, f'drums:node_resident_memory_bytes:deriv30m{{node=~"{"|".join(OUR_NODES)}"}}')}
    assert all(10 * growth[n] < growth["/leaker"] for n, _, _ in leaking if n != "/leaker"), (leaking, growth)


def test_a_subscription_whose_qos_cannot_connect_fires_its_alert(live):
    # Last in this module: the alert wants its condition for a minute (the lab has run a while by now).
    def firing():
        alerts = [(a["metric"]["publisher"], a["metric"]["subscriber"], a["metric"]["topic"], a["metric"]["policy"],
                   a["metric"]["alertstate"]) for a in instant(live, 'ALERTS{alertname="DrumsQoSIncompatible"}')]
        assert alerts == [("/hasty", "/strict", "/hasty_chatter", "reliability", "firing")], alerts
    eventually(firing, timeout=90)
    # The fleet board's count of firing alerts ends in `or vector(0)`, which answers whatever happens:
    # with an alert firing it must count it.
    (expr,) = [e for where, e in panel_queries() if where.startswith("drums-fleet / Firing alerts /")]
    (count,) = instant(live, substituted(expr))
    assert float(count["value"][1]) >= 1, (expr, count)
    compatible = instant(live, 'drums_edge_qos_incompatible{topic="/chatter"}')
    assert [(r["metric"]["policy"], r["value"][1]) for r in compatible] == [("none", "0")], compatible
