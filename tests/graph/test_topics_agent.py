"""Per-topic counts from the `drums agent` process as the README starts it (`--graph ros2`), with
every ROS 2 node started after the agent in a process of its own: the path a user runs, where the
agent must find librcl in processes that load it late and name every count's node."""
from __future__ import annotations

import pytest
from prometheus_client.parser import text_string_to_metric_families
from std_msgs.msg import String

from tests.agentproc import running_agent, samples, scrape
from tests.conftest import eventually, every, wait_until
from tests.graph.rosnodes import payload
from tests.graph.test_topics import UDP

N = 40  # messages each publisher sends: 4 s at 10 Hz
TRANSPORTS = {"shm": {}, "udp": UDP}


# Room for every process of the host: without the sched and sockets probes no process is more
# active than another, and past the budget which ones keep their own series is chance (the tests
# compare the nodes' processes' own rows with their nodes').
ARGS = ("--graph", "ros2", "--probe", "rcl", "--probe", "rtps", "--probe", "loads", "--probe", "process",
        "--max-processes", "100000")


@pytest.fixture(scope="module")
def agent():
    with running_agent(*ARGS) as url:
        yield url


def scraped(url: str):
    """Scrapes the agent every 0.5 s, as a Prometheus with a short interval would, until the end."""
    return every(0.5, lambda: scrape(url))


@pytest.fixture
def scraper(agent):
    with scraped(agent):
        yield


def topic_counts(url: str, topic: str) -> tuple[dict, dict]:
    """{node: messages published} and {node: messages taken} on the topic, from /metrics."""
    text = scrape(url)
    out = []
    for name in ("drums_topic_messages_published_total", "drums_topic_messages_taken_total"):
        out.append({dict(k)["node"]: v for k, v in samples(text, name).items() if dict(k)["topic"] == topic})
    return out[0], out[1]


def burst(ros_nodes, env: dict, talkers: tuple[str, ...], listener: str, delay: float = 0):
    """A listener, then a process of talker nodes (loading ROS 2 `delay` s after it starts) that
    each publish N messages on /chatter once it is matched; waits until the listener has them all."""
    env = {**env, "DRUMS_TEST_BURST": str(N)}
    sub = ros_nodes("listener", listener, env=env)
    pub = ros_nodes("talker", *talkers, env={**env, "DRUMS_TEST_IMPORT_DELAY": str(delay)})
    pub.go()
    wait_until(lambda: (pub.count(), sub.count()) == (N * len(talkers),) * 2, "the burst sent and taken", timeout=30)
    return sub, pub


def expect(url: str, published: dict, taken: dict) -> None:
    """Wait for /chatter's counts on /metrics to be exactly these (the graph may lag a second)."""
    def check():
        assert topic_counts(url, "/chatter") == (published, taken)
    eventually(check, timeout=10)


def expect_udp(url: str, talker: str, listener: str) -> None:
    """Over UDP the RTPS parse has seen every sample from the first: once each, at its size."""
    text = scrape(url)
    size = payload(String(data="hello"))
    topic = {"topic": "/chatter", "node": talker}
    edge = {"topic": "/chatter", "publisher": talker, "subscriber": listener}
    for name, labels, count in (("drums_topic_samples_sent_total", topic, N),
                                ("drums_topic_sent_bytes_total", topic, N * size),
                                ("drums_edge_samples_received_total", edge, N),
                                ("drums_edge_received_bytes_total", edge, N * size)):
        assert samples(text, name).get(tuple(sorted(labels.items()))) == count, (name, samples(text, name))


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_nodes_started_after_the_agent_are_counted_exactly_while_it_is_scraped(agent, scraper, ros_nodes,
                                                                               transport):
    talker, listener = f"talker_{transport}", f"listener_{transport}"
    burst(ros_nodes, TRANSPORTS[transport], (talker,), listener)
    expect(agent, {f"/{talker}": N}, {f"/{listener}": N})
    if transport == "udp":
        expect_udp(agent, f"/{talker}", f"/{listener}")


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_nodes_are_counted_exactly_when_nobody_scraped_until_the_end(agent, ros_nodes, transport):
    talker, listener = f"quiet_talker_{transport}", f"quiet_listener_{transport}"
    burst(ros_nodes, TRANSPORTS[transport], (talker,), listener)
    expect(agent, {f"/{talker}": N}, {f"/{listener}": N})
    if transport == "udp":
        expect_udp(agent, f"/{talker}", f"/{listener}")


