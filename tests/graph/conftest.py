"""ROS 2 nodes in processes of their own, on a DDS domain of this test session's own, so that
other ROS 2 software on the host neither shows up in the graph nor sees the test nodes."""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from drums.graph.adapter import Follower
from drums.graph.model import Graph
from drums.graph.ros2 import Ros2Adapter
from tests.conftest import ros_domain_id

NODES = os.path.join(os.path.dirname(__file__), "rosnodes.py")


@pytest.fixture(scope="session", autouse=True)
def ros_domain():
    os.environ["ROS_DOMAIN_ID"] = str(ros_domain_id())
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


class RosProcess:
    def __init__(self, role: str, *names: str, env: dict | None = None, under: tuple[str, ...] = ()):
        """`under`: a command that execs the node's process, e.g. one that puts it on another host."""
        self.proc = subprocess.Popen([*under, sys.executable, NODES, role, *names], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})
        line = self.proc.stdout.readline().split()
        if line[:1] != ["ready"]:
            self.stop()
            raise RuntimeError(f"ROS 2 test node {role} did not start")
        self.pid = int(line[1])

    def count(self) -> int:
        """Messages this process published or received so far, as it counts them."""
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        return int(self.proc.stdout.readline().split()[1])

    def times(self, what: str) -> list[int]:
        """The metronome's "beats" (CLOCK_MONOTONIC, ns, right before each publish), the reactor's
        "reactions" (ns from the start of each callback to its publish) or the receiver's "latencies"
        (ns from each message's stamp to the start of its callback), "ages" and "transports" (ns from
        the RMW's source stamp to the take, and to its received stamp)."""
        self.proc.stdin.write(what + "\n")
        self.proc.stdin.flush()
        return [int(ns) for ns in self.proc.stdout.readline().split()[1:]]

    def matched(self) -> list[int]:
        """The reactor's: how many subscribers each of its /reaction publishers has matched."""
        return self.times("matched")

    def go(self) -> None:
        """Start the burst of a publisher run with DRUMS_TEST_BURST."""
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()

    def stop(self) -> None:
        """End as a user would (Ctrl-C): the node says goodbye to the other participants."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.kill()
        self.proc.wait()

    def kill(self) -> None:
        """End as a crash would: nothing said to anyone."""
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def ros_nodes():
    """ros_nodes(role, *names) -> a running RosProcess; all are killed at the end of the test."""
    started = []

    def start(role, *names, env=None):
        p = RosProcess(role, *names, env=env)
        started.append(p)
        return p
    yield start
    for p in started:
        p.stop()


@pytest.fixture(scope="module")
def ros2_graph():
    graph = Graph()
    follower = Follower(Ros2Adapter(interval=0.25), graph)
    follower.start(wait=True)
    yield graph
    follower.stop()
