"""Runs every benchmark one after the other and prints all their tables (`make bench`).

Each benchmark runs in its own process, with its default (modest) durations unless --quick;
a benchmark that cannot run is reported and the others still run; the exit code is 1 if any
could not run. Meeting or missing a goal does not change the exit code: these are measurements.

    .venv/bin/python bench/run_all.py [--quick] [--only render --only startup ...]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
# In order of running: the cheap ones first. Each: (name, quick arguments).
BENCHMARKS = (
    ("render", ["--repeats", "5"]),
    ("startup", ["--runs", "1"]),
    ("event_cost", ["--rounds", "3", "--ops", "20000", "--pingpongs", "10000"]),
    ("workload_overhead", ["--rounds", "1", "--seconds", "2"]),
    ("agent_cost", ["--seconds", "5"]),
    ("topic_latency", ["--rounds", "1", "--seconds", "2"]),
    ("stream_bandwidth", ["--seconds", "3"]),
)
TIMEOUT = 600  # seconds; each benchmark is meant to finish within about 3 minutes


def run_one(name: str, extra: list[str]) -> tuple[int, float]:
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, os.path.join(HERE, f"{name}.py"), *extra])
    try:
        code = proc.wait(TIMEOUT)
    except subprocess.TimeoutExpired:
        print(f"bench: {name} ran over {TIMEOUT} s; stopping it", file=sys.stderr)
        proc.terminate()  # the benchmarks clean up on SIGTERM
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        code = 124
    except KeyboardInterrupt:
        proc.terminate()
        proc.wait(60)
        raise
    return code, time.monotonic() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="short runs of everything (a smoke test)")
    parser.add_argument("--only", action="append", choices=[n for n, _ in BENCHMARKS],
                        help="run only this benchmark (repeatable)")
    args = parser.parse_args()
    print("# Drums benchmarks\n")
    print(f"host: {os.uname().release}, {os.cpu_count()} CPUs; "
          f"{'quick runs (--quick): figures are rough' if args.quick else 'default durations'}")
    sys.stdout.flush()
    failed, timings = [], []
    for name, quick in BENCHMARKS:
        if args.only and name not in args.only:
            continue
        print(f"\n## {name}", flush=True)
        code, seconds = run_one(name, quick if args.quick else [])
        timings.append(f"{name} {seconds:.0f} s")
        if code != 0:
            failed.append(name)
            print(f"\n(bench/{name}.py could not run: exit {code}; its error is above)", flush=True)
    print(f"\nran: {', '.join(timings)}" + (f"; could not run: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
