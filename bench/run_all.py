"""Runs every benchmark one after the other and prints all their tables (`make bench`).

Each benchmark runs in its own process, with its default (modest) durations unless --quick;
a benchmark that cannot run is reported and the others still run; the exit code is 1 if any
could not run. Meeting or missing a goal does not change the exit code: these are measurements.

The tables of every benchmark that ran whole (not --quick) go into bench/results.json with the
commit measured and the machine, replacing that benchmark's earlier ones; the README's "Measured"
section is made from that file (bench/readme.py), and a test fails when the two disagree.

    .venv/bin/python bench/run_all.py [--quick] [--only render --only startup ...]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results.json")
# In order of running: the cheap ones first. Each: (name, quick arguments).
BENCHMARKS = (
    ("render", ["--repeats", "5"]),
    ("startup", ["--runs", "1"]),
    ("event_cost", ["--rounds", "3", "--ops", "20000", "--pingpongs", "10000"]),
    ("workload_overhead", ["--rounds", "1", "--seconds", "2"]),
    ("agent_cost", ["--seconds", "5"]),
    ("topic_latency", ["--rounds", "1", "--seconds", "2"]),
    ("stream_bandwidth", ["--seconds", "3"]),
    ("foxglove_cost", ["--seconds", "5"]),
    ("http_robustness", ["--seconds", "5"]),
    ("detect", ["--ticks", "5", "--series-quality", "50"]),
    ("nab", []),  # NAB from $NAB (make bench NAB=PATH)
)
TIMEOUT = 600  # seconds; the longest benchmarks (agent_cost, workload_overhead) take about 6 minutes
# What a whole run adds to a benchmark's arguments, and the longer time it may take then.
FULL = {"event_cost": (["--kernel", "6.1"], 3600)}  # then in a VM of 6.1, under emulation here


def run_one(name: str, extra: list[str], tables: str, timeout: float = TIMEOUT) -> tuple[int, float]:
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, os.path.join(HERE, f"{name}.py"), *extra],
                            env={**os.environ, "DRUMS_BENCH_TABLES": tables})
    try:
        code = proc.wait(timeout)
    except subprocess.TimeoutExpired:
        print(f"bench: {name} ran over {timeout:.0f} s; stopping it", file=sys.stderr)
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


def machine() -> dict:
    with open("/proc/meminfo") as f:
        memory = int(f.readline().split()[1]) * 1024
    return {"cores": os.cpu_count(), "kernel": platform.release(), "memory_gib": round(memory / 2**30),
            "system": _os_release()}


def _os_release() -> str:
    try:
        with open("/etc/os-release") as f:
            fields = dict(line.rstrip("\n").split("=", 1) for line in f if "=" in line)
        return fields.get("PRETTY_NAME", "").strip('"')
    except OSError:
        return ""


def commit() -> str:
    """The commit measured, with "+changes" when the work tree differs from it."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=HERE, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short=12", "HEAD")
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", "drums", "bpf", "bench")
    return head + ("+changes" if dirty else "")


def record(name: str, tables: list[dict]) -> None:
    """The benchmark's tables into bench/results.json, in place of its earlier ones."""
    try:
        with open(RESULTS) as f:
            results = json.load(f)
    except FileNotFoundError:
        results = {}
    results[name] = {"commit": commit(), "date": time.strftime("%Y-%m-%d"), "machine": machine(),
                     "tables": tables}
    order = [n for n, _ in BENCHMARKS]
    with open(RESULTS, "w") as f:
        json.dump(dict(sorted(results.items(), key=lambda kv: order.index(kv[0]))), f, indent=1)
        f.write("\n")


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
        with tempfile.NamedTemporaryFile("r", suffix=".jsonl") as tables:
            extra, timeout = ([], TIMEOUT) if args.quick else FULL.get(name, ([], TIMEOUT))
            code, seconds = run_one(name, quick if args.quick else extra, tables.name, timeout)
            measured = [json.loads(line) for line in tables]
        timings.append(f"{name} {seconds:.0f} s")
        if code != 0:
            failed.append(name)
            print(f"\n(bench/{name}.py could not run: exit {code}; its error is above)", flush=True)
        elif not args.quick:
            record(name, measured)
    print(f"\nran: {', '.join(timings)}" + (f"; could not run: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
