"""The detector's checks on series whose truth is known: noise, steps, ramps and spikes drawn here,
judged all at once as the detector judges them."""
from __future__ import annotations

import numpy as np
import pytest

from drums.detect import checks

K = 240  # points per series, as the detector holds


def judged(window: np.ndarray, floor: float = 0.0, relative: float = 0.0) -> set[int]:
    n = len(window)
    return set(checks.judge(window.astype(np.float32), np.full(n, floor), np.full(n, relative)).anomalous.tolist())


def noise(n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).normal(100.0, 5.0, (n, K))


def test_noise_alone_is_almost_never_flagged_even_with_no_floor():
    window = noise(2000)
    assert len(judged(window)) <= 20  # 1% of rows at most, where every check sees chance alone


def test_a_step_of_ten_deviations_is_flagged_in_every_row_and_only_there():
    window = noise(200)
    stepped = np.arange(0, 200, 2)
    window[stepped, -checks.RECENT:] += 50.0  # 10 standard deviations, for the last 10 points
    flagged = judged(window)
    assert set(stepped.tolist()) <= flagged
    assert len(flagged - set(stepped.tolist())) <= 2


def test_a_step_under_the_floor_is_not_news():
    window = noise(100)
    window[:, -checks.RECENT:] += 20.0  # +20% of 100 (4 deviations): under a relative floor of 30%
    assert judged(window, relative=0.30) == set()
    assert judged(window, floor=30.0) == set()
    assert len(judged(window, relative=0.10)) >= 50  # the checks still judge what clears the floor


def test_a_constant_series_that_moves_by_more_than_its_floor_is_flagged():
    window = np.full((3, K), 1000.0)
    window[0, -checks.TAIL:] = 1000.0 + 5  # under the floor of 10
    window[1, -checks.TAIL:] = 1000.0 + 11
    window[2, -checks.TAIL:] = 1000.0 - 11
    assert judged(window, floor=10.0) == {1, 2}


def test_a_leak_is_flagged_within_ten_points_of_its_start():
    """Resident memory at 50 MiB (a few KiB of noise) that starts growing by 3 MiB a point."""
    mib = 1024.0 ** 2
    rng = np.random.default_rng(3)
    series = 50 * mib + rng.normal(0, 4096, 400)
    series[300:] += 3 * mib * np.arange(1, 101)
    first = next(t for t in range(checks.MIN_POINTS, 400)
                 if judged(series[None, max(0, t - K):t + 1], floor=4 * mib, relative=0.05))
    assert 300 <= first <= 310


def test_growth_names_a_leak_from_birth_and_no_allocation_that_then_stays():
    """Resident memory of new processes, a point a second: each row GROWTH_POINTS points from where
    its process began, with a page cache's worth of noise."""
    mib, k = 1024.0 ** 2, checks.GROWTH_POINTS
    rng = np.random.default_rng(4)
    t = np.arange(k)
    rows = {
        "leaks 5 MiB/s from birth": 10 * mib + 5 * mib * t,
        "leaks 5 MiB/s from birth, read every 5 s": 10 * mib + 5 * mib * (t // 5 * 5),
        "allocates 200 MiB in its second second, then stays": np.where(t >= 1, 210 * mib, 10 * mib),
        "allocates 200 MiB over its first two reads": 10 * mib + np.minimum(t // 5, 2) * 100 * mib,
        "grows 200 KiB/s (under the floor)": 10 * mib + 0.2 * mib * t,
        "fills a cache and empties it twice": 10 * mib + 5 * mib * t - 30 * mib * ((t >= 6) + (t >= 12)),
        "flat": np.full(k, 50 * mib),
    }
    window = np.array(list(rows.values())) + rng.normal(0, 4096, (len(rows), k))
    flagged = checks.growth(window.astype(np.float32), np.full(len(rows), 4 * mib), np.full(len(rows), 0.05))
    assert [name for name, f in zip(rows, flagged) if f] == ["leaks 5 MiB/s from birth",
                                                             "leaks 5 MiB/s from birth, read every 5 s"]


def test_a_single_spike_is_diluted_but_a_large_one_is_not():
    window = noise(2)
    window[0, -1] += 30.0  # 6 deviations, one point: 2 when averaged over the tail of 3
    window[1, -1] += 300.0
    assert judged(window) == {1}


def test_shift_distance_equals_the_two_sample_kolmogorov_smirnov_statistic_with_ties():
    rng = np.random.default_rng(7)
    window = rng.integers(0, 6, (50, 60)).astype(np.float64)  # many ties
    window[:25, -checks.RECENT:] += rng.integers(0, 4, (25, checks.RECENT))
    older, recent = window[:, :-checks.RECENT], window[:, -checks.RECENT:]

    def distance(a, b):  # by the definition: the largest gap between the two empirical CDFs
        points = np.union1d(a, b)
        return max(abs((a <= x).mean() - (b <= x).mean()) for x in points)
    expected = np.array([distance(a, b) for a, b in zip(older, recent)])
    critical = np.sqrt(-np.log(checks.SHIFT_P / 2) / 2 * (1 / older.shape[1] + 1 / recent.shape[1]))
    assert (checks._shift(window) == (expected > critical)).all()
    assert 0 < (expected > critical).sum() < 50  # both outcomes occur: the comparison means something


@pytest.mark.parametrize("direction", [1, -1])
def test_trend_follows_the_direction_of_the_change(direction):
    ramp = np.linspace(0, 100, K)[None, :] * direction
    assert checks._trend(ramp, np.array([direction])).all()
    assert not checks._trend(ramp, np.array([-direction])).any()
    flat = np.random.default_rng(5).normal(0, 1, (100, K))
    assert checks._trend(flat, np.ones(100)).sum() <= 1
