"""Prometheus text exposition of a Snapshot, served over HTTP at /metrics.

The text is rendered here rather than by prometheus_client's generate_latest, which builds a
Python object per sample and took about 100 ms for 10,000 series (bench/render.py compares
the two); tests parse our output with prometheus_client's own parser to keep it honest.
"""
from __future__ import annotations

import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable

from drums.errors import DrumsError
from drums.metrics import HISTOGRAM, INFO, Metric, Snapshot

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
DEFAULT_PORT = 9969
log = logging.getLogger("drums")


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


def render(snap: Snapshot) -> bytes:
    out: list[str] = []
    for metric in sorted(snap.series, key=lambda m: m.name):
        rows = snap.series[metric]
        if not rows:
            continue
        out.append(_family(metric, rows))
    return "".join(out).encode()


def _family(metric: Metric, rows) -> str:
    kind = "gauge" if metric.kind == INFO else metric.kind
    lines = [f"# HELP {metric.name} {metric.help}\n# TYPE {metric.name} {kind}\n"]
    name, names = metric.name, metric.labels
    if metric.kind == HISTOGRAM:
        bounds = ['le="' + _number(b) + '"' for b in metric.buckets]
        for values, h in rows:
            for bound, count in zip(bounds, h.cumulative):
                lines.append(f"{name}_bucket{_labels(names, values, bound)} {count}\n")
            lines.append(f"{name}_bucket{_labels(names, values, _INF)} {h.count}\n")
            lines.append(f"{name}_sum{_labels(names, values)} {_number(h.sum)}\n")
            lines.append(f"{name}_count{_labels(names, values)} {h.count}\n")
    else:
        for values, v in rows:
            lines.append(f"{name}{_labels(names, values)} {_number(v)}\n")
    return "".join(lines)


class MetricsServer:
    """Serves /metrics from a fresh snapshot per request; anything else is 404."""

    def __init__(self, collect: Callable[[], Snapshot], address: str, port: int):
        handler = _handler(collect)
        try:
            self.httpd = ThreadingHTTPServer((address, port), handler)
        except OSError as e:
            raise DrumsError(f"cannot listen on {address}:{port}: {e.strerror}") from None
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="metrics-http", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        if self._thread.is_alive():
            self.httpd.shutdown()
        self.httpd.server_close()


def _handler(collect: Callable[[], Snapshot]):
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):
            path = self.path.split("?", 1)[0]
            if path == "/":
                self._reply(200, b'<html><body><a href="/metrics">/metrics</a></body></html>\n',
                            "text/html; charset=utf-8")
                return
            if path != "/metrics":
                self._reply(404, b"not found: Drums serves /metrics\n", "text/plain; charset=utf-8")
                return
            try:
                body = render(collect())
            except Exception as e:  # a scrape must never take the agent down
                log.exception("collect failed")
                self._reply(500, f"collect failed: {e}\n".encode(), "text/plain; charset=utf-8")
                return
            self._reply(200, body, CONTENT_TYPE)

        def _reply(self, code: int, body: bytes, content_type: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, fmt, *args):  # scrapes are not news
            pass

    return Handler
