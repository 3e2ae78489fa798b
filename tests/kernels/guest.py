"""Runs inside a kernel of the matrix (booted by tests/kernels/run.py over this machine's root): makes
the guest what scripts/setup.sh makes a host (bpffs, tracefs, that kernel's headers for bcc), then
runs `drums doctor` and the portable tests (`drums agent` as the README starts it among them),
writing what it saw to OUT/guest.json and the tests' outcomes to OUT/junit.xml. Or a benchmark
(bench/event_cost.py --kernel), its tables to OUT/tables.jsonl.

    python -m tests.kernels.guest OUT HEADERS TIME_SCALE TEST...
    python -m tests.kernels.guest bench OUT HEADERS SCRIPT ARG...
"""
from __future__ import annotations

import importlib.util
import json
import os
import platform
import subprocess
import sys
import time

CHECKOUT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DRUMS = [sys.executable, "-m", "drums"]


def _mount(fstype: str, target: str) -> None:
    from drums.kernel.features import is_mount_of_type
    if not is_mount_of_type("/proc/mounts", target, fstype):
        subprocess.run(["mount", "-t", fstype, fstype, target], check=False)


def paths_offered() -> dict[str, list[tuple[str, str]]]:
    """Each BPF probe's attach paths, best first, and why this kernel does not offer each (or "")."""
    from drums.kernel.features import Features
    from drums.probes.bpf import BpfProbe
    from drums.probes.registry import build
    from drums.proctable import ProcessTable
    f = Features()
    return {p.name: [(path.name, path.requires(f) or "") for path in p.paths]
            for p in build(f, ProcessTable()) if isinstance(p, BpfProbe)}


def prepare(headers: str) -> None:
    """What scripts/setup.sh makes of a host: bpffs, tracefs, and the kernel's headers for bcc."""
    os.chdir(CHECKOUT)
    _mount("bpf", "/sys/fs/bpf")
    _mount("tracefs", "/sys/kernel/tracing")
    os.environ["BCC_KERNEL_SOURCE"] = headers


def bench(out: str, headers: str, argv: list[str]) -> int:
    prepare(headers)
    with open(os.path.join(out, "bench.out"), "w") as stdout:
        return subprocess.run([sys.executable, *argv], stdout=stdout,
                              env=dict(os.environ, DRUMS_BENCH_TABLES=os.path.join(out, "tables.jsonl"))).returncode


def main(out: str, headers: str, time_scale: str, tests: list[str]) -> int:
    prepare(headers)
    # The guest's root is this machine's, read-only but for /tmp and a few overlays: ROS 2 logs
    # there. Under emulation everything takes about ten times as long.
    os.environ["ROS_LOG_DIR"] = "/tmp/ros-log"
    os.environ["DRUMS_TEST_TIME_SCALE"] = time_scale
    # The portable tests need no pytest plugin; importing those installed (hypothesis, schemathesis,
    # anyio) took 25 of the 70 s that collecting them took under emulation.
    os.environ["PYTEST_DISABLE_PLUGIN_AUTOLOAD"] = "1"
    seen: dict = {"release": platform.release(), "python": platform.python_version(),
                  "ros2": importlib.util.find_spec("rclpy") is not None}
    started = time.monotonic()
    seen["doctor"] = subprocess.run(DRUMS + ["doctor"], capture_output=True, text=True).stdout
    seen["paths"] = paths_offered()
    seen["doctor_s"] = round(time.monotonic() - started, 1)
    started = time.monotonic()
    # A line a test, written as it ends: the host can follow a run that takes half an hour.
    pytest = subprocess.run([sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", "-o", "addopts=",
                             "--durations=15", "-m", "kernel", "--junitxml", os.path.join(out, "junit.xml"), *tests],
                            stdout=open(os.path.join(out, "pytest.log"), "w"), stderr=subprocess.STDOUT,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    seen["pytest_status"] = pytest.returncode
    seen["tests_s"] = round(time.monotonic() - started, 1)
    with open(os.path.join(out, "guest.json"), "w") as f:
        json.dump(seen, f, indent=1)
    return 0


if __name__ == "__main__":
    if sys.argv[1] == "bench":
        sys.exit(bench(sys.argv[2], sys.argv[3], sys.argv[4:]))
    sys.exit(main(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]))
