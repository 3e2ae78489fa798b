"""`drums agent` in a process of its own, as users run it, and reading what it serves."""
import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.conftest import TIME_SCALE

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def reserved_port() -> int:
    """A free port below the kernel's ephemeral range, for a program that binds it seconds after
    it is chosen (the demo starts its nodes first): a port from free_port() may be taken meanwhile
    by any socket bound to port 0 or connecting out, as the other lane of make test has many."""
    with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
        ephemeral = int(f.read().split()[0])
    for port in random.sample(range(max(1024, ephemeral - 10000), ephemeral), 500):
        try:
            socket.create_server(("127.0.0.1", port)).close()
            return port
        except OSError:
            continue
    raise RuntimeError(f"no free port in the 10,000 below {ephemeral}")


@contextlib.contextmanager
def running_agent(*argv, bpf: bool = True, under: tuple[str, ...] = (), address: str = "127.0.0.1",
                  logs: list | None = None):
    """`drums agent` on a free port, serving; yields its /metrics URL. Stops it and checks it
    left no traceback and (for an agent with BPF probes, `bpf`) no pins behind. Each agent pins
    in a folder of its own, so that agents of tests running side by side leave each other alone.
    `under`: a command that execs the agent, e.g. one that gives it a host name of its own;
    `address`: where it listens (and is reached); `logs`: gets the agent's log once it has stopped."""
    port = free_port()
    pins = f"/sys/fs/bpf/drums_agent_{port}"
    proc = subprocess.Popen([*under, sys.executable, "-m", "drums", "agent", "--port", str(port), "--pin-dir", pins,
                             "--stream-port", "0", "--address", address, *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = f"http://{address}:{port}/metrics"
    serving(proc, url)
    try:
        yield url
    finally:  # a failed test stops its agent too
        proc.terminate()
    try:
        code = proc.wait(timeout=10 * TIME_SCALE)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR2)  # its threads' stacks, into its log
        time.sleep(1)
        proc.kill()
        pytest.fail(f"the agent did not stop within {10 * TIME_SCALE:g} s of SIGTERM; the end of its log, with what each of its "
                    f"threads was doing:\n{proc.communicate()[0][-8000:]}")
    assert code == 0
    log = proc.stdout.read()
    if logs is not None:
        logs.append(log)
    assert "Traceback" not in log, log
    if bpf:
        assert not os.path.exists(pins), "pins left behind after shutdown"


def serving(proc: subprocess.Popen, url: str, what: str = "agent") -> None:
    """Wait until `proc` (the agent, or `what` it is) answers at `url`, 30 s at most; kill it and
    fail with its log if it ends or does not answer by then."""
    deadline = time.monotonic() + 30 * TIME_SCALE
    while True:
        try:
            urllib.request.urlopen(url, timeout=5).read()
            return
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"{what} did not serve: {proc.stdout.read()}")
            time.sleep(0.1)


def scrape(url: str) -> str:
    return urllib.request.urlopen(url, timeout=10).read().decode()


def samples(text: str, name: str) -> dict[tuple, float]:
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == name:
                out[tuple(sorted(s.labels.items()))] = s.value
    return out


def series_begun(url: str, name: str, pid: int) -> float:
    """Wait until the process has a series of `name` and return its value. A series counts from
    where it began (what the process counted before is in `other`): a test that counts a process's
    work exactly has the agent see it first, idle."""
    from tests.conftest import eventually

    def begun() -> float:
        found = [v for labels, v in samples(scrape(url), name).items() if dict(labels).get("pid") == str(pid)]
        assert found, f"no series of {name} for pid {pid} yet"
        return sum(found)
    return eventually(begun, timeout=10)


def counters(text: str) -> dict[str, float]:
    """Every sample of a counter (and of a histogram's buckets, count and sum) in a scrape, by its
    name and labels as written."""
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            series, _, value = line.rpartition(" ")
            name = series.split("{", 1)[0]
            if name.endswith(("_total", "_bucket", "_count", "_sum")):
                out[series] = float(value)
    return out


def assert_monotonic(scrapes: list[str]) -> None:
    """No counter of a series went backwards from one scrape to the next (a series that left and
    came back may start again: that is a new entity's)."""
    last: dict[str, float] = {}
    for text in scrapes:
        now = counters(text)
        back = {s: (last[s], v) for s, v in now.items() if s in last and v < last[s]}
        assert not back, f"counters went backwards: {dict(list(back.items())[:5])}"
        last = now
