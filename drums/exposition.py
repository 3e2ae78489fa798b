"""Our own /metrics text read back, for `drums top` and `drums detect`: the lines that
drums.exporters.prometheus writes, `name{labels} value` with label values escaped and no
timestamps, and a `# TYPE` line for each family.
"""
from __future__ import annotations

import re
from collections.abc import Collection, Iterator

Rows = list[tuple[dict[str, str], float]]

_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\]|\\.)*)"')
_ESCAPE = re.compile(r"\\(.)")


def _unescape(value: str) -> str:
    return _ESCAPE.sub(lambda m: "\n" if m[1] == "n" else m[1], value) if "\\" in value else value


def samples(text: str) -> Iterator[tuple[str, str, str]]:
    """(its name, the series as written: name{labels}, its value as written) of each sample line."""
    for line in text.splitlines():
        if not line or line[0] == "#":
            continue
        space = line.rfind(" ")  # the value never holds one; a label value may
        if space < 0:
            raise ValueError(f"a line without a value: {line[:80]!r}")
        brace = line.find("{", 0, space)
        yield (line[:brace] if brace >= 0 else line[:space]), line[:space], line[space + 1:]


def labels(series: str) -> dict[str, str]:
    """The labels of a series as written, `name{a="1",b="2"}`."""
    brace = series.find("{")
    return {} if brace < 0 else {k: _unescape(v) for k, v in _LABEL.findall(series, brace)}


def types(text: str) -> dict[str, str]:
    """family name -> its type (counter, gauge, histogram), from the `# TYPE` lines."""
    found = {}
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            parts = line.split(" ", 3)
            if len(parts) == 4:
                found[parts[2]] = parts[3]
    return found


def rows(text: str, wanted: Collection[str]) -> dict[str, Rows]:
    """name -> [(labels, value)] for each wanted name (a histogram's rows are `<name>_bucket`,
    `_sum` and `_count`); names not on the page have no rows."""
    out: dict[str, Rows] = {name: [] for name in wanted}
    for name, series, value in samples(text):
        found = out.get(name)
        if found is not None:
            found.append((labels(series), float(value)))
    return out
