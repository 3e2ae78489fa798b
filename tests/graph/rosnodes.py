"""ROS 2 test nodes, each run as its own process: `python rosnodes.py ROLE [NAME ...]`.

Roles: talker (publishes /chatter at 10 Hz), listener (subscribes /chatter), both with the Deadline
QoS $DRUMS_TEST_DEADLINE_MS if set, producer (a 1 MB image-like message on /image at 10 Hz;
$DRUMS_TEST_IMAGE_BYTES sets another size), viewer
(subscribes /image), processor (/image -> /processed), sink (subscribes /processed), idle (a node
with no endpoints of its own), leaker (keeps $DRUMS_TEST_LEAK_BYTES more memory, default 100 kB,
every 0.1 s, as a leak does), flooder (logs a line every 10 ms: it floods /rosout), metronome (on each
"go", publishes $DRUMS_TEST_BURST messages on /beat (with $DRUMS_TEST_DEADLINE_MS), the times between
them cycling through $DRUMS_TEST_PERIODS_MS, default "20x9,40": 20 ms apart but every tenth 40 ms;
on a line "beats" it prints its clock, CLOCK_MONOTONIC in ns, right before each publish (from a
thread of real-time priority); each
message says CLOCK_REALTIME in ns as it is published), receiver (takes /beat, requesting
$DRUMS_TEST_DEADLINE_MS, and on a line "latencies" prints for each message the ns from its stamp
to the callback's start; "ages" the ns from the RMW's source stamp to right after rclpy took it, and
"transports" the RMW's received less source stamps, as the message info says), reactor
(takes /beat, sleeps 15 ms and publishes /reaction; a timer publishes /status every 50 ms; on a line
"reactions" it prints how long each callback took from its start to its publish, in ns; on a line
"matched" how many subscribers its /reaction publisher has matched). Several NAMEs
put several nodes in one process; arguments after --ros-args go to ROS (remapping). Prints
"ready <pid>" once its nodes exist, and on each line of input "count <n>" with the messages it
published or received so far (a line "go" starts a burst instead: see DRUMS_TEST_BURST). With
$DRUMS_TEST_IMPORT_DELAY=S it waits S seconds before it loads ROS 2, as a program that imports
rclpy late does.
"""
import collections
import os
import sys
import threading
import time

time.sleep(float(os.environ.get("DRUMS_TEST_IMPORT_DELAY", "0")))
import rclpy  # noqa: E402  (after the delay, on purpose)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from std_msgs.msg import String, UInt8MultiArray  # noqa: E402

IMAGE_BYTES = int(os.environ.get("DRUMS_TEST_IMAGE_BYTES", 1 << 20))


