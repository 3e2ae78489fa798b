"""The statistical checks that judge the newest points of many series at once, in the spirit of
Skyline (the detector the paper that started Drums ran over its series): each check is cheap, none
is trusted alone, and a point is anomalous when most of them agree.

Every function works on a whole array of series (one row each, oldest point first): the cost of a
tick is a few numpy passes, not a Python loop per series. A series is judged on the mean of its
newest TAIL points (one odd sample is diluted, a change that holds is not) against the points
before them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHECKS = ("average", "median", "histogram", "shift", "trend")
CONSENSUS = 3  # checks that must agree
TAIL = 3  # newest points judged together
RECENT = 10  # newest points whose distribution the shift check compares with the older ones
MIN_POINTS = 30  # a series is judged once it has this many (its warm-up)
SIGMAS = 3.0  # average: how far from the mean, in standard deviations
MADS = 6.0  # median: how far from the median, in median absolute deviations
BINS = 15  # histogram: bins over the series' range
RARE = 0.01  # histogram: a bin holding at most this share of the history (and at least 1 point) is rare
SHIFT_P = 0.01  # shift: two-sample Kolmogorov-Smirnov p-value under which the recent points differ
TREND_SIGMAS = 4.0  # trend: the fitted change over the window against the residuals' deviation
GROWTH_POINTS = 16  # growth: the newest points of a memory series judged for a leak, from its 16th
RISES = 3  # growth: rises of an eighth of the floor or more it must take (the agent reads a process's memory every 5 s)


@dataclass
class Verdict:
    """The judgement of rows `rows` (indices into the judged array): which checks each failed,
    its tail value, the history's median (the baseline) and how unusual it is (severity: the
    effect over the larger of the floor and the history's spread)."""

    rows: np.ndarray  # indices of the rows whose effect cleared the floor; only they were checked
    failed: np.ndarray  # bool (len(rows), len(CHECKS))
    value: np.ndarray
    baseline: np.ndarray
    severity: np.ndarray

    @property
    def anomalous(self) -> np.ndarray:
        """Indices (into the judged array) of the rows at least CONSENSUS checks call anomalous."""
        return self.rows[self.failed.sum(axis=1) >= CONSENSUS]


def judge(window: np.ndarray, floor: np.ndarray, relative: np.ndarray) -> Verdict:
    """Judge the newest points of each row of `window` (n, k), k >= MIN_POINTS.

    A change only counts when it is big enough to matter to a user: more than `floor` (absolute,
    in the series' unit) and more than `relative` times the baseline. The checks run on those rows
    only; on a quiet host that is almost none of them.
    """
    history, tail = window[:, :-TAIL], window[:, -TAIL:]
    value = tail.mean(axis=1, dtype=np.float64)
    baseline = _median(history)
    effect = value - baseline
    rows = np.flatnonzero(np.abs(effect) > np.maximum(floor, relative * np.abs(baseline)))
    history, value, baseline, effect = history[rows].astype(np.float64), value[rows], baseline[rows], effect[rows]
    spread = 1.4826 * _median(np.abs(history - baseline[:, None]))  # the MAD, as a standard deviation
    failed = np.column_stack([
        _average(history, value),
        np.abs(effect) > MADS / 1.4826 * spread,  # a zero spread: any change that cleared the floor
        _histogram(history, value),
        _shift(window[rows].astype(np.float64)),
        _trend(window[rows].astype(np.float64), effect),
    ]) if len(rows) else np.zeros((0, len(CHECKS)), bool)
    severity = np.abs(effect) / np.maximum(np.maximum(floor[rows], spread), 1e-12)
    return Verdict(rows, failed, value, baseline, severity)


def _median(a: np.ndarray) -> np.ndarray:
    """Row medians by partition (np.median also checks for NaN and averages two middles: 7x slower);
    for an even count, the upper middle."""
    if a.shape[1] == 0:
        return np.zeros(a.shape[0])
    middle = a.shape[1] // 2
    return np.partition(a, middle, axis=1)[:, middle].astype(np.float64)


def _average(history: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Farther than SIGMAS standard deviations from the history's mean."""
    return np.abs(value - history.mean(axis=1)) > SIGMAS * history.std(axis=1)


def _histogram(history: np.ndarray, value: np.ndarray) -> np.ndarray:
    """In a bin of the history's range (value included) that few of the history's points share."""
    low = np.minimum(history.min(axis=1), value)
    width = (np.maximum(history.max(axis=1), value) - low) / BINS
    width[width == 0] = 1.0  # a constant history: everything in one bin
    bins = np.minimum(((history - low[:, None]) / width[:, None]).astype(np.int64), BINS - 1)
    own = np.minimum(((value - low) / width).astype(np.int64), BINS - 1)
    shared = (bins == own[:, None]).sum(axis=1)
    return shared <= max(1, int(RARE * history.shape[1]))


def _shift(window: np.ndarray) -> np.ndarray:
    """The newest RECENT points come from another distribution than the points before them
    (two-sample Kolmogorov-Smirnov, computed for all rows at once; ties step together)."""
    older, recent = window.shape[1] - RECENT, RECENT
    if older < RECENT:
        return np.zeros(window.shape[0], bool)
    order = np.argsort(window, axis=1, kind="stable")
    ordered = np.take_along_axis(window, order, axis=1)
    steps = np.where(order < older, 1.0 / older, -1.0 / recent)
    cdf_gap = np.cumsum(steps, axis=1)
    # Only where the value changes (or at the end) is the empirical CDF's step complete.
    ends = np.ones_like(ordered, dtype=bool)
    ends[:, :-1] = ordered[:, 1:] != ordered[:, :-1]
    distance = np.where(ends, np.abs(cdf_gap), 0.0).max(axis=1)
    # The asymptotic critical distance for the level SHIFT_P (1.63 / sqrt(n) at 1%).
    return distance > np.sqrt(-np.log(SHIFT_P / 2) / 2 * (older + recent) / (older * recent))


def _trend(window: np.ndarray, effect: np.ndarray) -> np.ndarray:
    """A least-squares line through the window changes, over its length, by more than TREND_SIGMAS
    times the points' deviation from it, in the direction of the effect: slow growth, as of a leak."""
    k = window.shape[1]
    t = np.arange(k, dtype=np.float64) - (k - 1) / 2
    centred = window - window.mean(axis=1, keepdims=True)
    slope = centred @ t / (t @ t)
    residual = centred - slope[:, None] * t
    deviation = np.sqrt((residual ** 2).sum(axis=1) / max(k - 2, 1))
    change = slope * (k - 1)
    return (np.abs(change) > TREND_SIGMAS * deviation) & (np.sign(change) == np.sign(effect))


def growth(window: np.ndarray, floor: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """Rows of `window` (n, GROWTH_POINTS) that grew all along: by more than the floor and `relative`
    times where they began, in RISES or more rises (of an eighth of the floor each), none more than
    half of the growth (an allocation at start, in one or two steps, that then stays is no leak),
    and no fall of a tenth of it. The checks above judge a series against its own history, which
    for a process that leaks from its first second is all growth: this one needs no history, so a
    new process is judged from its GROWTH_POINTS-th point."""
    steps = np.diff(window.astype(np.float64), axis=1)
    grown = steps.sum(axis=1)
    return ((grown > np.maximum(floor, relative * np.abs(window[:, 0])))
            & ((steps > floor[:, None] / 8).sum(axis=1) >= RISES)
            & (steps.max(axis=1) < grown / 2) & (steps.min(axis=1) > -grown / 10))
