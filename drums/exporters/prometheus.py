"""Prometheus text exposition of a Snapshot (served at /metrics by drums.exporters.http).

The text is rendered here rather than by prometheus_client's generate_latest, which builds a
Python object per sample and took about 100 ms for 10,000 series (bench/render.py compares
the two); tests parse our output with prometheus_client's own parser to keep it honest.
"""
from __future__ import annotations

from itertools import compress
from operator import ne

from drums.metrics import HISTOGRAM, INFO, Metric, Snapshot

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
DEFAULT_PORT = 9969


def _escape(value: str) -> str:
    if "\\" in value or "\n" in value or '"' in value:
        return value.replace("\\", r"\\").replace("\n", r"\n").replace('"', r"\"")
    return value


def _number(value) -> str:
    if isinstance(value, int):
        return str(value)
    if value != value:
        return "NaN"
    if value in (float("inf"), float("-inf")):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value))


_INF = 'le="+Inf"'


def _labels(names: tuple[str, ...], values: tuple[str, ...]) -> str:
    parts = [f'{n}="{_escape(v)}"' for n, v in zip(names, values)]
    return "{" + ",".join(parts) + "}" if parts else ""


# The page is handed on in chunks of about this many bytes (a family is not split): a block of
# 256 KiB or more gets pages of its own from the system (selfcost.MMAP_THRESHOLD), faulted in at each
# scrape (about 3 us a page here: the whole page once joined, and again encoded, took 1-2 ms).
CHUNK = 64 * 1024


class Renderer:
    """Renders snapshots, remembering each family's rows and text: from one scrape to the next most
    families are the same (their rows compare equal, at C speed), and their text is taken as it
    was. In a family that changed, each row's text (a line, or a histogram's buckets, sum and
    count) is remembered with it: where the rows stand as they stood (as a rule), the rows are
    compared with the last ones in place, at C speed, and only the text of those that differ is
    written again. What a render did not use is forgotten."""

    def __init__(self):
        # metric -> (its rows, their texts, header, the texts' length)
        self._families: dict[Metric, tuple[list, list[str], str, int]] = {}

    def __call__(self, snap: Snapshot) -> bytes:
        return b"".join(self.chunks(snap))

    def chunks(self, snap: Snapshot) -> list[bytes]:
        """The page, as chunks of whole families of about CHUNK bytes each."""
        families, kept = self._families, {}
        chunks: list[bytes] = []
        part: list[str] = []
        size = 0
        for metric in sorted(snap.series, key=lambda m: m.name):
            rows = snap.series[metric]
            if not rows:
                continue
            last = families.get(metric)
            if last is None or last[0] != rows:  # rows copied: a snapshot may be added to after
                texts = _texts(metric, rows, last)
                header = last[2] if last else _header(metric)
                last = (rows.copy(), texts, header, len(header) + sum(map(len, texts)))
            kept[metric] = last
            part.append(last[2])
            part += last[1]
            size += last[3]
            if size >= CHUNK:
                chunks.append("".join(part).encode())
                part, size = [], 0
        if part:
            chunks.append("".join(part).encode())
        # Two renders at once: the last one's is kept, both are right.
        self._families = kept
        return chunks


def render(snap: Snapshot) -> bytes:
    """One snapshot, remembering nothing."""
    return Renderer()(snap)


def _header(metric: Metric) -> str:
    kind = "gauge" if metric.kind == INFO else metric.kind
    return f"# HELP {metric.name} {metric.help}\n# TYPE {metric.name} {kind}\n"


def _texts(metric: Metric, rows: list, last: tuple | None) -> list[str]:
    """The text of each row: the last render's where the row is the same (2 where 2.0 came: it is
    written as it was), else written again, with the label part of the last render's row of the
    same labels."""
    bounds = ['le="' + _number(b) + '"' for b in metric.buckets] if metric.kind == HISTOGRAM else None
    if last is not None and len(last[0]) == len(rows):  # the rows in place: compared one to one
        before, texts = last[0], last[1].copy()
        for i in compress(range(len(rows)), map(ne, rows, before)):
            texts[i] = _text(metric, rows[i], before[i], last[1][i], bounds)
        return texts
    known = {row[0]: (row, text) for row, text in zip(*last[:2])} if last is not None else {}
    return [_text(metric, row, *known.get(row[0], (None, "")), bounds) for row in rows]


def _text(metric: Metric, row: tuple, before: tuple | None, text: str, bounds: list[str] | None) -> str:
    """One row's text; `before`: the last render's row with its `text`, if one had these labels."""
    values, v = row
    same_labels = before is not None and before[0] == values
    if same_labels and before[1] == v:
        return text
    if bounds is not None:  # labels as escaped for the series' last text: its _count line's
        labels = text[text.rindex("\n", 0, -1) + len(metric.name) + 7:text.rindex(" ")] if same_labels else \
            _labels(metric.labels, values)
        return _histogram(metric.name, labels, v, bounds)
    line = text[:text.rindex(" ") + 1] if same_labels else f"{metric.name}{_labels(metric.labels, values)} "
    return f"{line}{_number(v)}\n"


def _histogram(name: str, labels: str, h, bounds: list[str]) -> str:
    """The lines of one histogram series (`labels` escaped and joined): its buckets, sum and count."""
    own = bounds if h.bounds is None else ['le="' + _number(b) + '"' for b in h.bounds]
    bucket = f"{name}_bucket{labels[:-1]}," if labels else f"{name}_bucket{{"
    lines = [f"{bucket}{bound}}} {count}\n" for bound, count in zip(own, h.cumulative)]
    lines.append(f"{bucket}{_INF}}} {h.count}\n")
    lines.append(f"{name}_sum{labels} {_number(h.sum)}\n")
    lines.append(f"{name}_count{labels} {h.count}\n")
    return "".join(lines)
