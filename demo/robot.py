"""The demo robot's nodes, one per process: `python demo/robot.py ROLE`.

camera      publishes /camera/image, about 1 MB at 30 Hz ($DRUMS_DEMO_IMAGE_BYTES: another size)
processor   /camera/image -> /detections (a small message per image)
controller  /detections -> /cmd_vel, at the camera's pace
logger      logs a line to /rosout for each second of detections

$DRUMS_DEMO_FAULT injects one of the faults of the paper that started Drums, $DRUMS_DEMO_FAULT_AFTER
seconds after start (default 20), for $DRUMS_DEMO_FAULT_FOR seconds (default: to the end): leak (the
processor keeps one image in ten: its memory grows by about 3 MB/s, up to 1 GiB) and flood (the
logger logs in a tight loop to /rosout). The third, throttle (a router that drops bandwidth), is
made outside the nodes, on the camera computer's link (demo/demo.sh). The node prints when its
fault starts and ends ("fault leak started at <Unix time>"), for the scenario tests' clock.
"""
import os
import sys
import time

import rclpy
from geometry_msgs.msg import Twist
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import String, UInt8MultiArray

IMAGE_BYTES = int(os.environ.get("DRUMS_DEMO_IMAGE_BYTES", "1000000"))
LEAK_BYTES = 1_000_000  # kept for one image in ten, whatever the images' size: 3 MB/s
RATE = 30.0
FAULT = os.environ.get("DRUMS_DEMO_FAULT", "")
FAULT_AFTER = float(os.environ.get("DRUMS_DEMO_FAULT_AFTER", "20"))
FAULT_FOR = float(os.environ.get("DRUMS_DEMO_FAULT_FOR", "inf"))
LEAK_IMAGES = (1 << 30) // LEAK_BYTES  # the leak stops at 1 GiB: a demo must not take the machine down


class Demo(Node):
    def __init__(self, role: str):
        super().__init__(role)
        self.started = time.monotonic()
        self.fault_said = ""  # the fault's last state printed: "", "started", "ended"
        self.kept = []  # the leak
        self.images = 0
        if role == "camera":
            self.image = UInt8MultiArray(data=bytes(IMAGE_BYTES))
            self.pub = self.create_publisher(UInt8MultiArray, "/camera/image", 5)
            self.create_timer(1 / RATE, lambda: self.pub.publish(self.image))
        elif role == "processor":
            self.pub = self.create_publisher(String, "/detections", 10)
            self.create_subscription(UInt8MultiArray, "/camera/image", self.on_image, 5)
        elif role == "controller":
            self.pub = self.create_publisher(Twist, "/cmd_vel", 10)
            self.create_subscription(String, "/detections", lambda _: self.pub.publish(Twist()), 10)
        elif role == "logger":
            self.seen = 0
            self.create_subscription(String, "/detections", self.on_detection, 10)
            self.create_timer(1.0, self.report)
        else:
            raise SystemExit(f"unknown role {role}: camera, processor, controller or logger")

    def faulty(self, fault: str) -> bool:
        if FAULT != fault:
            return False
        elapsed = time.monotonic() - self.started
        state = "started" if FAULT_AFTER < elapsed < FAULT_AFTER + FAULT_FOR else \
            "ended" if elapsed >= FAULT_AFTER + FAULT_FOR else ""
        if state != self.fault_said:
            self.fault_said = state
            print(f"fault {fault} {state} at {time.time():.3f}", flush=True)
        return state == "started"

    def on_image(self, msg) -> None:
        self.images += 1
        if self.faulty("leak") and self.images % 10 == 0 and len(self.kept) < LEAK_IMAGES:
            self.kept.append(bytes(msg.data[:1]) * LEAK_BYTES)  # memory that is never freed
        self.pub.publish(String(data=f"objects in {len(msg.data)} bytes"))

    def on_detection(self, _msg) -> None:
        self.seen += 1

    def report(self) -> None:
        self.get_logger().info(f"{self.seen} detections so far")
        while self.faulty("flood") and rclpy.ok():  # an emergency stop that logs in a tight loop
            self.get_logger().warning("emergency stop: obstacle!")


def main() -> None:
    rclpy.init(args=sys.argv)
    node = Demo(sys.argv[1])
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == "__main__":
    main()
