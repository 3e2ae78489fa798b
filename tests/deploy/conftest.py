"""The mixin's tests run ROS 2 nodes on the test session's own DDS domain, as the graph tests do."""
from tests.graph.conftest import ros_domain  # noqa: F401  (an autouse session fixture, shared)
