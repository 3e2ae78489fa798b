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


def node_pid(url: str, name: str) -> int | None:
    with urllib.request.urlopen(url.replace("/metrics", "/graph?format=json"), timeout=5) as answer:
        graph = json.load(answer)
    return next((v.get("pid") for v in graph["nodes"] if v.get("kind") == "node" and v["name"] == name), None)


def test_the_period_histogram_gives_the_publishers_own_p50_and_p99_within_a_millisecond(ros_nodes):
    with running_agent(*ARGS) as url, running_prometheus("drums", url.split("/")[2], {}, []) as prometheus:
        metronome = ros_nodes("metronome", env={"DRUMS_TEST_BURST": str(BEATS)})
        wait_until(lambda: node_pid(url, "/metronome") == metronome.pid, "the metronome in the graph", timeout=15)
        metronome.go()
        wait_until(lambda: metronome.count() == BEATS, "the beats published", timeout=30)
        own = np.diff(metronome.beats()) / 1e9
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
    """Deadline QoS 100 ms; 20 messages 50 ms apart, a silence of 1.55 s, two more."""
    deadline = 100_000_000
    with running_agent(*ARGS) as url:
        metronome = ros_nodes("metronome", env={"DRUMS_TEST_BURST": "22", "DRUMS_TEST_DEADLINE_MS": "100",
                                                "DRUMS_TEST_PERIODS_MS": "50x19,1550,50"})
        wait_until(lambda: node_pid(url, "/metronome") == metronome.pid, "the metronome in the graph", timeout=15)
        metronome.go()
        wait_until(lambda: metronome.count() == 20, "the first 20 messages", timeout=10)
        wait_until(lambda: missed(url) == 0, "the publisher counted, on time", timeout=2)  # 50 ms < 100 ms
        time.sleep(0.8)
        before = time.monotonic_ns()
        silent = missed(url)  # the silence goes on: what has passed of it counts already
        after = time.monotonic_ns()
        last = metronome.beats()[-1]
        assert (before - last) // deadline <= silent <= (after - last) // deadline, (silent, before - last, after - last)

        wait_until(lambda: metronome.count() == 22, "the last two messages", timeout=5)
        beats = np.array(metronome.beats())
        # Each period of n deadlines or more misses n, as the publisher's own clock says (no period
        # is within a few ms of a multiple of the deadline, where the two clocks could disagree).
        expected = int(sum(np.diff(beats) // deadline))
        assert expected == 15
        eventually(lambda: missed(url) == expected, timeout=5)
