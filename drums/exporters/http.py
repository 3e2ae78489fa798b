"""The agent's HTTP server: /metrics for Prometheus, /graph, and the job API under /drums/v1
(described by the OpenAPI document it serves at /drums/v1/openapi.json).

Reads are open to anyone who can reach the port. With a token, every request that changes
something (POST, DELETE) must carry `Authorization: Bearer <token>`, compared in constant time;
the CLI refuses to bind off loopback without one.

It holds against clients that are slow, many or gone (h11's HTTP/1.1 parser on one asyncio event
loop, so a connection costs a few kilobytes and no thread):
- a connection that has not sent a whole request within IDLE seconds is closed, and so is one
  idle that long between requests; a body must arrive within BODY_TIMEOUT, an answer must be
  taken within SEND_TIMEOUT;
- at most `limit` connections are open (below the open-file limit): one more closes the oldest
  connection that is waiting for a request, so a flood of slow or idle connections cannot lock
  Prometheus out;
- request heads and bodies have size limits, and heads a limit on their header lines; a request
  the parser refuses is answered with a 4xx that says why, and counted;
- scrapes and /graph reads share snapshots: a request is answered from a snapshot collected after
  it arrived, and every request that arrives while one is being collected shares the next, drawn
  once per page and query. A client that hangs up leaves the others' work running and adds none.
"""
from __future__ import annotations

import asyncio
import functools
import hmac
import http
import json
import logging
import os
import resource
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Callable
from urllib.parse import parse_qs, urlsplit

import h11
from isal import isal_zlib

from drums.errors import DrumsError, UsageError
from drums.exporters import READ_AT
from drums.exporters.jobs import KINDS, Forbidden, Jobs, NotFound, job_id, job_target, parse_body
from drums.metrics import COUNTER, GAUGE, Metric, Snapshot

if TYPE_CHECKING:
    from drums.exporters.stream import Stream

log = logging.getLogger("drums")

API = "/drums/v1"
MAX_BODY = 64 << 10  # a job's body is a few bytes
MAX_HEAD = 16 << 10  # a request line and its headers
MAX_HEADERS = 64
READ_SIZE = 64 << 10  # bytes read from a connection at a time
IDLE = 10.0  # seconds a connection may take to send a whole request head, or stay idle between requests
BODY_TIMEOUT = 10.0
SEND_TIMEOUT = 30.0  # a scrape of a large host is a few MB: 30 s is a slow link, not a stalled reader
BACKLOG = 1024  # connections the kernel queues for us
ACCEPT_BATCH = 64  # connections asyncio accepts at a time, before any is counted against the limit
MAX_CONNECTIONS = 512
FD_RESERVE = 256  # open files kept for the probes, jobs and /proc reads
WORKERS = 2  # threads drawing pages and answering the API (the GIL makes more useless)
DRAWN_PER_SNAPSHOT = 8  # distinct page and query pairs whose drawings a snapshot keeps
GZIP_FROM = 1400  # bytes: a smaller page fits in one packet as it is
# ISA-L's gzip at its level 1: a scrape of 230 KB in 0.26 ms to 29 KB, where zlib's fastest level
# took 1.3 ms for 31 KB; on a robot the CPU is dearer than a few KB a scrape.
GZIP_LEVEL = 1
GZIP_WBITS = 31  # zlib's way to say a gzip header and trailer
CLOSED_SAID_EVERY = 60.0  # seconds: at most one line about connections closed over the limit
JSON = "application/json"
TEXT = "text/plain; charset=utf-8"
OPENAPI = os.path.join(os.path.dirname(__file__), "openapi.yaml")
HOME = os.path.join(os.path.dirname(__file__), "home.html")  # the live graph, for a browser
READ_ONLY = (["info"], ["openapi.json"], ["jobs"])  # API paths that take only GET

HTTP_CONNECTIONS = Metric("drums_http_connections", GAUGE, "Open connections to the agent's HTTP server")
HTTP_CONNECTION_LIMIT = Metric("drums_http_connection_limit", GAUGE,
                               "Connections the HTTP server holds at most (set from the open-file limit)")
