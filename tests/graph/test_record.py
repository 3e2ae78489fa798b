"""`drums record` as a user runs it, beside `drums agent --graph ros2` and rclpy nodes in their own
processes: the MCAP file it leaves on SIGINT is read back by the `mcap` reader (PyPI), every
message is valid under its channel's schema, and a node's and a topic's rates add up to the messages
the talker published; a recorder killed outright leaves a file read back up to its last chunk."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest
from mcap.reader import NonSeekingReader, make_reader

from drums.foxglove.record import CHUNK
from tests.agentproc import running_agent
from tests.conftest import wait_until

BURST = 50  # messages the talker publishes, at 10 Hz, after the recording began
TYPES = {"string": str, "number": (int, float), "null": type(None)}


def recorder(url: str, output: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "drums", "record", "--output", output, "--agent", url],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def valid(schema: dict, message: dict) -> bool:
    """Whether the message has the schema's properties, each of one of its types, and no other."""
    properties = schema["properties"]
    return message.keys() == properties.keys() and all(
        isinstance(message[k], tuple(TYPES[t] for t in p["type"])) for k, p in properties.items())


def integral(messages: list[tuple[int, dict]], field: str) -> float:
    """A rate over the recording: each message's value over the time since the one before."""
    return sum(m[field] * (t - t0) / 1e9 for (t0, _), (t, m) in zip(messages, messages[1:]) if m[field] is not None)


@pytest.mark.lane2
def test_a_recording_reads_back_with_valid_messages_whose_rates_add_up(ros_nodes, tmp_path):
    host, output = socket.gethostname(), str(tmp_path / "robot.mcap")
    with running_agent("--graph", "ros2") as url:
        base = url.rsplit("/", 1)[0]
        # On a topic of their own: the other lanes of make test count /chatter exactly
        remap = ("--ros-args", "-r", "chatter:=rec_chatter")
        ros_nodes("listener", "rec_listener", *remap)
        talker = ros_nodes("talker", "rec_talker", *remap, env={"DRUMS_TEST_BURST": str(BURST)})
        rec = recorder(base, output)
        started = time.monotonic()
        time.sleep(6)  # the nodes in the graph, and polls before the burst
        talker.go()
        wait_until(lambda: talker.count() == BURST, "the burst published", timeout=20)
        time.sleep(max(0.0, 30 - (time.monotonic() - started)))  # 30 s in all; the last polls after the burst
        rec.send_signal(signal.SIGINT)
        assert rec.wait(timeout=30) == 0, rec.stdout.read()
    with open(output, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()  # written on SIGINT, with the index
        assert summary is not None and summary.statistics.message_count > 0
        by_topic: dict[str, list[tuple[int, dict]]] = {}
        for schema, channel, message in reader.iter_messages():
            value = json.loads(message.data)
            assert valid(json.loads(schema.data), value), (channel.topic, value)
            by_topic.setdefault(channel.topic, []).append((message.log_time, value))
    assert {f"/drums/nodes/{host}/rec_talker", "/drums/topics/rec_chatter", "/drums/edges/rec_chatter/rec_talker/rec_listener",
            f"/drums/hosts/{host}"} <= by_topic.keys(), sorted(by_topic)
    talker_rows = by_topic[f"/drums/nodes/{host}/rec_talker"]
    assert all(m["pid"] == talker.proc.pid for _, m in talker_rows)
    # Stamped with the agent's clock, a second apart as it was polled.
    times = [t for t, _ in talker_rows]
    assert all(0.5e9 < b - a < 3e9 for a, b in zip(times, times[1:])), times
    for topic, field in ((f"/drums/nodes/{host}/rec_talker", "published_hz"), ("/drums/topics/rec_chatter", "rate_hz"),
                         ("/drums/edges/rec_chatter/rec_talker/rec_listener", "rate_hz")):
        assert abs(integral(by_topic[topic], field) - BURST) <= 0.02 * BURST, (topic, by_topic[topic])


@pytest.mark.lane2
def test_a_killed_recorder_leaves_a_file_read_back_up_to_its_last_chunk(tmp_path):
    output = str(tmp_path / "killed.mcap")
    with running_agent() as url:
        rec = recorder(url.rsplit("/", 1)[0], output)
        time.sleep(12)
        killed_at = time.time()
        rec.kill()
        rec.wait()
    read, written = [], 0
    with open(output, "rb") as f:
        try:
            for record_ in NonSeekingReader(f).iter_messages(log_time_order=False):
                read.append(record_[2].log_time)
                written += len(record_[2].data)
        except Exception:  # the cut in the unfinished chunk
            pass
    assert read, "nothing read back"
    # What was lost is the unfinished chunk: at the rate the messages came, at most a chunk's worth
    # of time (and a poll) before the kill.
    per_second = written / max((read[-1] - read[0]) / 1e9, 1e-9)
    assert killed_at - read[-1] / 1e9 <= CHUNK / per_second + 2, (killed_at - read[-1] / 1e9, per_second)
    with pytest.raises(Exception):
        make_reader(open(output, "rb")).get_summary()  # no summary: the recorder was killed
