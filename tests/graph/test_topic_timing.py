"""Time on the graph, from the `drums agent` process as the README starts it (`--graph ros2`): a
real rclpy publisher in its own process on a known schedule, and a real Prometheus computing the
quantiles from the buckets the agent exports."""
from __future__ import annotations

import json
import subprocess
import urllib.request

import numpy as np

from tests.agentproc import running_agent, samples, scrape
from tests.conftest import eventually, wait_until
from tests.deploy.promproc import instant, running_prometheus
from tests.graph.test_topics_agent import ARGS

BEATS = 250  # 20 ms apart, every tenth 40 ms: 5.5 s
PERIOD = "drums_topic_publish_period_seconds"


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
        own = np.array(metronome.periods())
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
