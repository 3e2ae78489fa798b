"""`drums detect` and the plain detectors it is judged beside, each fed one series point by point
and counted alike: a detection is the start of an episode, and an episode goes on while its
detector flags the series again within HOLD points (the detector's own rule for an anomaly). The
baselines judge what the detector judges, the mean of the newest 3 points against the 240 before
them, and like it judge nothing before the 30th point. bench/nab.py and bench/detect.py use them.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

SMOOTH = 3  # the detector judges the mean of the newest points (drums.detect.checks.TAIL)
WINDOW = 240  # against the points before them (drums.detect.detector.WIDTH)
WARM = 30  # nothing is judged before this many points (drums.detect.checks.MIN_POINTS)
HOLD = 30  # points an episode lasts after it was last flagged (drums.detect.detector.HOLD at 1 s a point)
SIGMAS = 3.0
T0 = 1.7e9


def episodes(flags: np.ndarray) -> np.ndarray:
    """1 where an episode of flagged points starts: a flagged point with none in the HOLD before it."""
    out = np.zeros(len(flags))
    last = -HOLD - 1
    for i in np.flatnonzero(flags).tolist():
        if i - last > HOLD:
            out[i] = 1.0
        last = i
    return out


def drums_detect(values: np.ndarray) -> np.ndarray:
    """1 where `drums detect`'s Detector, with its defaults, starts an anomaly of the series, fed to
    it a point a tick as a gauge of no unit it knows (whose floors: a change of 2, or of a tenth)."""
    from drums.detect.detector import Detector
    from drums.detect.sources import Reading
    d = Detector()
    out = np.zeros(len(values))
    for i, v in enumerate(values.tolist()):
        for event in d.tick([Reading("bench", T0 + i, {"value": v})], now=T0 + i):
            if event.kind == "anomaly":
                out[i] = 1.0
    return out


def _smooth(values: np.ndarray) -> np.ndarray:
    """The mean of the newest SMOOTH points at every point."""
    return np.convolve(values, np.ones(SMOOTH) / SMOOTH, "full")[:len(values)]


def _judged(values: np.ndarray):
    """(newest-3 mean, the WINDOW points before them) for every point."""
    from numpy.lib.stride_tricks import sliding_window_view
    before = np.concatenate([np.full(WINDOW + SMOOTH - 1, np.nan), values])
    return _smooth(values), sliding_window_view(before, WINDOW)[:len(values)]


def _warm(flags: np.ndarray) -> np.ndarray:
    flags[:WARM] = False
    return flags


def three_sigma(values: np.ndarray) -> np.ndarray:
    smooth, before = _judged(values)
    with warnings.catch_warnings():  # the first points' windows are all NaN: judged as nothing
        warnings.simplefilter("ignore", RuntimeWarning)
        return _warm(np.abs(smooth - np.nanmean(before, axis=1)) > SIGMAS * np.nanstd(before, axis=1))


def robust_z(values: np.ndarray, z: float = 3.5) -> np.ndarray:
    """Median and MAD (as a standard deviation), the usual robust z-score cut of 3.5."""
    smooth, before = _judged(values)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(before, axis=1)
        mad = 1.4826 * np.nanmedian(np.abs(before - median[:, None]), axis=1)
        return _warm(np.abs(smooth - median) > z * mad)


def ewma(values: np.ndarray, alpha: float = 2 / (WINDOW + 1)) -> np.ndarray:
    """An exponentially weighted mean and variance (span WINDOW) of the points before; the smoothed
    point outside 3 of its standard deviations."""
    smooth = _smooth(values)
    flags = np.zeros(len(values), bool)
    mean, var = values[0], 0.0
    for i in range(1, len(values)):
        flags[i] = abs(smooth[i] - mean) > SIGMAS * math.sqrt(var)
        delta = values[i] - mean
        mean += alpha * delta
        var = (1 - alpha) * (var + alpha * delta * delta)
    return _warm(flags)


def windowed_gaussian(values: np.ndarray, size: int = 6400, step: int = 100) -> np.ndarray:
    """NAB's windowed Gaussian: each point's anomaly score is how improbable it is under a normal
    distribution fitted to the window of points before it (grown to `size`, then moved on every
    `step` points). A score, not a flag: NAB thresholds it where it scores best."""
    out = np.zeros(len(values))
    mean, sd, count = 0.0, 1.0, 0
    for i, v in enumerate(values.tolist()):
        if count:
            out[i] = 1.0 - 0.5 * math.erfc(abs(v - mean) / sd / math.sqrt(2))
        if i < size:
            count = i + 1
            window = values[:count]
        elif (i - size + 1) % step == 0:
            window = values[i + 1 - size:i + 1]
        else:
            continue
        mean, sd = float(window.mean()), float(window.std()) or 1e-6
    return out


# The windowed Gaussian's score of a point SIGMAS standard deviations out: its flag where no
# optimizer picks a threshold.
GAUSSIAN_AT_SIGMAS = 1.0 - 0.5 * math.erfc(SIGMAS / math.sqrt(2))

# (name, detections of a series: episode starts, or for the windowed Gaussian its scores)
DETECTORS = (
    ("drums detect (defaults)", drums_detect),
    ("3-sigma on the newest-3 mean vs 240 before", lambda v: episodes(three_sigma(v))),
    ("robust z (median, MAD) > 3.5, same", lambda v: episodes(robust_z(v))),
    ("EWMA band, 3 sd, span 240", lambda v: episodes(ewma(v))),
    ("windowed Gaussian (NAB's)", windowed_gaussian),
)
