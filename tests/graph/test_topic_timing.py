"""Time on the graph, from the `drums agent` process as the README starts it (`--graph ros2`): a
real rclpy publisher in its own process on a known schedule, and a real Prometheus computing the
quantiles from the buckets the agent exports."""
from __future__ import annotations

import json
import subprocess
import time
import urllib.request

import numpy as np

from tests.agentproc import running_agent, samples, scrape
from tests.conftest import eventually, wait_until
from tests.deploy.promproc import instant, running_prometheus
from tests.graph.test_topics_agent import ARGS

BEATS = 250  # 20 ms apart, every tenth 40 ms: 5.5 s
PERIOD = "drums_topic_publish_period_seconds"
MISSED = "drums_topic_deadlines_missed_total"


def node(url: str, name: str) -> dict:
    """The node's vertex in the agent's /graph, {} if it has none."""
    with urllib.request.urlopen(url.replace("/metrics", "/graph?format=json"), timeout=5) as answer:
        graph = json.load(answer)
    return next((v for v in graph["nodes"] if v.get("kind") == "node" and v["name"] == name), {})


def node_pid(url: str, name: str) -> int | None:
    return node(url, name).get("pid")


def test_the_period_histogram_gives_the_publishers_own_p50_and_p99_within_a_millisecond(ros_nodes):
    with running_agent(*ARGS) as url, running_prometheus("drums", url.split("/")[2], {}, []) as prometheus:
        metronome = ros_nodes("metronome", env={"DRUMS_TEST_BURST": str(BEATS)})
        wait_until(lambda: node_pid(url, "/metronome") == metronome.pid, "the metronome in the graph", timeout=15)
        metronome.go()
        wait_until(lambda: metronome.count() == BEATS, "the beats published", timeout=30)
        own = np.diff(metronome.times("beats")) / 1e9
        assert len(own) == BEATS - 1

        def every_period_counted():
            counts = {dict(k)["node"]: v for k, v in samples(scrape(url), PERIOD + "_count").items()
                      if dict(k)["topic"] == "/beat"}
            assert counts == {"/metronome": BEATS - 1}
        eventually(every_period_counted, timeout=10)

        def quantile(q: float) -> float:
            """What Prometheus makes of the buckets it scraped last."""
            [row] = instant(prometheus, f'histogram_quantile({q}, {PERIOD}_bucket{{topic="/beat"}})')
            return float(row["value"][1])

        def quantiles_seen():
            seen = instant(prometheus, f'{PERIOD}_count{{topic="/beat"}}')
            assert [float(r["value"][1]) for r in seen] == [BEATS - 1]
        eventually(quantiles_seen, timeout=10)
        for q in (0.5, 0.99):
            # The publisher's clock is read just before rcl_publish, the probe's at its entry.
            assert abs(quantile(q) - np.quantile(own, q)) <= 0.001, (q, quantile(q), np.quantile(own, q))
        text = scrape(url)
        checked = subprocess.run(["promtool", "check", "metrics"], input=text, capture_output=True, text=True)
        assert (checked.returncode, checked.stdout, checked.stderr) == (0, "", "") and PERIOD in text, checked
        # The sum is the time from the first publish to the last, on either clock.
        [total] = [v for k, v in samples(text, PERIOD + "_sum").items() if dict(k)["topic"] == "/beat"]
        assert abs(total - own.sum()) <= 0.002, (total, own.sum())


def missed(url: str) -> float | None:
    rows = [v for k, v in samples(scrape(url), MISSED).items() if dict(k) == {"topic": "/beat", "node": "/metronome"}]
    return rows[0] if rows else None


