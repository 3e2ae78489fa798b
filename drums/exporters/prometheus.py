"""Prometheus text exposition of a Snapshot, served over HTTP at /metrics.

The text is rendered here rather than by prometheus_client's generate_latest, which builds a
Python object per sample and took about 100 ms for 10,000 series (bench/render.py compares
the two); tests parse our output with prometheus_client's own parser to keep it honest.
"""
from __future__ import annotations

import logging
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable
from urllib.parse import parse_qs, urlsplit

from drums.errors import DrumsError, UsageError
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


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        """One line, not socketserver's traceback; a client that hung up first is no news."""
        error = sys.exc_info()[1]
        if not isinstance(error, (BrokenPipeError, ConnectionResetError)):
            log.warning("request from %s failed: %s", client_address[0], error)


class MetricsServer:
    """Serves /metrics from a fresh snapshot per request, and /graph?format=F (text, json, dot,
    graphml) when given `graph`, which renders a format to (body, content type) and raises
    UsageError for a format it does not know; anything else is 404."""

    def __init__(self, collect: Callable[[], Snapshot], address: str, port: int,
                 graph: Callable[[str], tuple[bytes, str]] | None = None):
        handler = _handler(collect, graph)
        try:
            self.httpd = _Server((address, port), handler)
        except OSError as e:
            raise DrumsError(f"cannot listen on {address}:{port}: {e.strerror}") from None
        self.port = self.httpd.server_address[1]
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="metrics-http", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        if self._thread.is_alive():
            self.httpd.shutdown()
        self.httpd.server_close()


_TEXT = "text/plain; charset=utf-8"


def _handler(collect: Callable[[], Snapshot], graph: Callable[[str], tuple[bytes, str]] | None):
    pages = "/metrics" + (" and /graph" if graph else "")

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):
            url = urlsplit(self.path)
            if url.path == "/":
                links = "".join(f'<a href="{p}">{p}</a> ' for p in pages.split(" and "))
                self._reply(200, f"<html><body>{links}</body></html>\n".encode(), "text/html; charset=utf-8")
            elif url.path == "/metrics":
                self._page(lambda: (render(collect()), CONTENT_TYPE))
            elif url.path == "/graph" and graph:
                self._page(lambda: graph(parse_qs(url.query).get("format", ["json"])[-1]))
            else:
                self._reply(404, f"not found: Drums serves {pages}\n".encode(), _TEXT)

        def _page(self, make: Callable[[], tuple[bytes, str]]) -> None:
            try:
                body, content_type = make()
            except UsageError as e:
                self._reply(400, f"{e}\n".encode(), _TEXT)
                return
            except Exception as e:  # a scrape must never take the agent down
                log.exception("collect failed")
                self._reply(500, f"collect failed: {e}\n".encode(), _TEXT)
                return
            self._reply(200, body, content_type)

        def _reply(self, code: int, body: bytes, content_type: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, fmt, *args):  # scrapes are not news
            pass

    return Handler
