"""An agent that is not root says what it cannot see, once at start, and in its metrics and
/healthz, instead of serving a graph that looks whole."""
import json
import os
import subprocess
import sys
import urllib.request

from drums.graph.ros2 import NOT_ROOT
from tests.agentproc import running_agent, samples, scrape
from tests.conftest import eventually

NODES = os.path.join(os.path.dirname(__file__), "..", "graph", "rosnodes.py")
NOBODY = ("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "env", "HOME=/tmp", "ROS_LOG_DIR=/tmp")


def test_an_agent_that_is_not_root_says_its_ros2_graph_is_partial():
    talker = subprocess.Popen([sys.executable, NODES, "talker", "talker"], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)  # a root node
    try:
        assert talker.stdout.readline().startswith("ready")
        with running_agent("--probe", "host", under=NOBODY, bpf=False) as url:
            def partial() -> dict:
                text = scrape(url)
                assert samples(text, "drums_graph_truncated") == {(("adapter", "ros2"),): 1}
                assert samples(text, "drums_graph_entities")[(("kind", "topic"),)] >= 1  # /chatter at least
                return json.loads(urllib.request.urlopen(url.replace("/metrics", "/healthz"), timeout=10).read())
            health = eventually(partial, timeout=20)
    finally:
        talker.kill()
        talker.wait()
    assert health["status"] == "degraded" and health["graph"]["truncated"] == NOT_ROOT