HTTP_CLOSED = Metric("drums_http_connections_closed_total", COUNTER,
                     "Connections the HTTP server closed before they were done: over_limit (the oldest waiting "
                     "one, when another came over the limit), slow_reader (an answer not taken in time), "
                     "bad_request (a request the HTTP parser refused, with a 400 that says why)",
                     ("reason",))
METRICS = (HTTP_CONNECTIONS, HTTP_CONNECTION_LIMIT, HTTP_CLOSED)

# A page: query parameters -> (body, content type); raises UsageError for a bad query (400).
Page = Callable[[dict[str, str]], tuple[bytes, str]]
# A picture: a page drawn from a snapshot of the agent, shared by the requests that arrive together.
Picture = Callable[[Snapshot, dict[str, str]], tuple[bytes, str]]


class HttpError(Exception):
    def __init__(self, code: int, message: str, headers: dict | None = None):
        super().__init__(message)
        self.code, self.headers = code, headers or {}


@functools.cache
def openapi_document() -> dict:
    """The API's OpenAPI description, parsed when first asked for: YAML takes 40 ms of a start
    (and its parser's memory) that an agent nobody asks this of never needs."""
    import yaml
    with open(OPENAPI) as f:
        return yaml.safe_load(f)


def connection_limit() -> int:
    """How many connections the server may hold: the open-file limit raised to its hard limit (as
    Go does for node_exporter), less the files open now and a reserve, at most MAX_CONNECTIONS."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError):
            pass
    free = ((soft if soft != resource.RLIM_INFINITY else 1 << 20) - len(os.listdir("/proc/self/fd")) - FD_RESERVE
            - ACCEPT_BATCH)
    return max(16, min(MAX_CONNECTIONS, free))


class _Connections:
    """The open connections, at most `limit`. Over it, the oldest connection that is waiting for a
    request (a slow or idle one) is closed; Prometheus's keep-alive connection, if it was that one,
    simply reconnects."""

    def __init__(self, limit: int):
        self.limit = limit
        self.closed = {"over_limit": 0, "slow_reader": 0, "bad_request": 0}
        self.open: set[asyncio.Transport] = set()
        self._waiting: dict[asyncio.Transport, None] = {}  # oldest first
        self._said = 0.0

    def came(self, transport: asyncio.Transport) -> None:
        self.open.add(transport)
        self._waiting[transport] = None
        if len(self.open) > self.limit:
            victim = next(iter(self._waiting))
            self.went(victim)
            victim.abort()  # its reader sees the end of the stream
            self.count_closed("over_limit")

    def went(self, transport: asyncio.Transport) -> None:
        self.open.discard(transport)
        self._waiting.pop(transport, None)

    def busy(self, transport: asyncio.Transport, busy: bool) -> None:
        """A request is being answered on the connection (it may not be closed), or is done."""
        if busy:
            self._waiting.pop(transport, None)
        elif transport in self.open:
            self._waiting[transport] = None

    def count_closed(self, reason: str, why: object = "") -> None:
        self.closed[reason] += 1
        now = time.monotonic()
        if now - self._said >= CLOSED_SAID_EVERY:
            self._said = now
            last = f"; the last bad request: {' '.join(str(why).split())[:200]}" if why else ""
            log.warning("http: connections closed since start: %s (at most %d are held)%s; said at most once a minute",
                        ", ".join(f"{n} {r.replace('_', ' ')}" for r, n in self.closed.items()), self.limit, last)


class _Request:
    """One request, as its connection read it: what the handlers need of it."""

    def __init__(self, event: h11.Request, connection: "_Connection"):
        self.method = event.method.decode("ascii")
        self.target = event.target.decode("ascii")  # h11 takes only visible ASCII there
        self.headers = {name.decode("latin-1"): value.decode("latin-1") for name, value in event.headers}
        self.local = connection.local
        self._connection = connection

    async def body(self) -> bytes:
        """The request's body (chunked or not), at most MAX_BODY bytes, within BODY_TIMEOUT."""
        if int(self.headers.get("content-length", 0)) > MAX_BODY:
            raise HttpError(413, f"a body over {MAX_BODY >> 10} KiB")
        try:
            return await asyncio.wait_for(self._connection.body(), BODY_TIMEOUT)
        except asyncio.TimeoutError:
            raise HttpError(408, f"the body did not arrive within {BODY_TIMEOUT:g} s") from None


