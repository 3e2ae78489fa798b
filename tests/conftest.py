"""Shared fixtures: the real BPF probes, loaded once per test session into a pin folder of the
session's own, so that a running agent or another test session is left alone."""
from __future__ import annotations

import contextlib
import fcntl
import glob
import importlib.util
import os
import re
import shutil
import socket
import subprocess
import threading
import time

import pytest

from drums.kernel.features import Features
from drums.metrics import Snapshot
from drums.proctable import ProcessTable

TEST_PIN_ROOT = f"/sys/fs/bpf/drums_test_{os.getpid()}"
# How much longer than here things take: under make test-kernels' software emulation, about ten
# times (tests/kernels/guest.py sets it). Waits for a process or an answer are scaled by it.
TIME_SCALE = float(os.environ.get("DRUMS_TEST_TIME_SCALE", "1"))
# ROS 2 from PyPI (rclpy, Fast DDS) has wheels for x86_64 alone: an arm64 kernel's run
# (tests/kernels/arm64.py) has none, and its agent runs no ROS 2 graph nor per-topic probes.
ROS2 = importlib.util.find_spec("rclpy") is not None
NO_ROS2 = "ROS 2's wheels on PyPI are x86_64 only: not installed on this machine"
_domain_slot: tuple[int, object] | None = None  # (slot, the lock file held for the session)


def ros_domain_id(offset: int = 0) -> int:
    """A ROS 2 domain id of this test session's own (offset 0-9 for its several uses), so that
    other ROS 2 software on the host, and the other lanes of make test, neither show up in its
    graphs nor see its nodes. Sessions side by side each hold a slot of ten ids by a lock file: ids
    drawn from the PID could meet (10-99, all safe for any host)."""
    global _domain_slot
    if _domain_slot is None:
        for slot in range(1, 10):
            lock = open(f"/tmp/drums-test-ros-domains-{slot}.lock", "w")
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                lock.close()
                continue
            _domain_slot = (slot, lock)
            break
        else:
            raise RuntimeError("no ROS 2 domain slot free: nine test sessions at once on this host?")
    return 10 * _domain_slot[0] + offset


_FEATURES = Features()  # one look at the kernel for the whole session (the fentry check loads bcc)


@pytest.fixture(scope="session")
def features():
    return _FEATURES


@pytest.fixture(scope="session")
def proctable():
    return ProcessTable()


def _started(probe):
    probe.start()
    yield probe
    probe.unload()


def offered_paths(probe_class) -> list[str]:
    """The attach paths of a BPF probe that this kernel offers (as `drums doctor` lists them): the
    probe's own tests run on each, forced one at a time. None offered fails the tests that need the
    probe, never skips them."""
    from drums.probes.bpf import usable_paths
    paths = [p.name for p in usable_paths(probe_class.paths, _FEATURES)] or ["none offered"]
    # make test-kernels --ci: the path the agent takes only, to fit CI's time (tests/kernels/run.py).
    return paths[:1] if os.environ.get("DRUMS_TEST_PATHS") == "first" else paths


def started_on_path(probe, path: str):
    """The probe held to one attach path (as `drums agent --attach` holds it), under a pin root of
    its own: loading a probe removes its pins of any other path."""
    from drums.probes.registry import held_to
    probe.pin_root = f"{TEST_PIN_ROOT}_{path}"
    if path == "none offered":
        pytest.fail(f"this kernel offers probe {probe.name} no attach path")
    held_to(probe, path).start()
    assert probe.status.attach_type == path
    yield probe
    probe.unload()


@pytest.fixture(scope="session")
def sockets_probe(features, proctable):
    from drums.probes.sockets import SocketsProbe
    yield from _started(SocketsProbe(features, proctable, pin_root=TEST_PIN_ROOT))


@pytest.fixture(scope="session")
def sched_probe(features, proctable):
    from drums.probes.sched import SchedProbe
    yield from _started(SchedProbe(features, proctable, pin_root=TEST_PIN_ROOT))


@pytest.fixture(scope="session")
def tcp_probe(features, proctable):
    from drums.probes.tcp import TcpProbe
    yield from _started(TcpProbe(features, pin_root=TEST_PIN_ROOT))


@pytest.fixture(scope="session")
def rtps_probe(features, proctable):
    from drums.probes.rtps import RtpsProbe
    yield from _started(RtpsProbe(features, proctable, pin_root=TEST_PIN_ROOT))


@pytest.fixture(scope="session")
def rcl_probe(features, proctable):
    from drums.probes.rcl import RclProbe
    yield from _started(RclProbe(features, proctable, pin_root=TEST_PIN_ROOT))


@pytest.fixture
def collect(proctable):
    """collect(probe) -> Snapshot, as the agent would take it."""
    def take(probe) -> Snapshot:
        proctable.refresh()
        snap = Snapshot()
        probe.collect(snap)
        return snap
    return take