def test_a_process_that_loads_ros_late_is_counted_from_its_first_message_by_an_agent_that_times_nothing(ros_nodes):
    """An agent of its own, which has seen no librcl yet: the first process to load it does so 5 s
    after it started, long after the agent listed it. The agent runs as `drums agent
    --no-ros-timing`, for a robot that wants the counts at the least cost: the programs count, and
    time nothing (no periods, deadlines, reactions or delivery times, though the nodes have a
    deadline they miss)."""
    with running_agent(*ARGS, "--no-ros-timing") as url, scraped(url):
        burst(ros_nodes, {"DRUMS_TEST_DEADLINE_MS": "50"}, ("late_talker",), "late_listener", delay=5)
        expect(url, {"/late_talker": N}, {"/late_listener": N})
        families = {f.name for f in text_string_to_metric_families(scrape(url))}
    timings = {"drums_ros_publish_period_seconds", "drums_ros_deadlines_missed", "drums_ros_take_deadlines_missed",
               "drums_ros_reaction_seconds", "drums_ros_delivery_age_seconds", "drums_topic_publish_period_seconds",
               "drums_topic_deadlines_missed", "drums_edge_delivery_age_seconds"}
    assert "drums_topic_messages_published" in families and families & timings == set()


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_two_nodes_of_one_process_on_one_topic_keep_their_own_counts(agent, scraper, ros_nodes, transport):
    # Only the endpoints' GIDs tell the two apart: same process, same topic, same kind. And no
    # count of theirs is left without its node: on every topic, what the processes' rows count
    # (per pid and endpoint) is what their nodes' rows do. (The host's count of rows without a
    # node says nothing here: ROS 2 processes of other graphs come and go beside this test.)
    # The processes' series count from where they began (what came before is in the budget's
    # `other`), the nodes' from the start: what each grew by over a second burst is compared.
    a, b, listener = f"twin_a_{transport}", f"twin_b_{transport}", f"twin_listener_{transport}"
    sub, pub = burst(ros_nodes, TRANSPORTS[transport], (a, b), listener)
    expect(agent, {f"/{a}": N, f"/{b}": N}, {f"/{listener}": 2 * N})

    def counts(text: str, kind: str) -> tuple[dict, dict]:
        by_process, by_node = {}, {}
        for labels, v in samples(text, f"drums_ros_messages_{kind}_total").items():
            row = dict(labels)
            if row["pid"] in (str(sub.pid), str(pub.pid)):
                by_process[row["topic"]] = by_process.get(row["topic"], 0) + v
        for labels, v in samples(text, f"drums_topic_messages_{kind}_total").items():
            row = dict(labels)
            if row["node"] in (f"/{a}", f"/{b}", f"/{listener}"):
                by_node[row["topic"]] = by_node.get(row["topic"], 0) + v
        return by_process, by_node
    before = scrape(agent)
    pub.go()
    wait_until(lambda: (pub.count(), sub.count()) == (4 * N,) * 2, "the second burst sent and taken", timeout=30)
    expect(agent, {f"/{a}": 2 * N, f"/{b}": 2 * N}, {f"/{listener}": 4 * N})
    after = scrape(agent)
    for kind in ("published", "taken"):
        (process_was, node_was), (process_now, node_now) = counts(before, kind), counts(after, kind)
        by_process = {t: v - process_was.get(t, 0) for t, v in process_now.items()}
        by_node = {t: v - node_was.get(t, 0) for t, v in node_now.items()}
        assert by_process == by_node and by_process.get("/chatter") == 2 * N, (kind, by_process, by_node)


def test_a_publishers_deadline_qos_is_exported_beside_its_counts(agent, ros_nodes):
    ros_nodes("talker", "deadline_talker", env={"DRUMS_TEST_DEADLINE_MS": "100"})
    ros_nodes("talker", "eager_talker")  # no deadline: no series

    def check():
        deadlines = {dict(k)["node"]: v for k, v in samples(scrape(agent), "drums_topic_deadline_seconds").items()
                     if dict(k)["topic"] == "/chatter"}
        assert deadlines == {"/deadline_talker": 0.1}
    eventually(check, timeout=10)


def test_a_process_of_thirty_nodes_keeps_every_label_short(agent, ros_nodes):
    names = [f"crowd_{i:02d}_{'x' * 20}" for i in range(30)]
    proc = ros_nodes("idle", *names)

    def check():
        text = scrape(agent)
        info = {dict(k)["node"]: dict(k) for k in samples(text, "drums_node_info")}
        assert {n: (v["pid"], v["nodes_in_process"]) for n, v in info.items() if n.startswith("/crowd_")} == \
            {f"/{n}": (str(proc.pid), "30") for n in names}
        # Each node's own /parameter_events count on its own series, never one series for them all.
        published = {dict(k)["node"] for k in samples(text, "drums_topic_messages_published_total")
                     if dict(k)["topic"] == "/parameter_events"}
        assert {f"/{n}" for n in names} <= published
        longest = max((len(v) for family in text_string_to_metric_families(text) for s in family.samples
                       for v in s.labels.values()), default=0)
        assert longest <= 64
    eventually(check, timeout=30)