class _Connection:
    """One client's connection: h11 reads its requests from the stream and frames the answers."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self.reader, self.writer = reader, writer
        self.h11 = h11.Connection(h11.SERVER, max_incomplete_event_size=MAX_HEAD)
        # drain() then waits until all is handed to the kernel: a connection closed after it loses nothing.
        writer.transport.set_write_buffer_limits(0)
        sockname = writer.get_extra_info("sockname")
        self.local = sockname[0] if sockname else "127.0.0.1"

    async def next_event(self):
        """The next event of the client, reading as needed; None when the client hung up (or the
        server closed the connection) between or inside requests."""
        while True:
            event = self.h11.next_event()
            if event is not h11.NEED_DATA:
                return event
            data = await self.reader.read(READ_SIZE)
            if not data:
                return None
            self.h11.receive_data(data)

    async def body(self) -> bytes:
        body = bytearray()
        if self.h11.they_are_waiting_for_100_continue:
            await self.send(h11.InformationalResponse(status_code=100, headers=[]))
        while isinstance(event := await self.next_event(), h11.Data):
            body += event.data
            if len(body) > MAX_BODY:
                raise HttpError(413, f"a body over {MAX_BODY >> 10} KiB")
        if event is None:
            raise ConnectionResetError("the client left in the middle of its body")
        return bytes(body)

    async def send(self, *events) -> None:
        self.writer.write(b"".join(self.h11.send(event) for event in events))
        await self.writer.drain()


class _Shared:
    """Snapshots and their drawings, shared by concurrent requests. Each request is answered from a
    snapshot collected after it arrived; those that arrive while one is being collected share the
    next. Runs on the event loop; collecting and drawing run in threads. The collector thread draws
    the picture of the request that started the collect itself: one hop between threads fewer
    (0.3-0.5 ms of a scrape, measured)."""

    def __init__(self, collect: Callable[[], Snapshot], workers: ThreadPoolExecutor):
        self._collect, self._workers = collect, workers
        self._collector = ThreadPoolExecutor(1, thread_name_prefix="http-collect")
        self._running: asyncio.Future | None = None
        self._next: asyncio.Future | None = None
        self._next_asked: tuple | None = None
        self._drawn: dict[tuple, asyncio.Future] = {}
        self._drawn_of: Snapshot | None = None
        # (snapshot, key, drawing, error) the collector thread drew; taken by draw() on the loop once
        # the collect's future is done
        self._ready: tuple | None = None

    async def snapshot(self, picture: Picture, query: dict[str, str], gzipped: bool) -> Snapshot:
        asked = (picture, query, gzipped)
        if self._running is None:
            self._running = self._start(asked)
            waited = self._running
        else:
            if self._next is None:
                self._next, self._next_asked = asyncio.get_running_loop().create_future(), asked
            waited = self._next
        return await asyncio.shield(waited)  # a request that goes leaves the snapshot to the others

    def _start(self, asked: tuple) -> asyncio.Future:
        running = asyncio.get_running_loop().run_in_executor(self._collector, self._collected_drawn, asked)
        running.add_done_callback(self._collected)
        return running

    def _collected_drawn(self, asked: tuple) -> Snapshot:
        """In the collector thread: a snapshot, and the picture asked drawn of it."""
        snap = self._collect()
        picture, query, gzipped = asked
        try:
            self._ready = (snap, _key(*asked), _drawn(picture, snap, query, gzipped), None)
        except Exception as e:  # noqa: BLE001 - the request that asked gets it, as from a worker
            self._ready = (snap, _key(*asked), None, e)
        return snap

    def _collected(self, done: asyncio.Future) -> None:
        self._running = None
        if self._next is None:
            return
        waiting, self._next = self._next, None
        self._running = self._start(self._next_asked)
        self._running.add_done_callback(lambda f: _settle(waiting, f))

    async def draw(self, picture: Picture, snap: Snapshot, query: dict[str, str], gzipped: bool) -> tuple:
        """(body, content type, headers) of `picture` of `snap`, drawn once for all who ask."""
        if snap is not self._drawn_of:
            self._drawn, self._drawn_of = {}, snap
            ready, self._ready = self._ready, None
            if ready is not None and ready[0] is snap:
                drawing = self._drawn[ready[1]] = asyncio.get_running_loop().create_future()
                if ready[3] is not None:
                    drawing.set_exception(ready[3])
                else:
                    drawing.set_result(ready[2])
        key = _key(picture, query, gzipped)
        drawing = self._drawn.get(key)
        if drawing is None:
            drawing = asyncio.get_running_loop().run_in_executor(self._workers, _drawn, picture, snap, query, gzipped)
            if len(self._drawn) < DRAWN_PER_SNAPSHOT:  # a stream of distinct queries is drawn, not kept
                self._drawn[key] = drawing
        return await asyncio.shield(drawing)

    def close(self) -> None:
        self._collector.shutdown(wait=False, cancel_futures=True)


def _key(picture: Picture, query: dict[str, str], gzipped: bool) -> tuple:
    return picture, tuple(sorted(query.items())), gzipped


def _settle(waiting: asyncio.Future, done: asyncio.Future) -> None:
    if waiting.done():
        return
    if done.cancelled():
        waiting.cancel()
    elif done.exception() is not None:
        waiting.set_exception(done.exception())
    else:
        waiting.set_result(done.result())


def _drawn(page: Callable, *args) -> tuple[bytes, str, dict]:
    """(body, content type, headers) of a page or picture drawn with `args`, the last of which
    says whether the client takes gzip. A page may come as a list of chunks (the metrics)."""
    body, content_type = page(*args[:-1])
    body, headers = _compressed(body if isinstance(body, list) else [body], args[-1])
    return body, content_type, headers


def _compressed(chunks: list[bytes], gzipped: bool) -> tuple[bytes, dict]:
    """The body gzipped if the client takes it (Prometheus does): a scrape is mostly repeated label
    text, an eighth of its size compressed. Chunks are compressed one after the other, never
    joined: the page whole would be a block of its own pages."""
    if not gzipped or sum(map(len, chunks)) < GZIP_FROM:
        return b"".join(chunks), {}
    deflate = isal_zlib.compressobj(GZIP_LEVEL, isal_zlib.DEFLATED, GZIP_WBITS)
    return (b"".join([*map(deflate.compress, chunks), deflate.flush()]),
            {"Content-Encoding": "gzip", "Vary": "Accept-Encoding"})


def _status(error: Exception) -> tuple[int, dict]:
    """The HTTP status and extra headers that say what went wrong with a request."""
    if isinstance(error, HttpError):
        return error.code, error.headers
    return (404 if isinstance(error, NotFound) else 403 if isinstance(error, Forbidden) else 400), {}


def _listen(address: str, port: int) -> socket.socket:
    try:
        family = socket.AF_INET6 if ":" in address else socket.AF_INET
        return socket.create_server((address, port), family=family, backlog=BACKLOG)
    except OSError as e:
        raise DrumsError(f"cannot listen on {address}:{port}: {os.strerror(e.errno)}") from None


class HttpServer:
    def __init__(self, address: str, port: int, pages: dict[str, Page], pictures: dict[str, Picture],
                 collect: Callable[[], Snapshot], jobs: Jobs | None, info: Callable[[], dict] | None,
                 token: str = "", stream: Stream | None = None):
        """`pages` are drawn on each request, `pictures` from the shared snapshot `collect()` takes.
        `stream`: the stream of job samples, named in every job. Without `jobs`
        there is no job API (the detector serves only its pages)."""
        self._sock = _listen(address, port)
        self.port = self._sock.getsockname()[1]
        with open(HOME, "rb") as f:
            home = f.read()
        self._pages = {"/": lambda _query: (home, "text/html; charset=utf-8"), **pages}
        self._pictures = pictures
        self._links = sorted([*self._pages, *pictures, *([f"{API}/openapi.json"] if jobs is not None else [])])
        self._jobs, self._info, self._token, self._stream = jobs, info, token, stream
        self._workers = ThreadPoolExecutor(WORKERS, thread_name_prefix="http")
        self._shared = _Shared(lambda: self._counted(collect()), self._workers)
        self._server: _Connections | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
        self._ready = threading.Event()
        self._failed: BaseException | None = None
        self._loop_said = 0.0
        self._thread = threading.Thread(target=self._run, name="http", daemon=True)

    def start(self) -> None:
        self._limit = connection_limit()  # after the probes have opened their files
        self._thread.start()
        self._ready.wait()
        if self._failed is not None:
            raise DrumsError(f"cannot serve http: {self._failed}")

    def stop(self) -> None:
        if self._thread.is_alive() and self._loop is not None:
            self._loop.call_soon_threadsafe(self._stopping.set)
            self._thread.join(timeout=5)
        self._shared.close()
        self._workers.shutdown(wait=False, cancel_futures=True)
        self._sock.close()

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as e:  # noqa: BLE001 - said by start(), which waits for it
            self._failed = e
            self._ready.set()

    async def _serve(self) -> None:
        self._loop, self._stopping = asyncio.get_running_loop(), asyncio.Event()
        self._server = _Connections(self._limit)
        self._loop.set_exception_handler(self._loop_error)
        # asyncio accepts as many connections at a time as the listen backlog it is given, each an open
        # file before the limit sees it: it gets a small one, and the kernel's queue is set long again.
        server = await asyncio.start_server(self._connection, sock=self._sock, backlog=ACCEPT_BATCH,
                                            limit=READ_SIZE)
        self._sock.listen(BACKLOG)
        self._ready.set()
        await self._stopping.wait()
        server.close()
        for transport in list(self._server.open):
            transport.abort()

    def _loop_error(self, _loop, context: dict) -> None:
        """asyncio's complaints (accept failing when the open files run out) in one line a minute."""
        now = time.monotonic()
        if now - self._loop_said >= CLOSED_SAID_EVERY:
            self._loop_said = now
            log.warning("http: %s: %s (said at most once a minute)", context.get("message"), context.get("exception"))

    def _counted(self, snap: Snapshot) -> Snapshot:
        """The snapshot with the server's own metrics (read from the collecting thread: a few ints)."""
        server = self._server
        if server is not None:
            snap.add(HTTP_CONNECTIONS, (), len(server.open))
            snap.add(HTTP_CONNECTION_LIMIT, (), server.limit)
            for reason, count in server.closed.items():
                snap.add(HTTP_CLOSED, (reason,), count)
        return snap

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Serve one connection's requests, one after the other, until either side ends it."""
        connections, transport = self._server, writer.transport
        connection = _Connection(reader, writer)
        connections.came(transport)
        try:
            while True:
                try:  # a whole request head within IDLE, from the connection or the last answer
                    event = await asyncio.wait_for(connection.next_event(), IDLE)
                except asyncio.TimeoutError:
                    return
                if not isinstance(event, h11.Request):
                    return  # the client hung up
                connections.busy(transport, True)
                _check_head(event)
                request = _Request(event, connection)
                code, body, content_type, headers = await self._answer(request)
                if not await self._send(connection, code, body, content_type, headers, request.method != "HEAD"):
                    return
                connections.busy(transport, False)
                if connection.h11.their_state is h11.SEND_BODY:  # a body we did not need: read it, bounded
                    await request.body()
                if connection.h11.our_state is not h11.DONE or connection.h11.their_state is not h11.DONE:
                    return  # HTTP/1.0, or "Connection: close"
                connection.h11.start_next_cycle()
        except h11.RemoteProtocolError as e:
            await self._refuse(connection, e)
        except (HttpError, ConnectionError):
            pass  # a body too large or too slow after its answer, or a client gone: no news
        finally:
            connections.went(transport)
            writer.close()  # all that was sent is with the kernel, or the connection is aborted

    async def _refuse(self, connection: _Connection, error: h11.RemoteProtocolError) -> None:
        """Answer a request h11 refused with a 4xx that says why (and close): a client's mistake,
        not the agent's, counted and said in one line at most once a minute."""
        code = error.error_status_hint
        # h11 says what it refused, then quotes it ("illegal request line: bytearray(b'...')"): the
        # first part is the reason; the client knows what it sent.
        why = f"a request head over {MAX_HEAD >> 10} KiB" if str(error) == "Receive buffer too long" \
            else str(error).partition(": ")[0]
        self._server.count_closed("bad_request", why)
        if connection.h11.our_state in (h11.IDLE, h11.SEND_RESPONSE):
            await self._send(connection, code, f"{why}\n".encode(), TEXT, {"Connection": "close"})

    async def _answer(self, request: _Request) -> tuple[int, bytes, str, dict]:
        url = urlsplit(request.target)
        in_api = self._jobs is not None and (url.path == API or url.path.startswith(API + "/"))
        method = request.method
        try:
            if in_api:
                return await self._api(request, method, url.path)
            if method not in ("GET", "HEAD"):
                raise HttpError(405, f"{method} {url.path}: only GET", {"Allow": "GET"})
            query = {k: v[-1] for k, v in parse_qs(url.query).items()}
            gzipped = "gzip" in {e.split(";")[0].strip() for e in request.headers.get("accept-encoding", "").split(",")}
            picture = self._pictures.get(url.path)
            if picture is not None:
                snap = await self._shared.snapshot(picture, query, gzipped)
                body, content_type, headers = await self._shared.draw(picture, snap, query, gzipped)
                if snap.read_at is not None:
                    headers = {**headers, READ_AT: f"{snap.read_at:.6f}"}
                return 200, body, content_type, headers
            page = self._pages.get(url.path)
            if page is None:
                raise NotFound(f"not found: Drums serves {', '.join(self._links)}")
            return (200, *await self._in_thread(_drawn, page, query, gzipped))
        except (HttpError, UsageError) as e:  # the API answers in JSON, pages in text
            code, headers = _status(e)
            if in_api:
                return _json(code, {"error": str(e)}, headers)
            return code, f"{e}\n".encode(), TEXT, headers
        except ConnectionError:
            raise  # the client left in the middle of its body: no answer, no news
        except Exception as e:  # a request must never take the agent down
            log.error("%s %s failed: %s", method, url.path, e, exc_info=log.isEnabledFor(logging.DEBUG))
            return 500, f"failed: {e}\n".encode(), TEXT, {}

    async def _in_thread(self, call, *args):
        return await asyncio.get_running_loop().run_in_executor(self._workers, call, *args)

    async def _api(self, request: _Request, method: str, path: str) -> tuple[int, bytes, str, dict]:
        parts = [p for p in path[len(API):].split("/") if p]
        if method not in ("GET", "POST", "DELETE"):
            # Allow names what this resource takes (RFC 9110): the read-only ones take only GET.
            allow = "GET" if parts in READ_ONLY else "GET, POST, DELETE"
            raise HttpError(405, f"{method}: the API takes GET, POST and DELETE", {"Allow": allow})
        if parts in READ_ONLY and method != "GET":  # before the token: no token makes it a method they take
            raise HttpError(405, f"{method} {API}/{parts[0]}: only GET", {"Allow": "GET"})
        authorized = not self._token or self._authorized(request)
        if method != "GET" and not authorized:
            raise HttpError(401, "a valid token is needed: Authorization: Bearer <token>",
                            {"WWW-Authenticate": "Bearer"})
        body = await request.body()
        return _json(*await self._in_thread(self._call, method, parts, body, request.local, authorized))

    def _authorized(self, request: _Request) -> bool:
        scheme, _, value = request.headers.get("authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(value.strip().encode(), self._token.encode())

    def _call(self, method: str, parts: list[str], body: bytes, local: str, authorized: bool) -> tuple[int, object]:
        """(status, JSON value) of a request under /drums/v1 that reached the agent at `local`; the
        stream's key goes only to a caller with the token (or to all, where there is none)."""
        stream = self._stream
        where = {"address": f"tcp://{f'[{local}]' if ':' in local else local}:{stream.port}",
                 "curve_public_key": stream.public_key if authorized else ""} if stream else {}

        def located(job: dict) -> dict:  # the stream as this client can reach it
            job["stream"].update(where)
            return job
        if parts in READ_ONLY:  # GET only (_api said 405 to anything else)
            if parts == ["info"]:
                return 200, dict(self._info(), stream=where)
            if parts == ["openapi.json"]:
                return 200, openapi_document()
            return 200, {"jobs": [located(j) for j in self._jobs.list()]}
        if len(parts) < 2 or parts[0] != "monitor" or parts[1] not in KINDS:
            raise NotFound(f"no such path {API}/{'/'.join(parts)}")
        kind = parts[1]
        target = job_target(kind, parts[2:])
        if method == "GET":
            return 200, located(self._jobs.get(job_id(kind, target)))
        if method == "DELETE":
            self._jobs.remove(job_id(kind, target))
            return 204, None
        try:
            # No body at all: the defaults. Anything else is JSON text, which whitespace alone is not;
            # a JSON null is no object.
            value = json.loads(body) if body else {}
        except (ValueError, UnicodeDecodeError, RecursionError) as e:
            why = "nested too deep" if isinstance(e, RecursionError) else e
            raise UsageError(f"the body is not JSON ({why})") from None
        job, created = self._jobs.add(kind, target, *parse_body(kind, value))
        return (201 if created else 200), located(job)

    async def _send(self, connection: _Connection, code: int, body: bytes, content_type: str, headers: dict,
                    with_body: bool = True) -> bool:
        """Send the answer within SEND_TIMEOUT: whether it went (else the connection is done).
        `with_body` is false for an answer to HEAD, which says the body's length but has none."""
        fields = [("Server", "drums"), *headers.items()]  # not our versions
        if code != 204:
            fields += [("Content-Type", content_type), ("Content-Length", str(len(body)))]
        events = [h11.Response(status_code=code, headers=fields, reason=http.HTTPStatus(code).phrase)]
        if code != 204 and with_body:
            events.append(h11.Data(data=body))
        events.append(h11.EndOfMessage())
        try:
            await asyncio.wait_for(connection.send(*events), SEND_TIMEOUT)
        except asyncio.TimeoutError:
            self._server.count_closed("slow_reader")
            connection.writer.transport.abort()
            return False
        except ConnectionError:
            return False  # the client hung up before the answer: no news
        return True


def _check_head(request: h11.Request) -> None:
    """h11 bounds a head that arrives in parts (max_incomplete_event_size); one that came whole in a
    read is bounded here, and so are its header lines."""
    if len(request.headers) > MAX_HEADERS:
        raise h11.RemoteProtocolError(f"more than {MAX_HEADERS} header lines", 431)
    if len(request.target) + sum(len(name) + len(value) for name, value in request.headers) > MAX_HEAD:
        raise h11.RemoteProtocolError(f"a request head over {MAX_HEAD >> 10} KiB", 431)


def _json(code: int, value, headers: dict | None = None) -> tuple[int, bytes, str, dict]:
    return code, b"" if code == 204 else json.dumps(value).encode() + b"\n", JSON, headers or {}
