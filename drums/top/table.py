"""Tables as `drums top` shows them: columns that know their format, rows that keep raw values,
and how rows are sorted, filtered and fitted to a width: columns are dropped by importance and
names cut with an ellipsis, so that a row never wraps.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

GAP = 1  # spaces between columns
ELLIPSIS = "…"


def plain(value) -> str:
    return "-" if value is None else str(value)


@dataclass(frozen=True)
class Column:
    key: str  # the value's name in a row and in --json, with its unit where it has one
    title: str
    fmt: Callable[[object], str] = plain
    name: bool = False  # a name: left-aligned, cut to fit, sorted A to Z; else a number, high first
    least: int = 0  # a name column's narrowest width before other columns are dropped
    keep: int = 0  # when the width is short, the columns with the lowest `keep` go first; 0: optional,
    # shown only where no name has to be cut for it


@dataclass
class Row:
    key: str  # the same across refreshes: the cursor and the history follow it
    values: dict[str, object]
    group: str = ""  # the key of the row it belongs under (a host's interfaces under the host)


@dataclass
class Table:
    view: str
    columns: list[Column]
    rows: list[Row]
    sort: str  # the column a view is sorted by until the user picks another
    spark: str  # the column the sparkline follows when the sort column is not a number
    note: str = ""  # said under the title: what a column cannot show yet, and why

    def column(self, key: str) -> Column:
        return next(c for c in self.columns if c.key == key)


def cells(table: Table, row: Row) -> list[str]:
    return [c.fmt(row.values.get(c.key)) for c in table.columns]


def arrange(table: Table, sort: str, reverse: bool, text: str) -> list[Row]:
    """The rows to show: those whose names contain `text` (any case), sorted by the column `sort`
    (names A to Z, numbers high to low, unknown values last; `reverse` turns it around), each
    row's group right under it."""
    column = table.column(sort)
    text = text.lower()
    leaders = [r for r in table.rows if not r.group]
    members: dict[str, list[Row]] = {}
    for r in table.rows:
        if r.group:
            members.setdefault(r.group, []).append(r)
    if text:
        leaders = [r for r in leaders if any(text in str(r.values.get(c.key) or "").lower()
                                             for c in table.columns if c.name)]
    known = [r for r in leaders if r.values.get(sort) is not None]
    unknown = [r for r in leaders if r.values.get(sort) is None]
    if column.name:
        known.sort(key=lambda r: str(r.values[sort]).lower(), reverse=reverse)
    else:
        known.sort(key=lambda r: r.values[sort], reverse=not reverse)
    unknown.sort(key=lambda r: r.key)
    return [r for leader in known + unknown for r in [leader, *members.get(leader.key, ())]]


def cut(text: str, width: int) -> str:
    """`text` in at most `width` characters: the middle gives way to an ellipsis, so that both a
    name's namespace and its end stay readable."""
    if len(text) <= width:
        return text
    if width <= 1:
        return ELLIPSIS[:width]
    head = (width - 1) // 3
    return text[:head] + ELLIPSIS + text[len(text) - (width - 1 - head):]


def fit(columns: list[Column], titles: list[str], rows: list[list[str]], width: int | None) -> list[int]:
    """Each column's width (0: left out) for rows of these cells to fit in `width` characters
    (None: as wide as they are). Numbers keep their full width; names shrink to their `least`,
    then the columns with the lowest `keep` go, and names get back what is left."""
    natural = [max([len(t)] + [len(r[i]) for r in rows]) for i, t in enumerate(titles)]
    if width is None:
        return natural
    least = [min(natural[i], max(c.least, len(titles[i]))) if c.name else natural[i]
             for i, c in enumerate(columns)]
    shown = list(range(len(columns)))

    def need(ix):
        return sum(least[i] for i in ix) + GAP * (len(ix) - 1)
    while len(shown) > 1 and need(shown) > width:
        shown.remove(min(reversed(shown), key=lambda i: columns[i].keep))  # the rightmost of the least kept
    if sum(natural[i] for i in shown) + GAP * (len(shown) - 1) > width:  # names will be cut:
        shown = [i for i in shown if columns[i].keep > 0] or shown  # optional columns make way for them
    widths = [0] * len(columns)
    for i in shown:
        widths[i] = least[i]
    spare = width - need(shown)
    if spare < 0:  # one column left, still too wide
        widths[shown[0]] = width
    for i in sorted((i for i in shown if columns[i].name), key=lambda i: -columns[i].keep):
        more = max(0, min(spare, natural[i] - widths[i]))
        widths[i] += more
        spare -= more
    return widths


def line(columns: list[Column], texts: list[str], widths: list[int]) -> str:
    """One row of text in these widths: names cut and left-aligned, numbers right-aligned."""
    out = []
    for column, text, width in zip(columns, texts, widths):
        if width:
            out.append(cut(text, width).ljust(width) if column.name else text.rjust(width)[-width:])
    return (" " * GAP).join(out)
