"""`drums top` from the command line: the live app, or one view printed for scripts."""
from __future__ import annotations

import asyncio
import os
import signal
import sys
import time
from functools import partial

from drums.client import AgentError
from drums.errors import UsageError
from drums.top.collector import Collector
from drums.top.model import Frame
from drums.top.screen import Views, document, text

ONCE_INTERVALS, ONCE_SLACK = 10, 10.0  # how long --once waits for a complete view, at most
ENDS = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)  # a closed terminal sends SIGHUP


def complete(frame: Frame, view: str = "") -> bool:
    """Whether every agent is down or has given two polls and two host samples (or said why not):
    every rate of the view is known; for Anomalies, whether the detector answered or said why not
    and every agent answered once or failed (the view names the agents' hosts)."""
    if view == "anomalies":
        return (frame.anomalies is not None or bool(frame.detector_error)) and \
            all(a.failed or a.latest is not None for a in frame.agents)
    return all(a.failed or (a.before is not None and (a.jobs_error or frame.sample(f"{a.host}:host:")[0] is not None))
               for a in frame.agents)


def _print(collector: Collector, view: str, as_json: bool) -> int:
    """One complete view (the first with every rate, or what is known after a while) for scripts."""
    deadline = time.monotonic() + ONCE_INTERVALS * collector.interval + ONCE_SLACK
    while not complete(collector.model.frame(), view) and time.monotonic() < deadline:
        collector.stopping.wait(0.05)
    frame = collector.model.frame()
    if all(a.latest is None for a in frame.agents):
        raise AgentError("; ".join(a.error or f"{a.url}: no answer" for a in frame.agents))
    table = Views().table(frame, view)
    sys.stdout.write((document if as_json else text)(frame, table, table.sort))
    return 0


def run(urls: list[str], token: str, interval: float, view: str = "nodes", once: bool = False,
        as_json: bool = False, color: bool = True, detector: str = "") -> int:
    if not (once or as_json) and not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise UsageError("the live view needs a terminal: --once or --json print one view for scripts")
    collector = Collector(urls, token, interval, detector)
    app = None

    def leave(signum, _frame):
        """SIGTERM or SIGINT: the app ends as on `q`, the terminal given back; outside the app top
        ends at once, through the finally below, which deletes top's jobs. SIGHUP: the terminal
        is gone, and Textual, which would give it back, busy-reads the dead one and may never end:
        top deletes its jobs and ends here."""
        if signum == signal.SIGHUP and app is not None:
            ignore()
            collector.close()
            os._exit(128 + signum)
        if app is None or not app.is_running:
            raise SystemExit(128 + signum)
        asyncio.get_running_loop().call_soon_threadsafe(partial(app.exit, return_code=128 + signum))

    def ignore():  # a second signal must not cut the deletion of the jobs short
        for sig in ENDS:
            signal.signal(sig, signal.SIG_IGN)
    for sig in ENDS:  # before anything is made on the agents
        signal.signal(sig, leave)
    try:
        if once or as_json:
            collector.start()
            return _print(collector, view, as_json)
        if not color:
            os.environ["NO_COLOR"] = "1"  # Textual reads it when the app is made
        from drums.top.app import TopApp
        app = TopApp(collector, view)
        app.run()
        return app.return_code or 0
    finally:
        ignore()
        collector.close()
