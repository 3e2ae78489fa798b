"""rtps: RTPS datagrams built here, their sequence numbers in the orders a lossy network delivers
them (repairs after later samples, resends, fragments out of order), sent to a process that maps a
DDS library; bpf/rtps.bpf.c must count each sample once and every datagram's payload."""
from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys

import pytest

from drums.probes import rtps
from tests.conftest import NO_ROS2, ROS2

pytestmark = pytest.mark.skipif(not ROS2, reason=NO_ROS2)  # the receiver loads Fast DDS's library
from tests.conftest import series

PREFIX = bytes(range(1, 13))  # the writers' participant
WRITER, FRAGMENTED = b"\x00\x00\x01\x03", b"\x00\x00\x02\x03"  # entity kind 0x03: a user writer
PAYLOAD = b"\x00\x01\x00\x00" + b"p" * 60  # CDR encapsulation header, then the sample

# Loads a DDS library, so the agent parses its datagrams; receives each with the call it is told.
RECEIVER = r"""
import ctypes, json, os, socket, sys
ctypes.CDLL(os.path.join(sys.prefix, "lib", "libfastdds.so"))
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
print(json.dumps(s.getsockname()[1]), flush=True)
for line in sys.stdin:
    call, n = line.split()
    for _ in range(int(n)):
        s.recvmsg(65536) if call == "recvmsg" else s.recvfrom(65536)
    print(json.dumps(n), flush=True)
"""


def data(entity: bytes, sn: int) -> bytes:
    # extraFlags, octetsToInlineQos (16: to the payload), readerId, writerId, writerSN (high, low)
    body = struct.pack("<HH4s4sII", 0, 16, b"\0" * 4, entity, sn >> 32, sn & 0xFFFFFFFF) + PAYLOAD
    return struct.pack("<BBH", 0x15, 0x05, len(body)) + body  # DATA, little-endian, carries data


def data_frag(entity: bytes, sn: int, fragment: int, size: int, sample: int) -> bytes:
    # ... then fragmentStartingNum, fragmentsInSubmessage, fragmentSize, sampleSize (28 to the payload)
    body = struct.pack("<HH4s4sIIIHHI", 0, 28, b"\0" * 4, entity, sn >> 32, sn & 0xFFFFFFFF,
                       fragment, 1, size, sample) + b"f" * size
    return struct.pack("<BBH", 0x16, 0x01, len(body)) + body


def datagram(*submessages: bytes) -> bytes:
    return b"RTPS\x02\x03\x01\x0f" + PREFIX + b"".join(submessages)


@pytest.fixture
def receiver(rtps_probe, collect):
    proc = subprocess.Popen([sys.executable, "-c", RECEIVER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    port = json.loads(proc.stdout.readline())
    collect(rtps_probe)  # the probe finds the process and its library

    def receive(call: str, *datagrams: bytes) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for d in datagrams:
                s.sendto(d, ("127.0.0.1", port))
        proc.stdin.write(f"{call} {len(datagrams)}\n")
        proc.stdin.flush()
        assert json.loads(proc.stdout.readline()) == str(len(datagrams))
    receive.pid = proc.pid
    yield receive
    proc.stdin.close()
    proc.wait(timeout=10)


def received(rtps_probe, collect, pid: int, entity: bytes) -> tuple[int, int, int]:
    snap = collect(rtps_probe)
    writer = (PREFIX + entity).hex()
    return tuple(sum(series(snap, m.name, pid=pid, writer=writer).values())
                 for m in (rtps.SAMPLES_RECEIVED, rtps.RECEIVED_BYTES, rtps.RECEIVED_WIRE_BYTES))


@pytest.mark.kernel
def test_each_sample_counts_once_in_whatever_order_its_datagrams_come(rtps_probe, collect, receiver):
    # 3 lost and repaired after 4 and 5; 5 and 2 resent; two samples in one datagram
    receiver("recvmsg", *(datagram(data(WRITER, sn)) for sn in (1, 2, 4, 5, 3, 5)),
             datagram(data(WRITER, 2), data(WRITER, 6)))
    assert received(rtps_probe, collect, receiver.pid, WRITER) == (6, 6 * len(PAYLOAD), 8 * len(PAYLOAD))
    # After 100: 37 is 63 behind, the oldest a repair can be and still count; 36 is too old to tell
    receiver("recvfrom", *(datagram(data(WRITER, sn)) for sn in (100, 37, 36, 37)))
    assert received(rtps_probe, collect, receiver.pid, WRITER) == (8, 8 * len(PAYLOAD), 12 * len(PAYLOAD))


@pytest.mark.kernel
def test_a_fragmented_sample_counts_once_at_its_full_size(rtps_probe, collect, receiver):
    # Three fragments of 1000 bytes, the first lost and repaired after the others; the second resent
    receiver("recvmsg", *(datagram(data_frag(FRAGMENTED, 7, f, 1000, 3000)) for f in (2, 3, 1, 2)))
    assert received(rtps_probe, collect, receiver.pid, FRAGMENTED) == (1, 3000, 4000)
