"""What every face of `drums top` shows the same way: the views by name, the line that sums up
the agents, and a table as plain text (for --once, and the app's rows)."""
from __future__ import annotations

import json

from drums.top import anomalies, hosts, views
from drums.top.losses import Losses
from drums.top.model import Frame
from drums.top.table import Row, Table, arrange, cells, fit, line


class Views:
    """Builds each view's Table from a frame; keeps what outlives a frame (messages lost)."""

    def __init__(self):
        self.losses = Losses()
        self.processes = True  # whether Nodes lists the processes that hold no node

    def table(self, frame: Frame, view: str) -> Table:
        if view == "nodes":
            return views.nodes(frame, self.processes)
        if view == "topics":
            return views.topics(frame, self.losses)
        if view == "edges":
            return views.edges(frame)
        if view == "connections":
            return hosts.connections(frame)
        if view == "anomalies":
            return anomalies.anomalies(frame)
        return hosts.hosts(frame)


def agents_line(frame: Frame) -> str:
    """Each agent's host (its URL until it answered) and state: "arm up, base down"."""
    return ", ".join(f"{a.host or a.url} {a.state(frame.at, frame.interval)}" for a in frame.agents)


def title(frame: Frame, table: Table, shown: int) -> str:
    """The view, how many of its rows the filter lets through, each agent's state."""
    every = sum(1 for r in table.rows if not r.group)
    return (f"drums top  {table.view.capitalize()}: {shown} of {every}  "
            f"hosts: {agents_line(frame)}  every {frame.interval:g} s")


def headers(table: Table, sort: str, reverse: bool) -> list[str]:
    """Column titles, the sort column's marked with the way it runs (names A to Z go up)."""
    arrow = {False: "▼", True: "▲"}
    return [c.title + (arrow[reverse ^ c.name] if c.key == sort else "") for c in table.columns]


def text(frame: Frame, table: Table, sort: str, reverse: bool = False, match: str = "") -> str:
    """The view as plain text, every name whole (for scripts: --once)."""
    rows = arrange(table, sort, reverse, match)
    titles = headers(table, sort, reverse)
    texts = [cells(table, r) for r in rows]
    widths = fit(table.columns, titles, texts, None)
    out = [title(frame, table, sum(1 for r in rows if not r.group))]
    if table.note:
        out.append(f"({table.note})")
    out += [line(table.columns, titles, widths).rstrip()] + [line(table.columns, t, widths).rstrip() for t in texts]
    return "\n".join(out) + "\n"


def document(frame: Frame, table: Table, sort: str, reverse: bool = False, match: str = "") -> str:
    """The view as JSON (--json): the agents and every row's values in base units, keyed as the
    columns are (cpu_percent, sent_bytes_per_second, ...)."""
    def row(r: Row) -> dict:
        return {"key": r.key, **({"group": r.group} if r.group else {}), **r.values}
    return json.dumps({
        "time": frame.at, "interval": frame.interval, "view": table.view, "note": table.note or None,
        "agents": [{"url": a.url, "host": a.host or None, "state": a.state(frame.at, frame.interval),
                    "error": a.error or a.jobs_error or None} for a in frame.agents],
        "columns": [c.key for c in table.columns],
        "rows": [row(r) for r in arrange(table, sort, reverse, match)]}, indent=1) + "\n"
