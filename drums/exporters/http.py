"""The agent's HTTP server: /metrics for Prometheus, /graph, and the job API under /drums/v1
(described by the OpenAPI document it serves at /drums/v1/openapi.json).

Reads are open to anyone who can reach the port. With a token, every request that changes
something (POST, DELETE) must carry `Authorization: Bearer <token>`, compared in constant time;
the CLI refuses to bind off loopback without one.
"""
from __future__ import annotations

import gzip
import hmac
import json
import logging
import os
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable
from urllib.parse import parse_qs, urlsplit

from drums.errors import DrumsError, UsageError
from drums.exporters.jobs import KINDS, Forbidden, Jobs, NotFound, job_id, job_target, parse_body, whole

log = logging.getLogger("drums")

API = "/drums/v1"
MAX_BODY = 64 << 10  # a job's body is a few bytes
GZIP_FROM = 1400  # bytes: a smaller page fits in one packet as it is
GZIP_LEVEL = 6
JSON = "application/json"
TEXT = "text/plain; charset=utf-8"
OPENAPI = os.path.join(os.path.dirname(__file__), "openapi.yaml")
HOME = os.path.join(os.path.dirname(__file__), "home.html")  # the live graph, for a browser
READ_ONLY = (["info"], ["openapi.json"], ["jobs"])  # API paths that take only GET

# A page: query parameters -> (body, content type); raises UsageError for a bad query (400).
Page = Callable[[dict[str, str]], tuple[bytes, str]]


class HttpError(Exception):
    def __init__(self, code: int, message: str, headers: dict | None = None):
        super().__init__(message)
        self.code, self.headers = code, headers or {}


def openapi_document() -> dict:
    import yaml
    with open(OPENAPI) as f:
        return yaml.safe_load(f)


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        """One line, not socketserver's traceback (a request the handler could not even read)."""
        log.warning("request from %s failed: %s", client_address[0], sys.exc_info()[1])


class HttpServer:
    def __init__(self, address: str, port: int, pages: dict[str, Page], jobs: Jobs, info: Callable[[], dict],
                 token: str = "", stream: dict | None = None):
        """`stream`: the stream's {"port", "curve_public_key"}, named in every job."""
        handler = _handler(pages, jobs, info, token, stream or {})
        try:
            self.httpd = _Server((address, port), handler)
        except OSError as e:
            raise DrumsError(f"cannot listen on {address}:{port}: {e.strerror}") from None
        self.port = self.httpd.server_address[1]
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="http", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        if self._thread.is_alive():
            self.httpd.shutdown()
        self.httpd.server_close()


def _status(error: Exception) -> tuple[int, dict]:
    """The HTTP status and extra headers that say what went wrong with a request."""
    if isinstance(error, HttpError):
        return error.code, error.headers
    return (404 if isinstance(error, NotFound) else 403 if isinstance(error, Forbidden) else 400), {}


