"""The agent's /metrics read back: the families `drums top` asks for, as (labels, value) rows.

A pure parser of the text our own exporter writes (drums.exporters.prometheus): `name{labels}
value` lines, label values escaped, no timestamps.
"""
from __future__ import annotations

import re
from collections.abc import Collection

Rows = list[tuple[dict[str, str], float]]

_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\]|\\.)*)"')
_ESCAPE = re.compile(r"\\(.)")


def _unescape(value: str) -> str:
    return _ESCAPE.sub(lambda m: "\n" if m[1] == "n" else m[1], value) if "\\" in value else value


def parse(text: str, wanted: Collection[str]) -> dict[str, Rows]:
    """name -> [(labels, value)] for each wanted name (a histogram's rows are `<name>_bucket`,
    `_sum` and `_count`); names not on the page have no rows."""
    out: dict[str, Rows] = {name: [] for name in wanted}
    for line in text.splitlines():
        if not line or line[0] == "#":
            continue
        space = line.rindex(" ")  # the value never holds one; a label value may
        brace = line.find("{", 0, space)
        rows = out.get(line[:brace] if brace >= 0 else line[:space])
        if rows is None:
            continue
        labels = {} if brace < 0 else {k: _unescape(v) for k, v in _LABEL.findall(line, brace, space)}
        rows.append((labels, float(line[space + 1:])))
    return out
