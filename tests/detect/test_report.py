"""`drums report` over a log written here: a figure per entity, a plot per anomalous series, the time
range honoured, lines that are not events skipped and counted, bad input one line."""
from __future__ import annotations

import json
import subprocess
import sys

T0 = 1_700_000_000.0


def anomaly(kind: str, name: str, series: str, start: float, end: float | None) -> dict:
    return {"time": end or start, "event": "ended" if end else "anomaly",
            "entity": {"kind": kind, "name": name, "host": "robot"}, "category": "network", "series": series,
            "what": "received bytes", "start": start, "end": end, "baseline": 100.0, "value": 18.0,
            "change": "-82%", "checks": ["average", "median", "histogram"], "severity": 9.0, "incident": 1,
            "leads": True, "text": "...", "points": [[start - 120 + i, 100.0 if i < 120 else 18.0] for i in range(130)]}


def report(tmp_path, *argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "drums", "report", *argv], capture_output=True, text=True,
                          timeout=60, cwd=tmp_path)


def test_a_figure_per_entity_and_a_plot_per_series_of_the_range(tmp_path):
    edge = ("edge", "/camera -> /processor on /image")
    lines = [anomaly(*edge, 'drums_edge_received_bytes_total{topic="/image"}', T0, None),
             anomaly(*edge, 'drums_edge_received_bytes_total{topic="/image"}', T0, T0 + 40),  # its end
             anomaly(*edge, 'drums_edge_samples_received_total{topic="/image"}', T0 + 1, T0 + 40),
             anomaly("node", "/processor", 'drums_node_cpu_seconds_total{node="/processor"}', T0 + 2, None),
             anomaly("node", "/planner", 'drums_node_cpu_seconds_total{node="/planner"}', T0 + 600, T0 + 700),
             {"time": T0, "event": "graph", "entity": {"kind": "node", "name": "/x", "host": "robot"}}]
    log = tmp_path / "events.jsonl"
    log.write_text("\n".join(json.dumps(line) for line in lines) + "\nnot json\n{\"event\": 1}\n")
    done = report(tmp_path, str(log), "--output", "page.html", "--from", str(T0 - 60), "--to", str(T0 + 300))
    assert done.returncode == 0, done.stderr
    assert done.stderr == f"drums: {log}: 2 lines that are not drums detect events were skipped\n"
    assert done.stdout == "page.html: 3 anomalous series\n"
    page = (tmp_path / "page.html").read_text()
    assert page.count("<figure>") == 2 and page.count("<polyline") == 3
    assert page.index("/camera -&gt; /processor on /image") < page.index("/processor</b>")  # the most series first
    assert "/planner" not in page  # outside the range
    assert page.count("(still anomalous)") == 1


def test_bad_input_is_one_line(tmp_path):
    for argv, says in ((["missing.jsonl", "--output", "x.html"], "missing.jsonl: No such file or directory"),
                       (["missing.jsonl", "--output", "x.html", "--from", "yesterday"], "'yesterday' is neither"),
                       (["missing.jsonl", "--output", "x.html", "--from", "200", "--to", "100"], "is not after")):
        done = report(tmp_path, *argv)
        assert done.returncode == 2 and len(done.stderr.splitlines()) == 1 and says in done.stderr, done.stderr
