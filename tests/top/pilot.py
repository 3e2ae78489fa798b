"""Driving `drums top`'s app with Textual's Pilot against live agents, and reading what it shows."""
from __future__ import annotations

import asyncio
import re
import time

from drums.top.app import TopApp
from drums.top.collector import Collector
from drums.top.widgets import RowTable

SCALE = {"B": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30, "Hz": 1, "kHz": 1000, "us": 1e-6, "ms": 1e-3,
         "s": 1, "%": 1}


def number(text: str) -> float | None:
    """A figure as top shows it ("1.5 KiB/s", "10.1 Hz", "12%", "850 us", "-") back in base units."""
    if text == "-":
        return None
    m = re.fullmatch(r"(-?[\d.]+)\s*([A-Za-z%]*)(/s)?", text)
    assert m, f"not a figure: {text!r}"
    return float(m[1]) * SCALE.get(m[2], 1)


def shown(app: TopApp) -> list[dict[str, str]]:
    """The rows on screen: column title (without its sort arrow) -> the cell's text."""
    table = app.query_one(RowTable)
    titles = [str(c.label).strip().rstrip("▲▼") for c in table.ordered_columns]
    return [dict(zip(titles, (str(cell).strip() for cell in table.get_row_at(i)))) for i in range(table.row_count)]


def row(app: TopApp, **match: str) -> dict[str, str]:
    """The one row on screen whose cells have these texts (an AssertionError if none)."""
    found = [r for r in shown(app) if all(r.get(k) == v for k, v in match.items())]
    assert len(found) == 1, (match, shown(app))
    return found[0]


async def until(pilot, check, timeout: float):
    """Retry `check` (which asserts) on the live app until it passes; its result."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return check()
        except AssertionError:
            if time.monotonic() > deadline:
                raise
            await pilot.pause(0.05)


def run(urls: list[str], interval: float, scenario, view: str = "nodes", size=(80, 24)) -> None:
    """Run `await scenario(app, pilot)` in top's app on these agents, then close top as it closes
    (its jobs deleted)."""
    collector = Collector(urls, "", interval)
    app = TopApp(collector, view)

    async def main():
        async with app.run_test(size=size) as pilot:
            await scenario(app, pilot)
    try:
        asyncio.run(main())
    finally:
        collector.close()