def test_deadlines_missed_are_counted_while_a_publisher_is_silent_and_when_it_speaks_again(ros_nodes):
    """Deadline QoS 100 ms; 20 messages 50 ms apart, a silence of 3.05 s, two more. The agent learns
    a publisher's handle at its first message and its deadline from the graph: it counts from the
    scrape after that, as the missed count's first appearance tells."""
    deadline = 100_000_000
    with running_agent(*ARGS) as url:
        metronome = ros_nodes("metronome", env={"DRUMS_TEST_BURST": "22", "DRUMS_TEST_DEADLINE_MS": "100",
                                                "DRUMS_TEST_PERIODS_MS": "50x19,3050,50"})
        wait_until(lambda: node_pid(url, "/metronome") == metronome.pid, "the metronome in the graph", timeout=15)
        metronome.go()
        wait_until(lambda: missed(url) is not None, "the deadline counted", timeout=5)
        counting = time.monotonic_ns()
        wait_until(lambda: metronome.count() >= 20, "the first 20 messages", timeout=10)
        time.sleep(1.0)
        before = time.monotonic_ns()
        silent = missed(url)  # the silence goes on: what has passed of it counts already
        after = time.monotonic_ns()
        beats = metronome.times("beats")
        assert len(beats) == 20 or beats[20] > after, "the scrape came after the silence: a host too busy"

        def misses(beats: list[int], since: int) -> tuple[int, int]:
            """Deadlines missed, as the publisher's clock says, in the periods that ended after
            `since`, and in those that ended before it (which the agent may not have counted)."""
            counted = [(b - a) // deadline for a, b in zip(beats, beats[1:]) if b > since]
            early = [(b - a) // deadline for a, b in zip(beats, beats[1:]) if b <= since]
            return int(sum(counted)), int(sum(early))
        done, early = misses(beats[:20], counting)  # 50 ms periods: 0 but on a host too busy
        last = beats[19]
        assert done + (before - last) // deadline <= silent <= done + early + (after - last) // deadline, \
            (silent, done, early, before - last, after - last)

        wait_until(lambda: metronome.count() == 22, "the last two messages", timeout=5)
        done, early = misses(metronome.times("beats"), counting)
        # Each period of n deadlines or more misses n (no period is within a few ms of a multiple of
        # the deadline, where the two clocks could disagree).
        assert done >= 30
        def all_counted():
            assert done <= missed(url) <= done + early, (missed(url), done, early)
        eventually(all_counted, timeout=5)


def test_a_node_that_sleeps_15_ms_between_take_and_publish_reacts_in_15_ms(ros_nodes):
    """The reactor takes /beat, sleeps 15 ms and publishes /reaction; its timer publishes /status
    from the same thread, which reacts to no message."""
    reaction = "drums_node_reaction_seconds"
    with running_agent(*ARGS) as url, running_prometheus("drums", url.split("/")[2], {}, []) as prometheus:
        reactor = ros_nodes("reactor")
        metronome = ros_nodes("metronome", env={"DRUMS_TEST_BURST": "100", "DRUMS_TEST_PERIODS_MS": "50"})
        for name, process in (("/reactor", reactor), ("/metronome", metronome)):
            wait_until(lambda: node_pid(url, name) == process.pid, f"{name} in the graph", timeout=15)
        metronome.go()
        wait_until(lambda: metronome.count() == 100, "the beats published", timeout=15)
        time.sleep(0.5)  # the last reaction
        own = np.array(reactor.times("reactions")) / 1e9

        def counted():
            rows = {(dict(k)["input"], dict(k)["output"]): v for k, v in samples(scrape(url), reaction + "_count").items()
                    if dict(k)["node"] == "/reactor"}  # (the host may run other ROS 2 software)
            assert rows == {("/beat", "/reaction"): len(own)}, rows  # none for /status
        eventually(counted, timeout=10)
        assert len(own) >= 90  # the metronome publishes whether or not the reactor hears it yet
        assert node(url, "/reactor")["reaction_seconds"]["/beat -> /reaction"]["count"] == len(own)

        def seen():
            assert [float(r["value"][1]) for r in instant(prometheus, f'{reaction}_count{{node="/reactor"}}')] == [len(own)]
        eventually(seen, timeout=10)
        [row] = instant(prometheus, f'histogram_quantile(0.5, {reaction}_bucket{{node="/reactor"}})')
        p50 = float(row["value"][1])
        # The reaction runs from rcl_take's return to rcl_publish: the callback's own time and the
        # executor's call of it (seen: 0.1-0.3 ms).
        assert abs(p50 - 0.015) <= 0.002 and abs(p50 - np.median(own)) <= 0.001, (p50, np.median(own))
