"""`drums report`: the anomalies of a time range from `drums detect --log`, as one HTML page with a
figure per flagged entity and in it a plot per anomalous series around its anomaly (the paper's
figures 5 and 7): its points from two minutes before to its end, the anomaly shaded.

The page stands alone (inline SVG, no script, nothing fetched), so it can be mailed or attached to
a bug report as it is.
"""
from __future__ import annotations

import html
import json
import sys
import time
from datetime import datetime

from drums.errors import UsageError

WIDTH, HEIGHT, PAD = 480, 120, 4


def moment(text: str) -> float:
    """Unix seconds from Unix seconds or an ISO 8601 time (local time when it has no zone)."""
    try:
        return float(text)
    except ValueError:
        pass
    try:
        return datetime.fromisoformat(text).timestamp()
    except ValueError:
        raise UsageError(f"{text!r} is neither Unix seconds nor an ISO 8601 time (2026-11-25T13:42)") from None


def read(path: str, begin: float, end: float) -> tuple[list[dict], int]:
    """The anomalies that overlap [begin, end), each once (its end event where it ended), and how
    many lines of the log were not events."""
    found: dict[tuple[str, str, float], dict] = {}
    bad = 0
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            for line in f:
                try:
                    event = json.loads(line)
                    kind = event["event"]
                except (ValueError, TypeError, KeyError):
                    bad += 1
                    continue
                if kind not in ("anomaly", "ended"):
                    bad += kind != "graph"
                    continue
                try:
                    start, stop = float(event["start"]), float(event["end"] or event["time"])
                    key = (event["entity"]["host"], event["series"], start)
                except (TypeError, KeyError, ValueError):
                    bad += 1
                    continue
                if start < end and stop >= begin and (key not in found or kind == "ended"):
                    found[key] = event
    except OSError as e:
        raise UsageError(f"{path}: {e.strerror}") from None
    return list(found.values()), bad


def plot(anomaly: dict) -> str:
    """An SVG line of the series' points, the anomaly's span shaded, its start a line."""
    points = [(float(t), float(v)) for t, v in anomaly.get("points") or []]
    if len(points) < 2:
        return '<p class="none">no points were logged for this series</p>'
    t0, t1 = points[0][0], points[-1][0]
    low, high = min(v for _, v in points), max(v for _, v in points)
    span, rise = (t1 - t0) or 1.0, (high - low) or 1.0

    def x(t: float) -> float:
        return PAD + (WIDTH - 2 * PAD) * (t - t0) / span

    def y(v: float) -> float:
        return HEIGHT - PAD - (HEIGHT - 2 * PAD) * (v - low) / rise
    start = min(max(float(anomaly["start"]), t0), t1)
    stop = min(float(anomaly.get("end") or t1), t1)
    line = " ".join(f"{x(t):.1f},{y(v):.1f}" for t, v in points)
    return (f'<svg viewBox="0 0 {WIDTH} {HEIGHT}" width="{WIDTH}" height="{HEIGHT}" role="img">'
            f'<rect class="span" x="{x(start):.1f}" y="0" width="{max(1.0, x(stop) - x(start)):.1f}" height="{HEIGHT}"/>'
            f'<line class="start" x1="{x(start):.1f}" x2="{x(start):.1f}" y1="0" y2="{HEIGHT}"/>'
            f'<polyline class="series" points="{line}"/></svg>')


def page(anomalies: list[dict], begin: float, end: float, source: str) -> str:
    """The report: entities with the most anomalous series first, each a figure."""
    by_entity: dict[tuple[str, str, str], list[dict]] = {}
    for a in sorted(anomalies, key=lambda a: a["start"]):
        e = a["entity"]
        by_entity.setdefault((e["host"], e["kind"], e["name"]), []).append(a)

    def when(t: float) -> str:
        return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))
    figures = []
    for (host, kind, name), found in sorted(by_entity.items(), key=lambda item: (-len(item[1]), item[0])):
        plots = "".join(
            f'<div class="plot"><h3>{html.escape(a["what"])} {html.escape(a["change"])}, {when(a["start"])}'
            f'{" to " + when(a["end"]) if a.get("end") else " (still anomalous)"}, {len(a["checks"])} checks of 5'
            f'</h3>{plot(a)}<p class="series">{html.escape(a["series"])}</p></div>' for a in found)
        figures.append(f'<figure><figcaption>{html.escape(kind)} <b>{html.escape(name)}</b> on '
                       f'{html.escape(host)}: {len(found)} anomalous series</figcaption>{plots}</figure>')
    body = "".join(figures) or "<p>No anomalies in this time range.</p>"
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>Drums anomalies {when(begin)} to {when(end)}</title>
<style>
body {{ font: 14px sans-serif; margin: 1em 2em; color: #222; }}
figure {{ border: 1px solid #ccc; padding: .5em 1em; margin: 1em 0; }}
figcaption {{ font-size: 16px; margin-bottom: .5em; }}
h3 {{ font-size: 13px; font-weight: normal; margin: .8em 0 .2em; }}
p.series {{ font: 11px monospace; color: #666; margin: 0; }}
svg {{ background: #fafafa; }}
rect.span {{ fill: #f6d3cf; }}
line.start {{ stroke: #c0392b; stroke-width: 1; }}
polyline.series {{ fill: none; stroke: #1f5f99; stroke-width: 1.5; }}
</style></head><body>
<h1>Anomalies from {when(begin)} to {when(end)}</h1>
<p>From {html.escape(source)}: {len(anomalies)} anomalous series on {len(by_entity)} entities.</p>
{body}
</body></html>
"""


def run(log: str, output: str, begin: str = "", end: str = "") -> int:
    t0, t1 = moment(begin) if begin else 0.0, moment(end) if end else time.time()
    if t1 <= t0:
        raise UsageError(f"--to {end} is not after --from {begin}")
    anomalies, bad = read(log, t0, t1)
    if bad:
        print(f"drums: {log}: {bad} lines that are not drums detect events were skipped", file=sys.stderr)
    text = page(anomalies, t0 or min((a["start"] for a in anomalies), default=t1), t1, log)
    try:
        with open(output, "w", encoding="utf-8") as f:
            f.write(text)
    except OSError as e:
        raise UsageError(f"--output {output}: {e.strerror}") from None
    print(f"{output}: {len(anomalies)} anomalous series", flush=True)
    return 0
