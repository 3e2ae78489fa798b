"""The ROS 2 test domain and nodes of tests/graph, for top's tests of live graphs."""
from tests.graph.conftest import ros_domain, ros_nodes  # noqa: F401 (fixtures)
