"""Rates and percentiles from two reads of the same counters, as Prometheus's rate() and
histogram_quantile() compute them: a counter that went back started again (its process did)."""
from __future__ import annotations

import math


def rate(now: float | None, before: float | None, seconds: float) -> float | None:
    """Per second between two reads; None until both are known."""
    if now is None or before is None or seconds <= 0:
        return None
    delta = now - before
    return (now if delta < 0 else delta) / seconds


def total(rates) -> float | None:
    """The sum of the rates that are known; None if none is."""
    known = [r for r in rates if r is not None]
    return sum(known) if known else None


def quantile(q: float, now: dict[float, float], before: dict[float, float] | None) -> float | None:
    """The q-quantile of what a histogram (upper bound -> cumulative count, +Inf included) counted
    between two reads, interpolated within its bucket; in the +Inf bucket, the highest finite
    bound (as histogram_quantile says it). None if nothing was counted."""
    if before is None or not now:
        return None
    bounds = sorted(now)
    counts = [now[b] - before.get(b, 0) for b in bounds]
    if any(c < 0 for c in counts):  # the histogram began again
        counts = [now[b] for b in bounds]
    if counts[-1] <= 0:
        return None
    rank = q * counts[-1]
    for i, (bound, count) in enumerate(zip(bounds, counts)):
        if count >= rank:
            if math.isinf(bound):
                return bounds[-2] if len(bounds) > 1 else None
            lower, below = (bounds[i - 1], counts[i - 1]) if i else (0.0, 0.0)
            return bound if count == below else lower + (bound - lower) * (rank - below) / (count - below)
    return None
