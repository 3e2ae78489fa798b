"""Map entries matched against the last read in bulk: what is new, counted on, changed or gone."""
import random
import struct
import subprocess
import sys

import numpy as np
import pytest

from drums.probes.entries import Entries


def entries(*items) -> tuple[bytes, bytes]:
    """(key, head, count) items as a batch read returns them: keys, then values."""
    return (b"".join(struct.pack("<Q", k) for k, _, _ in items),
            b"".join(struct.pack("<QQ", head, count) for _, head, count in items))


def test_entries_are_matched_by_key_head_and_value_and_keep_what_the_caller_made():
    e = Entries(16, 8)
    m = e.read(*entries((30, 1, 5), (10, 1, 5), (20, 2, 7)))
    assert m.keys.tolist() == [10, 20, 30] and m.words[:, 1].tolist() == [5, 7, 5]
    assert not m.same_head.any() and not m.same.any() and m.rows.tolist() == [None] * 3
    m.rows[:] = ["a", "b", "c"]
    e.keep(m, m.keys != 20)  # 20 is not kept: next time it is new
    # 10 idle; 30 counted on; 20 back (new to the table); 40 new; the order of the read is another
    m = e.read(*entries((40, 4, 0), (20, 2, 7), (30, 1, 6), (10, 1, 5)))
    assert m.keys.tolist() == [10, 20, 30, 40]
    assert m.same.tolist() == [True, False, False, False]
    assert m.same_head.tolist() == [True, False, True, False]
    assert m.rows.tolist() == ["a", None, "c", None]
    e.keep(m, m.keys > 0)
    # 10's key now names another thing (the kernel reused it): not the same head, its row is the
    # caller's to make again
    m = e.read(*entries((10, 9, 5), (30, 1, 6)))
    assert m.same_head.tolist() == [False, True] and m.same.tolist() == [False, True]
    assert m.rows.tolist() == ["a", "c"] and m.gone.tolist() == [None, None]  # 20 and 40: kept, never made


def test_an_empty_map_reads_as_nothing():
    e = Entries(16, 8)
    m = e.read(b"", b"")
    assert len(m.keys) == 0 and m.words.shape == (0, 2)
    e.keep(m, m.same)
    assert len(e.read(*entries((1, 1, 1))).keys) == 1


def test_changes_applied_to_the_last_read_match_as_a_whole_read_does():
    """Random steps of a map (keys come, go, are counted on, or reused for another thing): what
    update() makes of the changes alone equals what read() makes of the whole map, and the
    entries counted on come with their values of the last kept read."""
    rng = random.Random(7)
    state: dict[int, tuple[int, int]] = {}  # key -> (head, count)
    kept: dict[int, tuple[int, int]] = {}  # as the last kept read had them
    by_changes, by_reads = Entries(16, 8), Entries(16, 8)
    for step in range(200):
        changes = {}
        for key in rng.sample(range(1, 60), rng.randint(0, 12)):
            roll = rng.random()
            if roll < 0.2:
                state.pop(key, None)
                changes[key] = None
            else:
                head, count = state.get(key, (rng.randint(1, 3), 0))
                state[key] = (rng.randint(4, 6), 0) if roll < 0.3 else (head, count + rng.randint(0, 2))
                changes[key] = struct.pack("<QQ", *state[key])
        items = sorted(state.items(), key=lambda _: rng.random())  # a batch read's order is the kernel's
        whole = by_reads.read(*entries(*[(k, h, c) for k, (h, c) in items]))
        part = by_changes.update([(struct.pack("<Q", k), v) for k, v in changes.items()])
        for m in (whole, part):
            m.rows[m.rows == None] = [f"{k}@{step}" for k in m.keys[m.rows == None].tolist()]  # noqa: E711
        assert part.keys.tolist() == whole.keys.tolist(), step
        assert (part.words == whole.words).all() and part.same.tolist() == whole.same.tolist(), step
        assert part.same_head.tolist() == whole.same_head.tolist() and part.rows.tolist() == whole.rows.tolist()
        # told against the last read, which was kept: the rows whose values are not those it had
        assert part.told()[:2] == whole.told()[:2] == (step, step + 1), step
        assert part.told()[2].tolist() == [at for at, k in enumerate(part.keys.tolist()) if kept.get(k) != state[k]]
        assert sorted(part.gone.tolist()) == sorted(whole.gone.tolist()), step  # the rows of keys gone
        on = sorted(k for k, (h, c) in state.items() if k in kept and kept[k][0] == h and kept[k][1] != c)
        for m in (whole, part):
            assert m.keys[m.grown].tolist() == on, step
            assert [tuple(w) for w in m.before.tolist()] == [kept[k] for k in on], step
        keep = np.array([rng.random() > 0.05 for _ in range(len(whole.keys))], bool)
        by_reads.keep(whole, keep)
        by_changes.keep(part, keep)
        for k in whole.keys[~keep].tolist():  # not kept: the caller deleted it from the map
            state.pop(k, None)
        kept = dict(state)


def test_a_read_the_caller_did_not_keep_makes_the_next_read_make_every_row_anew():
    """A collect that fails between update() and keep() leaves values written in place beside rows
    that do not show them: the next read is of the whole map (update() refuses), and no row of the
    last kept read is taken as still current."""
    e = Entries(16, 8)
    m = e.read(*entries((10, 1, 5), (20, 1, 5)))
    m.rows[:] = ["a", "b"]
    e.keep(m, m.keys > 0)
    assert e.kept
    e.update([(struct.pack("<Q", 10), struct.pack("<QQ", 1, 6))])  # then the collect fails
    assert not e.kept
    with pytest.raises(ValueError):
        e.update([])
    m = e.read(*entries((10, 1, 6), (20, 1, 5)))
    assert m.rows.tolist() == [None, None] and not m.same_head.any() and not m.same.any()
    assert m.told() is None  # told against no read: a reader compares every row
    assert m.words[:, 1].tolist() == [6, 5]
    e.keep(m, m.keys > 0)
    assert e.kept


def test_distinct_values_come_ascending_without_importing_numpy_ma():
    """What the sockets and sched probes take per process each collect: np.unique asked for values
    alone imports numpy.ma (1.2 MB) at its first call."""
    code = ("import sys, numpy as np; from drums.arrays import distinct; "
            "print(distinct(np.array([7, 3, 7, 1, 3], np.int64)).tolist(), "
            "distinct(np.array([], np.uint32)).tolist(), 'numpy.ma' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[0] == "[1, 3, 7] [] False"
