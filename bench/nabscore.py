"""The Numenta Anomaly Benchmark's corpus and its scoring rules (NAB v1.1), written here from its
documentation and scorer: a detector's anomaly scores over each data file, weighted by where each
detection falls relative to the labelled anomaly windows, summed over the corpus at the threshold
that scores best, and normalized so that no detection is 0 and every window found at its start 100.

- A detection inside a window is worth more the earlier it comes (a scaled sigmoid of its position
  from -1 at the window's start to 0 past its end); only a window's best detection counts, and a
  window with none costs the profile's false-negative weight.
- A detection outside every window costs the profile's false-positive weight, less right after a
  window (the sigmoid of its distance past the window's end, in window widths) and fully where no
  window came before.
- The first 15% of each file (at most 750 rows) is the detector's probation: not scored.
"""
from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass

import numpy as np

PROFILES = {  # (true-positive, false-positive, false-negative) weights
    "standard": (1.0, 0.11, 1.0),
    "reward_low_FP_rate": (1.0, 0.22, 1.0),
    "reward_low_FN_rate": (1.0, 0.11, 2.0),
}
PROBATION, PROBATION_CAP = 0.15, 750


@dataclass
class DataFile:
    name: str  # as NAB's labels name it: realKnownCause/nyc_taxi.csv
    values: np.ndarray
    windows: list[tuple[int, int]]  # first and last row of each labelled window


def load(nab: str) -> list[DataFile]:
    """The corpus of a NAB checkout: every file its combined windows label, in their order."""
    with open(os.path.join(nab, "labels", "combined_windows.json")) as f:
        labels = json.load(f)
    files = []
    for name, windows in labels.items():
        with open(os.path.join(nab, "data", name), newline="") as f:
            rows = list(csv.DictReader(f))
        row_of = {r["timestamp"]: i for i, r in enumerate(rows)}
        # The labels write their limits with microseconds: "2014-04-10 07:15:00.000000".
        limits = [(row_of[start.split(".")[0]], row_of[end.split(".")[0]]) for start, end in windows]
        files.append(DataFile(name, np.array([float(r["value"]) for r in rows]), limits))
    return files


def _scaled_sigmoid(position: float) -> float:
    return -1.0 if position > 3.0 else 2.0 / (1.0 + math.exp(5.0 * position)) - 1.0


def _weights(f: DataFile, tp: float, fp: float) -> tuple[np.ndarray, np.ndarray]:
    """Each row's worth if detected, and its window's number (-1: outside every window; -2: probation)."""
    n = len(f.values)
    worth, window = np.empty(n), np.full(n, -1)
    best = _scaled_sigmoid(-1.0)
    inside = {}
    for k, (first, last) in enumerate(f.windows):
        for i in range(first, last + 1):
            inside[i] = k
    previous = None  # (last row, width) of the window before
    for i in range(n):
        k = inside.get(i)
        if k is not None:
            first, last = f.windows[k]
            width = last - first + 1
            worth[i] = _scaled_sigmoid(-(last - i + 1) / width) * tp / best
            window[i] = k
            if i == last:
                previous = (last, width)
        elif previous is None:
            worth[i] = -fp
        else:
            worth[i] = _scaled_sigmoid(abs(previous[0] - i) / (previous[1] - 1)) * fp
    window[:min(math.floor(PROBATION * n), PROBATION_CAP)] = -2
    return worth, window


def score(files: list[DataFile], scores: list[np.ndarray], profile: str) -> tuple[float, float]:
    """(normalized score, threshold) of a detector's scores (one array per file, each row's anomaly
    score) under a profile, at the threshold that scores best over the corpus, as NAB's optimizer
    finds it: a row is a detection where its score is at least the threshold."""
    tp, fp, fn = PROFILES[profile]
    worth, window, value = [], [], []
    offset = 0
    for f, s in zip(files, scores):
        w, k = _weights(f, tp, fp)
        keep = k != -2
        worth.append(w[keep])
        window.append(np.where(k[keep] >= 0, k[keep] + offset, -1))
        value.append(np.asarray(s, float)[keep])
        offset += len(f.windows)
    worth, window, value = np.concatenate(worth), np.concatenate(window), np.concatenate(value)
    windows = {int(k): -fn for k in np.unique(window[window >= 0])}  # those with rows past probation
    null = sum(windows.values())
    perfect = tp * sum(len(f.windows) for f in files)
    order = np.argsort(-value, kind="stable")
    total, best, best_threshold = null, null, math.inf
    found = dict(windows)
    i = 0
    while i < len(order):
        level = value[order[i]]
        while i < len(order) and value[order[i]] == level:  # every row at this score joins at once
            row = order[i]
            k = int(window[row])
            if k < 0:
                total += worth[row]
            elif worth[row] > found[k]:
                total += worth[row] - found[k]
                found[k] = worth[row]
            i += 1
        if total > best:
            best, best_threshold = total, level
    return 100.0 * (best - null) / (perfect - null), best_threshold
