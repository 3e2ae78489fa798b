"""Every graph adapter by name, and which one `auto` means on this host."""
from __future__ import annotations

import importlib.util
import os

from drums.errors import UsageError
from drums.graph.adapter import Adapter
from drums.graph.model import Host

ADAPTERS = ("ros2", "ros1", "static", "auto")


def default() -> str:
    """ros1 or ros2 as ROS_VERSION says; else ros2 where rclpy is importable; else auto."""
    if os.environ.get("ROS_VERSION") == "1":
        return "ros1"
    if os.environ.get("ROS_VERSION") == "2" or importlib.util.find_spec("rclpy") is not None:
        return "ros2"
    return "auto"


def build(name: str, graph_file: str = "", announce: Host | None = None) -> Adapter:
    """`announce`: an agent's own host, address and URL, which the ros2 reader tells the other
    agents of its ROS domain (ROS 1 and static graphs name their hosts themselves)."""
    if graph_file and name != "static":
        raise UsageError(f"--graph-file is read by --graph static only, not by --graph {name}")
    if name == "ros2":
        from drums.graph.ros2 import Ros2Adapter
        return Ros2Adapter(announce=announce)
    if name == "ros1":
        from drums.graph.ros1 import Ros1Adapter
        return Ros1Adapter()
    if name == "static":
        if not graph_file:
            raise UsageError("--graph static needs --graph-file FILE (a YAML description)")
        from drums.graph.static import StaticAdapter
        return StaticAdapter(graph_file)
    if name == "auto":
        from drums.graph.auto import AutoAdapter
        return AutoAdapter()
    raise UsageError(f"--graph {name}: one of {', '.join(ADAPTERS)}")
