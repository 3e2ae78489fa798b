"""Map entries matched against the last read in bulk: what is new, counted on, changed or gone."""
import struct

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
    assert m.rows.tolist() == ["a", "c"]


def test_an_empty_map_reads_as_nothing():
    e = Entries(16, 8)
    m = e.read(b"", b"")
    assert len(m.keys) == 0 and m.words.shape == (0, 2)
    e.keep(m, m.same)
    assert len(e.read(*entries((1, 1, 1))).keys) == 1