def _handler(pages: dict[str, Page], jobs: Jobs, info: Callable[[], dict], token: str, stream: dict):
    with open(HOME, "rb") as f:
        home = f.read()
    pages = {"/": lambda _query: (home, "text/html; charset=utf-8"), **pages}
    links = sorted(pages) + [f"{API}/openapi.json"]
    document = openapi_document()

    def api(method: str, parts: list[str], body: bytes, local: str) -> tuple[int, object]:
        """(status, JSON value) of a request under /drums/v1 that reached the agent at `local`."""
        where = {"address": f"tcp://{f'[{local}]' if ':' in local else local}:{stream['port']}",
                 "curve_public_key": stream["curve_public_key"]} if stream else {}

        def located(job: dict) -> dict:  # the stream as this client can reach it
            job["stream"].update(where)
            return job
        if parts in READ_ONLY:  # GET only (_api said 405 to anything else)
            if parts == ["info"]:
                return 200, dict(info(), stream=where)
            return 200, (document if parts == ["openapi.json"] else {"jobs": [located(j) for j in jobs.list()]})
        if len(parts) < 2 or parts[0] != "monitor" or parts[1] not in KINDS:
            raise NotFound(f"no such path {API}/{'/'.join(parts)}")
        kind = parts[1]
        target = job_target(kind, parts[2:])
        if method == "GET":
            return 200, located(jobs.get(job_id(kind, target)))
        if method == "DELETE":
            jobs.remove(job_id(kind, target))
            return 204, None
        try:
            # No body at all: the defaults. Anything else is JSON text, which whitespace alone is not;
            # a JSON null is no object.
            value = json.loads(body) if body else {}
        except (ValueError, UnicodeDecodeError) as e:
            raise UsageError(f"the body is not JSON ({e})") from None
        job, created = jobs.add(kind, target, *parse_body(kind, value))
        return (201 if created else 200), located(job)

    class Handler(BaseHTTPRequestHandler):
        def __getattr__(self, name: str):
            # http.server calls do_<METHOD>: every method goes to _serve, which answers what it does
            # not take (TRACE, OPTIONS, PUT ...) with a 405 that says what is served, not a 501 page.
            if name.startswith("do_"):
                return lambda: self._serve(name[3:])
            raise AttributeError(name)

        def _serve(self, method: str) -> None:
            url = urlsplit(self.path)
            in_api = url.path == API or url.path.startswith(API + "/")
            try:
                if in_api:
                    self._api(method, url.path)
                    return
                if method != "GET":
                    raise HttpError(405, f"{method} {url.path}: only GET", {"Allow": "GET"})
                page = pages.get(url.path)
                if page is None:
                    raise NotFound(f"not found: Drums serves {', '.join(links)}")
                query = {k: v[-1] for k, v in parse_qs(url.query).items()}
                body, content_type = page(query)
                body, headers = self._compressed(body)
                self._reply(200, body, content_type, headers)
            except (HttpError, UsageError) as e:  # the API answers in JSON, pages in text
                code, headers = _status(e)
                if in_api:
                    self._json(code, {"error": str(e)}, headers)
                else:
                    self._reply(code, f"{e}\n".encode(), TEXT, headers)
            except Exception as e:  # a request must never take the agent down
                log.error("%s %s failed: %s", method, url.path, e, exc_info=log.isEnabledFor(logging.DEBUG))
                self._reply(500, f"failed: {e}\n".encode(), TEXT)

        def _api(self, method: str, path: str) -> None:
            parts = [p for p in path[len(API):].split("/") if p]
            if method not in ("GET", "POST", "DELETE"):
                # Allow names what this resource takes (RFC 9110): the read-only ones take only GET.
                allow = "GET" if parts in READ_ONLY else "GET, POST, DELETE"
                raise HttpError(405, f"{method}: the API takes GET, POST and DELETE", {"Allow": allow})
            if parts in READ_ONLY and method != "GET":  # before the token: no token makes it a method they take
                raise HttpError(405, f"{method} {API}/{parts[0]}: only GET", {"Allow": "GET"})
            if method != "GET" and token and not self._authorized():
                raise HttpError(401, "a valid token is needed: Authorization: Bearer <token>",
                                {"WWW-Authenticate": "Bearer"})
            self._json(*api(method, parts, self._body(), self.connection.getsockname()[0]))

        def _authorized(self) -> bool:
            given = self.headers.get("Authorization", "")
            scheme, _, value = given.partition(" ")
            return scheme.lower() == "bearer" and hmac.compare_digest(value.strip().encode(), token.encode())

        def _body(self) -> bytes:
            given = self.headers.get("Content-Length", "0")
            length = whole(given)
            if length is None:
                raise HttpError(400, f"Content-Length {given!r} is not a length")
            if length > MAX_BODY:
                raise HttpError(413, f"a body over {MAX_BODY >> 10} KiB")
            return self.rfile.read(length)

        def _compressed(self, body: bytes) -> tuple[bytes, dict]:
            """The body gzipped if the client takes it (Prometheus does): a scrape is mostly
            repeated label text, a fifth of its size compressed."""
            accepted = {e.split(";")[0].strip() for e in self.headers.get("Accept-Encoding", "").split(",")}
            if "gzip" not in accepted or len(body) < GZIP_FROM:
                return body, {}
            return gzip.compress(body, compresslevel=GZIP_LEVEL), {"Content-Encoding": "gzip", "Vary": "Accept-Encoding"}

        def _json(self, code: int, value, headers: dict | None = None) -> None:
            body = b"" if code == 204 else json.dumps(value).encode() + b"\n"
            self._reply(code, body, JSON, headers)

        def _reply(self, code: int, body: bytes, content_type: str, headers: dict | None = None) -> None:
            try:
                self.send_response(code)
                if code != 204:
                    self.send_header("Content-Type", content_type)
                    self.send_header("Content-Length", str(len(body)))
                for name, value in (headers or {}).items():
                    self.send_header(name, value)
                self.end_headers()
                if code != 204 and self.command != "HEAD":  # an answer to HEAD has no body
                    self.wfile.write(body)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the client hung up before the answer (a scrape can take a while): no news

        def log_message(self, fmt, *args):  # scrapes are not news
            pass

    return Handler
