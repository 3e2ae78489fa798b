"""`drums detect`'s own cost and its detection quality: CPU and memory watching 1,000 and 10,000
series at 1 s (the agent's page parsed and judged, as the detector does each tick) beside the same
checks run series by series in a Python loop (Skyline's way), and precision, recall and delay on
labelled synthetic series beside plain detectors counted alike (bench/baselines.py). Needs
neither root nor BPF.

The Numenta Anomaly Benchmark's labelled data ships in no package here, so the labelled series are
made by this script: noise with a step, a ramp, a spike or a change of variance at a random point.

    .venv/bin/python bench/detect.py [--ticks 60] [--series-quality 400]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from baselines import DETECTORS, GAUSSIAN_AT_SIGMAS, episodes
from common import PYTHON, fmt, main_wrapper, median, print_table, progress, ratio

SIZES = (1000, 10000)
GOALS = {1000: (2.0, None), 10000: (10.0, 50.0)}  # % of a core, MB of USS
WARM = 260  # ticks before measuring: every history full
KINDS = ("step", "ramp", "spike", "variance")
POINTS = 600  # per labelled series
DETECTED_WITHIN = 30  # points after the anomaly's start that count as detecting it


def exposition(n: int, t: int) -> str:
    """An agent's page of `n` watched series at tick t: per-process counters and gauges with noise."""
    rng = np.random.default_rng(t)
    lines = ["# TYPE drums_process_cpu_seconds_total counter", "# TYPE drums_process_socket_sent_bytes_total counter"]
    per = 4
    noise = rng.normal(1.0, 0.05, n)
    for i in range(n // per):
        pid = 1000 + i
        labels = f'pid="{pid}",process="node_{pid}"'
        lines.append(f"drums_process_cpu_seconds_total{{{labels}}} {t * 0.2 + noise[per * i] * 0.002:.6f}")
        lines.append(f'drums_process_socket_sent_bytes_total{{{labels},protocol="udp"}} {t * 1e5 * (1 + i % 7):.0f}')
        lines.append(f"drums_process_resident_memory_bytes{{{labels}}} {50e6 * noise[per * i + 2]:.0f}")
        lines.append(f"drums_process_open_fds{{{labels}}} {20 + int(noise[per * i + 3] * 3)}")
    return "\n".join(lines) + "\n"


def cost_child(n: int, ticks: int, loop: bool) -> None:
    """In its own process: warm a detector on n series, then time `ticks` ticks (or, with `loop`,
    the same checks row by row); print CPU seconds per tick and USS."""
    import psutil

    from drums.detect import checks
    from drums.detect.detector import Detector
    from drums.detect.sources import parse_exposition
    from drums.selfcost import Heap

    d = Detector()
    heap = Heap()
    heap.trim_every = 0.0
    for t in range(WARM):
        d.tick([parse_exposition("bench", 1e9 + t, exposition(n, t))], now=1e9 + t)
    texts = [exposition(n, t) for t in range(WARM, WARM + ticks)]
    began = time.process_time()
    for k, text in enumerate(texts):
        t = WARM + k
        if loop:
            d.history.tick(*d._ingest([parse_exposition("bench", 1e9 + t, text)]))
            for rows, window in d.history.cohorts(checks.MIN_POINTS):
                state = d._state[rows]
                for i in range(len(rows)):
                    checks.judge(window[i:i + 1], state["floor"][i:i + 1], state["relative"][i:i + 1])
        else:
            d.tick([parse_exposition("bench", 1e9 + t, text)], now=1e9 + t)
    spent = (time.process_time() - began) / ticks
    del texts  # the pages made in advance are this script's, not the detector's
    heap.trim()  # as `drums detect` does at most every 10 s
    print(json.dumps({"cpu_per_tick": spent, "uss": psutil.Process().memory_full_info().uss,
                      "watched": d.watched}))


def cost(n: int, ticks: int, loop: bool) -> dict:
    out = subprocess.run([PYTHON, __file__, "--child", str(n), "--ticks", str(ticks), *(["--loop"] if loop else [])],
                         capture_output=True, text=True, check=True, timeout=1800)
    return json.loads(out.stdout.strip().splitlines()[-1])


def labelled(count: int, seed: int = 11):
    """(series, kind, start) of `count` labelled series: a fifth without an anomaly (start -1)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        kind = "none" if i % 5 == 4 else KINDS[i % 5]
        sd = rng.uniform(1, 10)
        x = rng.normal(0.0, sd, POINTS)
        start = -1 if kind == "none" else int(rng.integers(320, POINTS - 60))
        size = rng.uniform(5, 10) * sd
        if kind == "step":
            x[start:] += size
        elif kind == "ramp":
            x[start:] += size * np.arange(POINTS - start) / 30  # the step's size within 30 points
        elif kind == "spike":
            x[start] += 3 * size
        elif kind == "variance":
            x[start:] *= 5
        out.append((x, kind, start))
    return out


def score(detections: list, data) -> dict:
    """Per kind: recall (a detection within DETECTED_WITHIN points of the start) and median delay;
    over all: precision of detections. One before the anomaly, or on a series without one, is
    false; one after the first DETECTED_WITHIN points, while the judged window still holds the
    change, is the anomaly's own and counted neither way."""
    from collections import defaultdict
    found, delays, true, false = defaultdict(int), defaultdict(list), 0, 0
    for (_, kind, start), flags in zip(data, detections):
        at = np.flatnonzero(flags).tolist()
        hit = [t for t in at if start >= 0 and start <= t < start + DETECTED_WITHIN]
        true += len(hit)
        false += sum(1 for t in at if start < 0 or t < start)
        if hit:
            found[kind] += 1
            delays[kind].append(hit[0] - start)
    total = {k: sum(1 for _, kind, _ in data if kind == k) for k in KINDS}
    return {"recall": {k: found[k] / total[k] for k in KINDS}, "delay": {k: median(delays[k]) for k in KINDS},
            "precision": true / max(1, true + false), "false": false}


def run(args) -> None:
    rows = []
    for n in SIZES:
        progress(f"{n} series: vectorised")
        vec = cost(n, args.ticks, loop=False)
        progress(f"{n} series: one series at a time")
        per = cost(n, max(3, args.ticks // 10), loop=True)
        goal_cpu, goal_mb = GOALS[n]
        ours_cpu, loop_cpu = 100 * vec["cpu_per_tick"], 100 * per["cpu_per_tick"]
        rows.append([f"{vec['watched']:,} series: CPU, % of one core at 1 s (goal <= {goal_cpu:g})",
                     fmt(ours_cpu, 2), fmt(loop_cpu, 1), ratio(ours_cpu, loop_cpu)])
        rows.append([f"{vec['watched']:,} series: USS MB" + (f" (goal <= {goal_mb:g})" if goal_mb else ""),
                     fmt(vec["uss"] / 1e6, 1), fmt(per["uss"] / 1e6, 1), ratio(vec["uss"], per["uss"])])
    print_table("Detector cost: the agent's page parsed and every series judged, each 1 s tick",
                ["measure", "drums detect", "same checks, a series at a time", "ratio"], rows,
                [f"series: per-process CPU and bytes counters (watched as rates) and memory and file gauges; "
                 f"{WARM} ticks to fill every history ({checks_width()} points), then {args.ticks} ticks timed "
                 f"({max(3, args.ticks // 10)} for the loop); CPU is process time per tick, parsing included",
                 "USS of the whole detector process (Python, numpy and the history array) after the timed ticks and a "
                 "malloc_trim, which `drums detect` makes every 10 s"])

    progress(f"quality over {args.series_quality} labelled series")
    data = labelled(args.series_quality)
    names, results = [], []
    for name, detect in DETECTORS:
        if name.startswith("windowed"):  # a score: flagged where it passes 3 sd, as the others
            detect = lambda v, f=detect: episodes(f(v) >= GAUSSIAN_AT_SIGMAS)  # noqa: E731
        names.append(name)
        results.append(score([detect(x) for x, _, _ in data], data))
    quality = [["precision: detections that found an anomaly / all but an anomaly's after-effects",
                *(fmt(r["precision"], 2) for r in results)],
               ["false detections", *(str(r["false"]) for r in results)]]
    for kind in KINDS:
        quality.append([f"recall, {kind}", *(fmt(r["recall"][kind], 2) for r in results)])
        quality.append([f"median delay, {kind} (points)", *(fmt(r["delay"][kind], 0) for r in results)])
    print_table("Detection quality on labelled synthetic series", ["measure", *names], quality,
                [f"{args.series_quality} series of {POINTS} points, Gaussian noise (sd 1-10 around 0); a fifth have "
                 "no anomaly, the rest one from point 320-540: a step of 5-10 sd, a ramp reaching that within 30 "
                 "points, a single spike of 15-30 sd, or the deviation times 5",
                 "each series fed point by point, as one gauge to drums detect (its floors for a unitless gauge: a "
                 "change of 2, or of a tenth of the baseline, which the noise's mean of 0 leaves at 2); the others "
                 "judge the mean of the newest 3 points against the 240 before them, NAB's windowed Gaussian each "
                 "point against all before it, flagged at 3 sd; all are counted alike (bench/baselines.py): a "
                 "detection is the start of an episode, which goes on while flagged again within 30 points"])


def checks_width() -> int:
    from drums.detect.detector import WIDTH
    return WIDTH


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ticks", type=int, default=60, help="ticks timed per size (default 60)")
    parser.add_argument("--series-quality", type=int, default=400, help="labelled series (default 400)")
    parser.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--loop", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        cost_child(args.child, args.ticks, args.loop)
        return
    main_wrapper(lambda: run(args))


if __name__ == "__main__":
    main()
