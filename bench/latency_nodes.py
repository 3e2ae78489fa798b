"""The ROS 2 nodes of bench/topic_latency.py, each run as its own process.

    python latency_nodes.py pub RATE SECONDS   # waits for a subscriber, publishes, prints "sent N"
    python latency_nodes.py pub RATE           # the same until its input ends
    python latency_nodes.py sub                # on end of input prints {"count", "p50_us", "p99_us"}
    python latency_nodes.py sub all            # ... and "at" and "latencies": each message's, in ns

Each message carries its publisher's CLOCK_MONOTONIC time (one clock for every process on the
host): the subscriber's latency is publish call to callback, through rclpy, DDS and the kernel.
"""
import json
import sys
import threading
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def publish(rate: float, seconds: float | None) -> None:
    """At `rate` for `seconds`, or until the input ends."""
    node = Node("latency_pub")
    pub = node.create_publisher(String, "latency", QOS)
    while pub.get_subscription_count() == 0:
        time.sleep(0.05)
    time.sleep(1.0)  # let the match settle on both sides
    period, sent = 1.0 / rate, 0
    ended = threading.Event()
    if seconds is None:
        threading.Thread(target=lambda: (sys.stdin.read(), ended.set()), daemon=True).start()
        print("publishing", flush=True)
    start = time.monotonic()
    while not ended.is_set() and (seconds is None or time.monotonic() - start < seconds):
        now = time.monotonic()
        due = start + sent * period
        if now < due:
            time.sleep(due - now)
        pub.publish(String(data=str(time.monotonic_ns())))
        sent += 1
    print("sent", sent, flush=True)


def subscribe(every: bool) -> None:
    """`every`: print each message's arrival and latency too."""
    node = Node("latency_sub")
    latencies, arrivals = [], []

    def take(m):
        now = time.monotonic_ns()
        latencies.append(now - int(m.data))
        arrivals.append(now)
    node.create_subscription(String, "latency", take, QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    print("ready", flush=True)
    sys.stdin.read()
    got = sorted(latencies)
    out = {"count": len(got), "p50_us": got[len(got) // 2] / 1e3 if got else None,
           "p99_us": got[int(len(got) * 0.99)] / 1e3 if got else None}
    if every:
        out.update(at=arrivals, latencies=latencies)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    rclpy.init()
    if sys.argv[1] == "pub":
        publish(float(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else None)
    else:
        subscribe(sys.argv[2:] == ["all"])
