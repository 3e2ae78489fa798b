"""`drums detect` on the Numenta Anomaly Benchmark (NAB v1.1: 58 real and artificial series with
labelled anomaly windows), scored by NAB's rules in its three profiles, beside NAB's published
scoreboard and baselines run here on the same terms.

Each series is fed point by point, one tick a point, through the detector as `drums detect` runs it
(drums.detect.detector.Detector with its defaults: its checks, floors, hold and grace), as one gauge;
a detection is the start of an anomaly. The baselines (bench/baselines.py) judge the same
newest-3-point mean against the same 240 points before it and are counted alike (a detection where
an episode starts, which goes on while flagged again within 30 points): 3-sigma, a robust z-score
(median and MAD) and an EWMA band; and NAB's windowed Gaussian as NAB runs it (its anomaly score
thresholded where it scores best, as NAB's optimizer does). The
scoring (bench/nabscore.py) is checked against NAB's own: the detections of published detectors
that NAB's checkout keeps (results/) score here what NAB published. NAB comes from a checkout given
by path (`make bench NAB=PATH`; nothing is downloaded).

    .venv/bin/python bench/nab.py --nab PATH
"""
from __future__ import annotations

import argparse
import os

import numpy as np

from common import BenchError, fmt, main_wrapper, print_table, progress
from baselines import DETECTORS
from nabscore import PROFILES, load, score

# NAB's scoreboard (its README, NAB v1.0 and later): standard, reward low FP, reward low FN.
# (name, its folder under NAB's results/, its scores)
PUBLISHED = (
    ("ARTime", "ARTime", (74.9, 65.1, 80.4)),
    ("Numenta HTM", "numenta", (70.1, 63.1, 74.3)),  # NAB's results/final_results.json
    ("earthgecko Skyline", "earthgeckoSkyline", (58.2, 46.2, 63.9)),
    ("Windowed Gaussian", "windowedGaussian", (39.6, 20.9, 47.4)),
    ("Etsy Skyline (the paper's detector)", "skyline", (35.7, 27.1, 44.5)),
    ("Random", "", (11.0, 1.2, 19.5)),
)

def stored(nab: str, files, detector: str) -> list[np.ndarray] | None:
    """A published detector's anomaly scores as NAB's checkout keeps them (results/), if it does."""
    import csv
    scores = []
    for f in files:
        folder, name = os.path.split(f.name)
        path = os.path.join(nab, "results", detector, folder, f"{detector}_{name}")
        if not os.path.exists(path):
            return None
        with open(path, newline="") as fh:
            scores.append(np.array([float(r["anomaly_score"]) for r in csv.DictReader(fh)]))
    return scores


def run(args) -> None:
    if not args.nab or not os.path.isfile(os.path.join(args.nab, "labels", "combined_windows.json")):
        raise BenchError(f"no NAB checkout at {args.nab or '(none given)'}: give one with --nab PATH "
                         "(make bench NAB=PATH), a clone of github.com/numenta/NAB with its data/ and labels/")
    files = load(args.nab)
    points = sum(len(f.values) for f in files)
    rows = []
    for name, detect in DETECTORS:
        progress(f"{name}: {len(files)} files, {points:,} points")
        scores = [detect(f.values) for f in files]
        results = [score(files, scores, p) for p in PROFILES]
        continuous = name.startswith("windowed")
        detections = "-" if continuous else f"{sum(int((s > 0).sum()) for s in scores):,}"
        rows.append([name + (f" (threshold {results[0][1]:.4g})" if continuous else ""),
                     *(fmt(r[0], 1) for r in results), detections])
    for name, _, published in PUBLISHED:
        rows.append([f"{name} (NAB's scoreboard)", *(fmt(v, 1) for v in published), "-"])
    print_table("Anomaly detection on the Numenta Anomaly Benchmark (NAB v1.1), NAB's scoring",
                ["detector", "standard", "reward low FP", "reward low FN", "detections"], rows,
                [f"{len(files)} files, {points:,} points, {sum(len(f.windows) for f in files)} labelled windows; "
                 "scores normalized as NAB does: no detection 0, every window found at its start 100",
                 "each series fed one point a tick; a detection is the start of an episode (one that goes on while "
                 "flagged again within 30 points), scored at the point it starts; NAB's first 15% of each file (at most 750 points) is not scored",
                 "NAB's windowed Gaussian run here differs from its published figure where its scores round to 1.0 "
                 "differently (they agree to 5e-13; its best threshold is exactly 1.0)"])
    check = []
    for name, detector, published in PUBLISHED:
        scores = stored(args.nab, files, detector) if detector else None
        if scores is not None:
            here = [score(files, scores, p)[0] for p in PROFILES]
            check.append([name, *(f"{fmt(h, 2)} ({fmt(p, 1)})" for h, p in zip(here, published))])
    if check:
        print_table("This scoring checked: NAB's stored detections of published detectors, scored here (published)",
                    ["detector", "standard", "reward low FP", "reward low FN"], check,
                    ["each detector's anomaly scores as NAB's checkout keeps them (results/), thresholded where "
                     "they score best, as NAB's optimizer does"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nab", default=os.environ.get("NAB", ""), help="a checkout of numenta/NAB")
    run(ap.parse_args())


if __name__ == "__main__":
    main_wrapper(main)
