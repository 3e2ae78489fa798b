"""What Drums' rclpy child processes share: how they start rclpy, and the rclpy side of
/diagnostics, a diagnostic_msgs/DiagnosticArray for each line of JSON the agent writes
({"status": [{level, name, message, hardware_id, values: [[key, value], ...]}, ...]}), answered
with a line the agent reads.

rclpy never runs in the agent. The arrays go out from the ROS 2 graph reader when the agent has one
(one rclpy process and one DDS participant for both), else from a child of their own
(`python -m drums.rclchild TOPIC`, as `drums detect --ros` publishes its anomalies), which imports
nothing of the agent's.
"""
from __future__ import annotations

import json
import sys

from drums.proctable import name_helper
from drums.selfcost import leave_out, on_first_use, without_openssl

# Drums' rclpy children log through the agent, not to files: rcl's file log needs a writable
# ~/.ros/log, and without one (a user whose HOME is not theirs) rclpy.init fails.
RCLPY_ARGS = ["--ros-args", "--disable-external-lib-logs"]
OWN_NODES = {"/diagnostics": "_drums_diagnostics"}  # any other topic: _drums_anomalies (drums detect)
INSTALL_HINT = "pip install ros-rclpy ros-diagnostic-msgs (ROS 2 from PyPI)"


class Arrays:
    """A publisher of DiagnosticArrays on `topic`, from a node of its own (rclpy initialised)."""

    def __init__(self, topic: str):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        self.topic = topic
        self._types = DiagnosticArray, DiagnosticStatus, KeyValue
        self.node = rclpy.create_node(OWN_NODES.get(topic, "_drums_anomalies"), enable_rosout=False,
                                      start_parameter_services=False)
        self._publisher = self.node.create_publisher(DiagnosticArray, topic, 10)

    def publish(self, line: str | bytes) -> str:
        """Publish the array of one line: "" once it went out, else why not."""
        array_type, status_type, value_type = self._types
        try:
            array = array_type(status=[
                status_type(level=bytes([s["level"]]), name=s["name"], message=s["message"], hardware_id=s["hardware_id"],
                            values=[value_type(key=k, value=v) for k, v in s["values"]])
                for s in json.loads(line)["status"]])
            array.header.stamp = self.node.get_clock().now().to_msg()
            self._publisher.publish(array)
        except Exception as e:  # one array that cannot go out: say why, take the next
            return f"publishing {self.topic}: {e}"
        return ""

    def destroy(self) -> None:
        self.node.destroy_node()


def start_helper(role: str) -> None:
    """What each of Drums' rclpy children does first: name itself drums-<role> (the agent's
    self-metrics count it by that), and keep out what rclpy would load and never use. Measured in
    the ROS 2 graph reader (55 MB without any of this):
    - numpy, 10.5 MB: service_msgs' generated code imports it for one fixed-size array
      (ServiceEventInfo.client_gid) that only service introspection fills;
    - rosidl_generator_py's code generator, 2.9 MB with the lark parser it imports: the package
      imports it only if it can (to build message packages), beside the type support rclpy uses;
    - yaml, 1.2 MB: rclpy.parameter imports it for parameter files, which these nodes are not given."""
    name_helper(role)
    without_openssl()
    leave_out("rosidl_generator_py.generate_py_impl")
    on_first_use("numpy", "yaml")


def answer(publish_error: str) -> str:
    """The line that answers one array: what the agent's Publisher reads."""
    return json.dumps({"answer": publish_error})


def child(topic: str) -> int:
    """The child on its own: publish each array read on stdin until stdin closes."""
    try:
        import rclpy

        rclpy.init(args=RCLPY_ARGS)
        arrays = Arrays(topic)
    except Exception as e:  # no ROS 2, or a DDS that will not start: say why, the agent logs it
        print(answer(f"cannot publish {topic}: {e} ({INSTALL_HINT})"), flush=True)
        return 2
    try:
        for line in sys.stdin:
            print(answer(arrays.publish(line)), flush=True)
    except (KeyboardInterrupt, BrokenPipeError):
        pass
    finally:
        arrays.destroy()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    start_helper("diag")
    sys.exit(child(sys.argv[1] if len(sys.argv) > 1 else "/diagnostics"))
