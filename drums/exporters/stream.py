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
makes a key pair at start and gives its public key to callers with the token (in /drums/v1/info and
in every job); a subscriber encrypts to it with the client key pair derived from the token
(`client_keys`), the one client key the agent allows. Without the token there is neither key.
"""
from __future__ import annotations

import hashlib
import hmac
import logging
import time

import msgpack
import zmq
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils import z85

from drums.errors import DrumsError

KEYFRAME = 10  # a late subscriber decodes from at most this many messages on
REFUSED_SAID_EVERY = 60.0  # seconds: at most one line about subscribers refused

log = logging.getLogger("drums")


def client_keys(token: str) -> tuple[bytes, bytes]:
    """The stream's client CURVE key pair (public, secret; Z85) for an API token: whoever holds the
    token can make it, nobody else can."""
    secret = z85.encode(hashlib.sha256(b"drums stream client\0" + token.encode()).digest())
    return zmq.curve_public(secret), secret


def layout_id(series: list) -> int:
    """A stable id of a list of [name, labels]: the same series in another run get the same id."""
    return int.from_bytes(hashlib.blake2b(msgpack.packb(series), digest_size=8).digest(), "little")


class Stream:
    """Owned by one thread (ZeroMQ sockets are not thread-safe): the jobs thread publishes."""

    def __init__(self, address: str, port: int, curve: bool, token: str = ""):
        """With `curve`, subscribers must hold `token` (see client_keys)."""
        self._context = zmq.Context()
        self.socket = self._context.socket(zmq.PUB)
        self.socket.linger = 0
        self.public_key = ""
        self._auth = None
        if curve:
            self._allowed, self._refused, self._said = client_keys(token)[0], 0, 0.0
            self._auth = ThreadAuthenticator(self._context, log=logging.getLogger("drums.stream.zap"))
            self._auth.start()
            self._auth.configure_curve_callback("*", credentials_provider=self)
            public, secret = zmq.curve_keypair()
            self.socket.curve_server = True
            self.socket.curve_secretkey = secret
            self.public_key = public.decode()
        host = f"[{address}]" if ":" in address else address
        try:
            self.socket.bind(f"tcp://{host}:{port}")
        except zmq.ZMQError as e:
            self.close()
            raise DrumsError(f"cannot publish the stream on {address}:{port}: {e.strerror}") from None
        self.port = int(self.socket.last_endpoint.decode().rsplit(":", 1)[1])
        self._seq: dict[str, int] = {}
        self._layout: dict[str, tuple[list, int]] = {}  # key -> (series, its id)

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
        self.socket.close()
        if self._auth is not None:
            self._auth.stop()
        self._context.term()
