"""Sets of integers (PIDs, keys, inodes) as numpy arrays: membership and distinct values in bulk,
for the probes, the budget and the agent alike."""
from __future__ import annotations

import numpy as np


def within(keys: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    """Whether each of `keys` is among `sorted_keys`: a binary search each (np.isin hashes both,
    ten times slower for ten thousand keys, and imports numpy.ma: see distinct)."""
    if not len(sorted_keys):
        return np.zeros(len(keys), bool)
    return sorted_keys[np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)] == keys


def among(keys: np.ndarray, values) -> np.ndarray:
    """Whether each of `keys` is among `values`, a collection of ints: `within`, sorted for it."""
    return within(keys, np.sort(np.fromiter(values, keys.dtype, len(values))))


def rows_differ(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether each row of `a` differs from that of `b` (2-D, of one shape). A column at a time: the
    rows of a probe's map are wider than the columns compared, and reading them whole for each
    (a != b then any) took twice as long for ten thousand."""
    differ = np.zeros(len(a), bool)
    for j in range(a.shape[1]):
        differ |= a[:, j] != b[:, j]
    return differ


def distinct(values: np.ndarray) -> np.ndarray:
    """The distinct values, ascending. Asked for the values alone, np.unique (numpy 2.4) first asks
    numpy.ma whether the array is masked, importing it at its first call: 1.2 MB of the agent's
    memory for nothing. Asked for their counts too, it does not."""
    return np.unique(values, return_counts=True)[0]


def distinct_rows(words: np.ndarray) -> np.ndarray:
    """Where one row of each distinct row of a 2-D integer array is, in the rows' order. Sorted
    as integer columns: sorting records of bytes (np.unique of a structured array) takes ten
    times longer."""
    order = np.lexsort(words.T[::-1])
    w = words[order]
    return order[np.concatenate(([True], (w[1:] != w[:-1]).any(axis=1)))] if len(w) else order
