"""Prometheus text exposition of a Snapshot (served at /metrics by drums.exporters.http).

The text is rendered here rather than by prometheus_client's generate_latest, which builds a
Python object per sample and took about 100 ms for 10,000 series (bench/render.py compares
the two); tests parse our output with prometheus_client's own parser to keep it honest.
"""
from __future__ import annotations

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


def _labels(names: tuple[str, ...], values: tuple[str, ...], extra: str = "") -> str:
    parts = [f'{n}="{_escape(v)}"' for n, v in zip(names, values)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


class Renderer:
    """Renders snapshots, remembering each family's rows and text: from one scrape to the next most
    families are the same (their rows compare equal, at C speed), and their text is taken as it
    was. In a family that changed, each series' text (a line, or a histogram's buckets, sum and
    count) is remembered with its value, and only that of series whose value changed is written
    again. What a render did not use is forgotten."""

    def __init__(self):
        self._families: dict[Metric, tuple[list, str]] = {}  # metric -> (its rows, their text)
        self._lines: dict[Metric, dict[tuple, tuple]] = {}  # metric -> labels -> (value, line)

    def __call__(self, snap: Snapshot) -> bytes:
        families, lines = self._families, self._lines
        kept_families, kept_lines = {}, {}
        out: list[str] = []
        for metric in sorted(snap.series, key=lambda m: m.name):
            rows = snap.series[metric]
            if not rows:
                continue
            last = families.get(metric)
            if last is not None and last[0] == rows:
                text = last[1]
                kept_lines[metric] = lines.get(metric, {})
            else:
                text = _family(metric, rows, lines.get(metric, {}), kept_lines.setdefault(metric, {}))
            kept_families[metric] = (rows.copy(), text)  # a copy: a snapshot may be added to after
            out.append(text)
        # Two renders at once: the last one's is kept, both are right.
        self._families, self._lines = kept_families, kept_lines
        return "".join(out).encode()


def render(snap: Snapshot) -> bytes:
    """One snapshot, remembering nothing."""
    return Renderer()(snap)


def _family(metric: Metric, rows, known: dict, kept: dict) -> str:
    kind = "gauge" if metric.kind == INFO else metric.kind
    lines = [f"# HELP {metric.name} {metric.help}\n# TYPE {metric.name} {kind}\n"]
    name, names = metric.name, metric.labels
    if metric.kind == HISTOGRAM:
        bounds = ['le="' + _number(b) + '"' for b in metric.buckets]
    for values, v in rows:
        last = known.get(values)
        if last is None or last[0] != v:  # (a value equal to the last, 2.0 after 2, is written as it was)
            if metric.kind == HISTOGRAM:
                last = (v, _histogram(name, names, values, v, bounds))
            else:
                line = last[1][:last[1].rindex(" ") + 1] if last else f"{name}{_labels(names, values)} "
                last = (v, f"{line}{_number(v)}\n")
        kept[values] = last
        lines.append(last[1])
    return "".join(lines)


def _histogram(name: str, names: tuple[str, ...], values: tuple[str, ...], h, bounds: list[str]) -> str:
    """The lines of one histogram series: its buckets, sum and count."""
    own = bounds if h.bounds is None else ['le="' + _number(b) + '"' for b in h.bounds]
    lines = [f"{name}_bucket{_labels(names, values, bound)} {count}\n" for bound, count in zip(own, h.cumulative)]
    lines.append(f"{name}_bucket{_labels(names, values, _INF)} {h.count}\n")
    lines.append(f"{name}_sum{_labels(names, values)} {_number(h.sum)}\n")
    lines.append(f"{name}_count{_labels(names, values)} {h.count}\n")
    return "".join(lines)
