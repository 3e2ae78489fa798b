"""A ROS 1 master that lists 100,000 topics (each published by a node of its own, about 17 MB of
XML-RPC), to the real agent: the graph is truncated at the adapter's limits, said in a metric, in
/healthz and in the log, the agent's memory grows by under 50 MB and every scrape is answered."""
import json
import time
import urllib.request

import pytest

from drums.graph.ros1 import MAX_NODES, MAX_VALUES
from tests.agentproc import assert_monotonic, running_agent, samples, scrape
from tests.conftest import wait_until
from tests.graph.test_ros1 import Wire
from tests.robustness.test_http import MB, agent_process, timed_scrape

pytestmark = pytest.mark.lane2  # twenty seconds of its own master and agent: make test runs it beside the rest


def value(url: str, name: str, **labels) -> float:
    return samples(scrape(url), name)[tuple(sorted(labels.items()))]


def truncated(url: str) -> float | None:
    """drums_graph_truncated of the ROS 1 adapter, None before its first graph."""
    return samples(scrape(url), "drums_graph_truncated").get((("adapter", "ros1"),))


def test_a_master_that_lists_a_hundred_thousand_topics_is_truncated_and_costs_little(monkeypatch):
    master = Wire("master")
    monkeypatch.setenv("ROS_MASTER_URI", master.uri)
    try:
        with running_agent("--graph", "ros1", "--probe", "host", bpf=False) as url:
            agent = agent_process(url)
            wait_until(lambda: truncated(url) == 0, "the small graph read whole", timeout=10)
            for _ in range(3):  # a few polls of the small graph: the baseline
                time.sleep(1)
                scrape(url)
            before = peak = agent.memory_full_info().uss
            texts = [scrape(url)]
            master.say("mode huge")
            wait_until(lambda: truncated(url) == 1, "the huge graph said truncated", timeout=30)
            times = []
            for _ in range(10):  # ten more polls of it
                times.append(timed_scrape(url))
                peak = max(peak, agent.memory_full_info().uss)
                time.sleep(1)
            texts.append(scrape(url))
            assert_monotonic(texts)
            topics = value(url, "drums_graph_entities", kind="topic")
            nodes = value(url, "drums_graph_entities", kind="node")
            with urllib.request.urlopen(url.replace("/metrics", "/healthz"), timeout=10) as reply:
                health = json.loads(reply.read())
    finally:
        master.kill()
    print(f"hostile master: USS +{(peak - before) / MB:.1f} MB, scrapes took {max(times):.3f} s at most, "
          f"{topics:g} topics and {nodes:g} nodes kept")
    assert None not in times, times
    assert peak - before < 50 * MB, (before, peak)
    # Each topic costs two values (its name and its one publisher's): the values kept name about half
    # as many topics, whose publishers are as many nodes, of which the first MAX_NODES are kept.
    assert MAX_VALUES // 2 - 10 <= topics <= MAX_VALUES // 2 and nodes == MAX_NODES
    assert health["status"] == "degraded" and health["graph"]["truncated"] == (
        f"the ROS master at {master.uri} answered getSystemState with more than {MAX_VALUES:,} values; the first {MAX_VALUES:,} were kept; "
        f"the ROS master at {master.uri} answered getTopicTypes with more than {MAX_VALUES:,} values; the first {MAX_VALUES:,} were kept; "
        f"the ROS master at {master.uri} listed {MAX_VALUES // 2 - 1:,} nodes; the first {MAX_NODES:,} were asked")
