"""The sample stream, the paper's push channel: a ZeroMQ PUB socket on which the agent publishes
every sample of every job as msgpack.

Each message is two frames: the key `<host>:<kind>:<target>` (a subscriber filters by prefix, so
"robot1:" takes one host and "robot1:pid:" its process jobs) and the payload, a map:

    seq     1, 2, 3 ... per key: a gap, or a first seq above 1, says what the subscriber missed
    time    when the sample was taken (Unix seconds)
    layout  an id for the list of series the values belong to
    series  [[name, {label: value}], ...]: only when the layout is new and every KEYFRAME messages
    values  one value per series, in layout order; a histogram as [count, sum, [[upper bound,
            cumulative count], ...]], its buckets as on /metrics

Labels are most of a sample's bytes and rarely change, so they travel only with a new layout and
in a periodic keyframe for subscribers that joined late; the messages between carry numbers only.

Off loopback the socket uses CURVE, and only subscribers that hold the API token get in: the agent
makes a key pair when first asked for it and gives its public key to callers with the token (in
/drums/v1/info and in every job); a subscriber encrypts to it with the client key pair derived
from the token (`client_keys`), the one client key the agent allows. Without the token there is
neither key.

ZeroMQ is loaded at the first sample, not at start: an agent whose job API nobody uses (one that
Prometheus scrapes) never holds it, 1.5 to 2.5 MB of its memory and two threads. Until then the
port is held by a listening socket that accepts nobody; a subscriber that connected to it is reset
when ZeroMQ takes the port over, and connects again by itself (ZeroMQ retries every 100 ms).
"""
from __future__ import annotations

import hashlib
import hmac
import logging
import socket
import threading
import time

import msgpack

from drums.errors import DrumsError

KEYFRAME = 10  # a late subscriber decodes from at most this many messages on
REFUSED_SAID_EVERY = 60.0  # seconds: at most one line about subscribers refused

log = logging.getLogger("drums")


def client_keys(token: str) -> tuple[bytes, bytes]:
    """The stream's client CURVE key pair (public, secret; Z85) for an API token: whoever holds the
    token can make it, nobody else can."""
    import zmq
    from zmq.utils import z85

    secret = z85.encode(hashlib.sha256(b"drums stream client\0" + token.encode()).digest())
    return zmq.curve_public(secret), secret


def layout_id(series: list) -> int:
    """A stable id of a list of [name, labels]: the same series in another run get the same id."""
    return int.from_bytes(hashlib.blake2b(msgpack.packb(series), digest_size=8).digest(), "little")


class Stream:
    """Owned by one thread (ZeroMQ sockets are not thread-safe): the jobs thread publishes."""

    def __init__(self, address: str, port: int, curve: bool, token: str = ""):
        """With `curve`, subscribers must hold `token` (see client_keys)."""
        self._address, self._curve, self._token = address, curve, token
        self._context = self.socket = self._auth = None
        self._keys: tuple[str, bytes] | None = None  # the server's CURVE key pair, made when first asked for
        self._keys_lock = threading.Lock()
        self._failed = False
        try:
            family, kind, proto, _, where = socket.getaddrinfo(address, port, type=socket.SOCK_STREAM,
                                                                flags=socket.AI_PASSIVE)[0]
            self._held = socket.socket(family, kind, proto)
            self._held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as ZeroMQ binds
            self._held.bind(where)
            self._held.listen(1)
        except OSError as e:
            raise DrumsError(f"cannot publish the stream on {address}:{port}: {e.strerror or e}") from None
        self.port = self._held.getsockname()[1]
        self._seq: dict[str, int] = {}
        self._layout: dict[str, tuple[list, int]] = {}  # key -> (series, its id)

    @property
    def public_key(self) -> str:
        """The server's CURVE public key (Z85), "" without CURVE."""
        return self._key_pair()[0] if self._curve else ""

    def _key_pair(self) -> tuple[str, bytes]:
        """Made when first asked for: by a caller of the API (an HTTP thread) or the first sample."""
        with self._keys_lock:
            if self._keys is None:
                import zmq

                public, secret = zmq.curve_keypair()
                self._keys = public.decode(), secret
            return self._keys

    def _open(self) -> bool:
        """The ZeroMQ socket, made at the first sample in place of the socket that held the port."""
        if self.socket is not None or self._failed:
            return not self._failed
        import zmq

        self._context = zmq.Context()
        self.socket = self._context.socket(zmq.PUB)
        self.socket.linger = 0
        if self._curve:
            from zmq.auth.thread import ThreadAuthenticator

            self._allowed, self._refused, self._said = client_keys(self._token)[0], 0, 0.0
            self._auth = ThreadAuthenticator(self._context, log=logging.getLogger("drums.stream.zap"))
            self._auth.start()
            self._auth.configure_curve_callback("*", credentials_provider=self)
            self.socket.curve_server = True
            self.socket.curve_secretkey = self._key_pair()[1]
        self._held.close()
        host = f"[{self._address}]" if ":" in self._address else self._address
        try:
            self.socket.bind(f"tcp://{host}:{self.port}")
        except zmq.ZMQError as e:  # the port was taken in the instant it was free: samples stay in the API
            self._failed = True
            log.error("cannot publish the stream on %s:%d: %s; job samples are in the API only",
                      self._address, self.port, e.strerror)
        return not self._failed

    def callback(self, _domain: str, client_key: bytes) -> bool:
        """ZeroMQ's authenticator asks whether a subscriber's key may in: only the token's."""
        if hmac.compare_digest(client_key, self._allowed):
            return True
        self._refused += 1
        now = time.monotonic()
        if now - self._said >= REFUSED_SAID_EVERY:
            self._said = now
            log.warning("stream: refused %d subscriber(s) without the token's key since start (said at most "
                        "once a minute)", self._refused)
        return False

    def publish(self, key: str, time: float, rows: list[dict]) -> None:
        """Publish one sample of `key`: rows of {"name", "labels", "value"}."""
        if not self._open():
            return
        series = [[r["name"], r["labels"]] for r in rows]
        seq = self._seq.get(key, 0) + 1
        self._seq[key] = seq
        known, layout = self._layout.get(key, (None, 0))
        message = {"seq": seq, "time": time}
        if series != known:
            layout = layout_id(series)
            self._layout[key] = (series, layout)
        if series != known or seq % KEYFRAME == 1:
            message["series"] = series
        message["layout"] = layout
        message["values"] = [[v["count"], v["sum"], v["buckets"]] if isinstance(v, dict) else v
                             for v in (r["value"] for r in rows)]
        self.socket.send_multipart([key.encode(), msgpack.packb(message)])

    def forget(self, key: str) -> None:
        """A job was deleted: if it comes back, its sequence starts again at 1."""
        self._seq.pop(key, None)
        self._layout.pop(key, None)

    def close(self) -> None:
        self._held.close()
        if self.socket is not None:
            self.socket.close()
        if self._auth is not None:
            self._auth.stop()
        if self._context is not None:
            self._context.term()
