"""`drums detect`'s own cost and its detection quality: CPU and memory watching 1,000 and 10,000
series at 1 s (the agent's page parsed and judged, as the detector does each tick) beside the same
checks run series by series in a Python loop (Skyline's way), and precision, recall and delay on
labelled synthetic series beside a plain 3-sigma threshold. Needs neither root nor BPF.

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

from common import PYTHON, fmt, main_wrapper, median, print_table, progress, ratio

SIZES = (1000, 10000)
GOALS = {1000: (2.0, None), 10000: (10.0, 50.0)}  # % of a core, MB of USS
WARM = 260  # ticks before measuring: every history full
KINDS = ("step", "ramp", "spike", "variance")
POINTS = 600  # per labelled series
DETECTED_WITHIN = 30  # points after the anomaly's start that count as detecting it


def exposition(n: int, t: int) -> str:
    """An agent's page of `n` watched series at tick t: per-process counters and gauges with noise."""
    import numpy as np
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
    import numpy as np
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        kind = "none" if i % 5 == 4 else KINDS[i % 5]
        sd = rng.uniform(1, 10)
        x = rng.normal(100.0, sd, POINTS)
        start = -1 if kind == "none" else int(rng.integers(320, POINTS - 60))
        size = rng.uniform(5, 10) * sd
        if kind == "step":
            x[start:] += size
        elif kind == "ramp":
            x[start:] += size * np.arange(POINTS - start) / 30  # the step's size within 30 points
        elif kind == "spike":
            x[start] += 3 * size
        elif kind == "variance":
            x[start:] = 100.0 + (x[start:] - 100.0) * 5
        out.append((x, kind, start))
    return out


def score(flags_of, data) -> dict:
    """Per kind: recall (flagged within DETECTED_WITHIN points of the start) and median delay; over
    all: precision of flag episodes (runs of flagged points). An episode that starts before the
    anomaly, or on a series without one, is false; one that starts after it, while the judged
    window still holds the change, is the anomaly's own and not counted either way."""
    from collections import defaultdict
    found, delays, true_flags, false_flags = defaultdict(int), defaultdict(list), 0, 0
    for (_, kind, start), flags in zip(data, flags_of(data)):
        hit = [t for t in flags if start >= 0 and start <= t < start + DETECTED_WITHIN]
        true_flags += bool(hit)
        episodes = [t for t in flags if t - 1 not in flags]
        false_flags += sum(1 for t in episodes if start < 0 or t < start)
        if hit:
            found[kind] += 1
            delays[kind].append(hit[0] - start)
    total = {k: sum(1 for _, kind, _ in data if kind == k) for k in KINDS}
    return {"recall": {k: found[k] / total[k] for k in KINDS}, "delay": {k: median(delays[k]) for k in KINDS},
            "precision": true_flags / max(1, true_flags + false_flags), "false": false_flags}


def ours(data) -> list[set[int]]:
    """The detector's checks over each series as it would see them point by point (floors at zero:
    synthetic series have no unit)."""
    import numpy as np

    from drums.detect import checks
    from drums.detect.detector import WIDTH
    window = np.stack([x for x, _, _ in data]).astype(np.float32)
    flags = [set() for _ in data]
    zero = np.zeros(len(data))
    for t in range(checks.MIN_POINTS, POINTS):
        verdict = checks.judge(window[:, max(0, t + 1 - WIDTH):t + 1], zero, zero)
        for i in verdict.anomalous.tolist():
            flags[i].add(t)
    return flags


def three_sigma(data) -> list[set[int]]:
    """A plain threshold: the newest point farther than 3 standard deviations from the mean of the
    points before it, over the same window."""
    import numpy as np

    from drums.detect import checks
    from drums.detect.detector import WIDTH
    window = np.stack([x for x, _, _ in data])
    flags = [set() for _ in data]
    for t in range(checks.MIN_POINTS, POINTS):
        history = window[:, max(0, t + 1 - WIDTH):t]
        out = np.abs(window[:, t] - history.mean(axis=1)) > 3 * history.std(axis=1)
        for i in np.flatnonzero(out).tolist():
            flags[i].add(t)
    return flags


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
    a, b = score(ours, data), score(three_sigma, data)
    quality = [["precision: flag episodes that found an anomaly / all but an anomaly's after-effects", fmt(a["precision"], 2),
                fmt(b["precision"], 2), ratio(a["precision"], b["precision"])],
               ["false flag episodes", str(a["false"]), str(b["false"]), ratio(a["false"], b["false"])]]
    for kind in KINDS:
        quality.append([f"recall, {kind}", fmt(a["recall"][kind], 2), fmt(b["recall"][kind], 2),
                        ratio(a["recall"][kind], b["recall"][kind])])
        quality.append([f"median delay, {kind} (points)", fmt(a["delay"][kind], 0), fmt(b["delay"][kind], 0), ""])
    print_table("Detection quality on labelled synthetic series", ["measure", "drums detect (5 checks, 3 agree)",
                "3-sigma threshold", "ratio"], quality,
                [f"{args.series_quality} series of {POINTS} points, Gaussian noise (sd 1-10 around 100); a fifth have "
                 "no anomaly, the rest one from point 320-540: a step of 5-10 sd, a ramp reaching that within 30 "
                 "points, a single spike of 15-30 sd, or the deviation times 5",
                 "both judge each point against the 240 before it; drums detect's floors are set to 0 here "
                 "(synthetic series have no unit), its warm-up is 30 points"])


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