def series(snap: Snapshot, metric_name: str, **labels) -> dict[tuple, object]:
    """The rows of one metric whose labels match, keyed by their full label tuple."""
    for metric, rows in snap.series.items():
        if metric.name == metric_name:
            idx = {k: metric.labels.index(k) for k in labels}
            return {lv: v for lv, v in rows if all(lv[i] == str(labels[k]) for k, i in idx.items())}
    return {}


def spliced_from(tx: socket.socket, rx: socket.socket, size: int, pipe: tuple[int, int]) -> int:
    """Send `size` bytes on `tx` and take them from `rx` by splice(2) into the pipe (emptied as it
    goes); the splices it took."""
    r, w = pipe
    sender = threading.Thread(target=tx.sendall, args=(b"p" * size,), daemon=True)
    sender.start()
    got = splices = 0
    while got < size:
        n = os.splice(rx.fileno(), w, min(65536, size - got))
        assert n > 0
        got += n
        splices += 1
        while n:
            n -= len(os.read(r, n))
    sender.join(30)
    return splices


def tids_of(pid: int) -> list[int]:
    return [int(t) for t in os.listdir(f"/proc/{pid}/task")]


def settle(pid: int, timeout: float = 5.0) -> None:
    """Wait until every thread of `pid` sleeps: a running slice is counted by neither the probe nor
    schedstat until the thread leaves the CPU."""
    deadline = time.monotonic() + timeout
    while True:
        states = []
        for tid in tids_of(pid):
            try:
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    states.append(f.read().rsplit(")", 1)[1].split()[0])
            except FileNotFoundError:
                pass  # the thread has just exited
        if all(s == "S" for s in states):
            return
        assert time.monotonic() < deadline, f"threads of {pid} still in states {states}"
        time.sleep(0.005)


def eventually(check, timeout: float = 3.0):
    """Retry `check` (which asserts) until it passes or `timeout` runs out; return its result."""
    deadline = time.monotonic() + timeout * TIME_SCALE
    while True:
        try:
            return check()
        except AssertionError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def wait_until(condition, what, timeout: float = 5.0) -> None:
    """`what`: a string, or a function that says what was awaited and what was seen at the end."""
    deadline = time.monotonic() + timeout * TIME_SCALE
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what() if callable(what) else what}")
        time.sleep(0.01)


@contextlib.contextmanager
def every(seconds: float, step):
    """Run `step()` every `seconds` in a thread of its own until the block ends."""
    stop = threading.Event()

    def run():
        while not stop.wait(seconds):
            step()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


@contextlib.contextmanager
def connected_pairs(count: int):
    """`count` loopback TCP connections of this process, as (client, server) pairs, closed at the
    end whatever the test did with them."""
    pairs = []
    try:
        with socket.create_server(("127.0.0.1", 0)) as lst:
            for _ in range(count):
                client = socket.create_connection(lst.getsockname())
                pairs.append((client, lst.accept()[0]))
        yield pairs
    finally:
        for pair in pairs:
            for sock in pair:
                sock.close()


def ip(*args: str) -> None:
    """Run ip(8), failing the test with its message if it fails."""
    subprocess.run(("ip", *args), check=True, capture_output=True)


@contextlib.contextmanager
def peer_namespace(index: int):
    """A network namespace joined to this one by a veth pair: (namespace, its device, our
    address, its address, our device). Only there can the test lose packets on purpose: loopback never drops them."""
    tag = f"{os.getpid() % 100000}{index}"
    ns, ours, theirs = f"drums_test_{tag}", f"drt{tag}a", f"drt{tag}b"
    local = f"10.213.{os.getpid() % 250}.{4 * index + 1}"
    remote = f"10.213.{os.getpid() % 250}.{4 * index + 2}"
    try:
        ip("netns", "add", ns)
        ip("link", "add", ours, "type", "veth", "peer", "name", theirs, "netns", ns)
        ip("addr", "add", f"{local}/30", "dev", ours)
        ip("link", "set", ours, "up")
        ip("-n", ns, "addr", "add", f"{remote}/30", "dev", theirs)
        ip("-n", ns, "link", "set", theirs, "up")
        yield ns, theirs, local, remote, ours
    finally:
        # Deleting the namespace frees its end of the pair only later: delete ours first.
        subprocess.run(("ip", "link", "del", ours), capture_output=True)
        subprocess.run(("ip", "netns", "del", ns), capture_output=True)


def pytest_sessionstart(session):
    if os.geteuid() != 0:
        raise pytest.UsageError("Drums tests load BPF programs: run them as root (make test)")
    for old in glob.glob("/sys/fs/bpf/drums_test_*"):  # left by sessions that were killed
        pid = re.match(r"/sys/fs/bpf/drums_test_(\d+)", old)  # drums_test_<pid>, or with _<path> after it
        if pid and not os.path.exists(f"/proc/{pid[1]}"):
            shutil.rmtree(old, ignore_errors=True)


def pytest_sessionfinish(session):
    shutil.rmtree(TEST_PIN_ROOT, ignore_errors=True)