def payload(msg) -> int:
    """Bytes of the serialized message as an RTPS DATA submessage carries it: padded to 4."""
    return -(-len(serialize_message(msg)) // 4) * 4
counted = [0]
# With DRUMS_TEST_BURST=N each publisher waits for a line "go" and for its subscribers
# ($DRUMS_TEST_BURST_SUBSCRIBERS, default 1: a subscriber matched late misses what came before),
# publishes exactly N messages, and stops.
burst = int(os.environ.get("DRUMS_TEST_BURST", "0"))
burst_subscribers = int(os.environ.get("DRUMS_TEST_BURST_SUBSCRIBERS", "1"))
bursts = []  # per publisher: messages still to publish; -1: no limit


def publishes(pub, msg):
    """A timer callback: publish unless the burst is spent, and count what was published."""
    left = [0 if burst else -1]
    bursts.append(left)

    def tick():
        if left[0] == 0 or (burst and pub.get_subscription_count() < burst_subscribers):
            return
        left[0] -= 1
        pub.publish(msg)
        counted[0] += 1
    return tick


def forwards(node, pub):
    """A subscription callback that publishes what it takes; in a burst, what is taken before the
    publisher's own subscribers matched waits for them (DDS discovery is pairwise: the graph may
    show the edge before this publisher knows of it)."""
    waiting = collections.deque()

    def flush():
        while waiting and (not burst or pub.get_subscription_count() >= burst_subscribers):
            pub.publish(waiting.popleft())
    if burst:
        node.create_timer(0.01, flush)

    def take(msg):
        counted[0] += 1
        waiting.append(msg)
        flush()
    return take


def qos():
    """Reliable (best effort with $DRUMS_TEST_BEST_EFFORT set), with a history of at least 100 messages (a whole burst if longer), and the
    Deadline QoS $DRUMS_TEST_DEADLINE_MS if set. A reliable writer sends again only what its
    history still holds, and a subscriber's history drops the oldest messages its callback has not
    taken yet: with a depth of 10, a sink on a busy host missed 6 of 30 samples of 1 MB over UDP, and
    top's test once counted one lost on /chatter at 10 Hz, as a listener not scheduled for a second
    (10 messages) would."""
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile
    from rclpy.qos import ReliabilityPolicy
    deadline = int(os.environ.get("DRUMS_TEST_DEADLINE_MS", "0"))
    reliability = ReliabilityPolicy.BEST_EFFORT if os.environ.get("DRUMS_TEST_BEST_EFFORT") else ReliabilityPolicy.RELIABLE
    return QoSProfile(depth=max(100, burst), deadline=Duration(nanoseconds=deadline * 1_000_000), reliability=reliability)


def make(role: str, name: str) -> Node:
    node = Node(name)
    if role == "talker":
        node.create_timer(0.1, publishes(node.create_publisher(String, "chatter", qos()), String(data="hello")))
    elif role == "listener":
        node.create_subscription(String, "chatter", lambda m: counted.__setitem__(0, counted[0] + 1), qos())
    elif role == "producer":
        msg = UInt8MultiArray(data=bytes(IMAGE_BYTES))
        node.create_timer(0.1, publishes(node.create_publisher(UInt8MultiArray, "image", qos()), msg))
    elif role == "viewer":
        node.create_subscription(UInt8MultiArray, "image", lambda m: counted.__setitem__(0, counted[0] + 1), qos())
    elif role == "processor":
        pub = node.create_publisher(UInt8MultiArray, "processed", qos())
        node.create_subscription(UInt8MultiArray, "image", forwards(node, pub), qos())
    elif role == "sink":
        node.create_subscription(UInt8MultiArray, "processed", lambda m: counted.__setitem__(0, counted[0] + 1), qos())
    elif role == "leaker":
        leak_bytes = int(os.environ.get("DRUMS_TEST_LEAK_BYTES", 100_000))
        kept = []
        # b"x" * n writes every page, so the memory is resident at once
        node.create_timer(0.1, lambda: kept.append(b"x" * leak_bytes))
    elif role == "metronome":
        pub = node.create_publisher(String, "beat", qos())
        threading.Thread(target=beat, args=(pub,), daemon=True).start()
    elif role == "receiver":
        def receive(msg, info):
            latencies.append(time.time_ns() - int(msg.data))
            ages.append(took[0] - info["source_timestamp"])
            transports.append(info["received_timestamp"] - info["source_timestamp"])
        node.create_subscription(String, "beat", receive, qos())
    elif role == "reactor":
        out = node.create_publisher(String, "reaction", 10)
        reacting.append(out)

        def react(msg):
            began = time.monotonic_ns()
            time.sleep(0.015)
            reactions.append(time.monotonic_ns() - began)
            out.publish(msg)
        node.create_subscription(String, "beat", react, 10)
        status = node.create_publisher(String, "status", 10)
        node.create_timer(0.05, lambda: status.publish(String(data="ok")))
    elif role == "flooder":
        node.create_timer(0.01, lambda: node.get_logger().info("flooding /rosout"))
    elif role != "idle":
        raise SystemExit(f"unknown role {role}")
    return node


started = threading.Event()
beats = []  # time.monotonic_ns() right before each publish of the metronome
reactions = []  # ns from the start of each of the reactor's callbacks to its publish
latencies = []  # ns from the stamp of each message the receiver took to its callback's start
ages, transports = [], []  # ns from the RMW's source stamp to the take, and to its received stamp
took = [0]  # CLOCK_REALTIME in ns right after the executor's last take
reacting = []  # the reactor's /reaction publishers


class TakeClock(SingleThreadedExecutor):
    """Notes the time as soon as a message is taken, before rclpy dispatches it to its callback (which
    takes longer than the middleware's part on this host): what a C++ node would see."""

    def _take_subscription(self, sub):
        taken = super()._take_subscription(sub)
        took[0] = time.time_ns()
        return taken


def schedule() -> list[int]:
    """$DRUMS_TEST_PERIODS_MS ("20x9,40": nine of 20 ms, then one of 40) in ns."""
    out = []
    for part in os.environ.get("DRUMS_TEST_PERIODS_MS", "20x9,40").split(","):
        ms, _, times = part.partition("x")
        out += [int(float(ms) * 1_000_000)] * int(times or 1)
    return out


def beat(pub) -> None:
    """Publish on an absolute schedule, so that a late wakeup does not shift the ones after it. The
    thread runs at a real-time priority: the tests compare its clock, read right before rcl_publish,
    with the probe's at rcl_publish's entry, and on a host busy with the other lanes of the suite a
    task run in between put milliseconds into one period of the two (p99 3 ms apart)."""
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))  # 0: this thread
    periods = schedule()
    while True:  # a burst at each "go"
        started.wait()
        started.clear()
        # With $DRUMS_TEST_BURST_SUBSCRIBERS, not before that many subscribers matched (DDS discovery
        # over UDP can take seconds); without, whether or not anyone listens.
        while pub.get_subscription_count() < int(os.environ.get("DRUMS_TEST_BURST_SUBSCRIBERS", "0")):
            time.sleep(0.01)
        due = time.monotonic_ns()
        for i in range(burst):
            time.sleep(max(0, due - time.monotonic_ns()) / 1e9)
            beats.append(time.monotonic_ns())
            pub.publish(String(data=str(time.time_ns())))
            counted[0] += 1
            due += periods[i % len(periods)]


def main() -> None:
    ours = sys.argv[:sys.argv.index("--ros-args")] if "--ros-args" in sys.argv else sys.argv
    role, names = ours[1], ours[2:] or [ours[1]]
    rclpy.init(args=sys.argv)
    executor = TakeClock()
    for name in names:
        executor.add_node(make(role, name))
    print("ready", os.getpid(), flush=True)

    def report():
        for line in sys.stdin:
            if line.strip() == "go":
                for left in bursts:
                    left[0] = burst
                started.set()
                continue
            asked = {"beats": beats, "reactions": reactions, "latencies": latencies, "ages": ages,
                     "transports": transports}.get(line.strip())
            if asked is not None:
                print(line.strip(), *asked, flush=True)
                continue
            if line.strip() == "matched":
                print("matched", *(pub.get_subscription_count() for pub in reacting), flush=True)
                continue
            print("count", counted[0], flush=True)
        os._exit(0)  # input closed: the test is done with us
    threading.Thread(target=report, daemon=True).start()
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # SIGINT: rclpy shut down and said goodbye to the other participants


if __name__ == "__main__":
    main()
