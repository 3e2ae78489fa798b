"""The channels: one per node (and process that holds none), topic, edge and host of the agents,
named /drums/<view>/<host>/<name>, each message a row of `drums top`'s view of that name with
its values in base units (cpu_percent, published_hz, age_p99_seconds, ...), under a JSON schema
made from the view's columns; and /drums/anomalies, the anomalies of a `drums detect` as
foxglove.Log messages, each once, when it starts.

Stamped with the agent's clock (when it read the counters), so that a recording lines up with a
rosbag2 MCAP of the same robot.
"""
from __future__ import annotations

import signal
import threading
from dataclasses import dataclass, field
from typing import Callable

from drums.top.collector import Collector
from drums.top.model import Frame
from drums.top.screen import Views
from drums.top.table import Table

VIEWS = ("nodes", "topics", "edges", "hosts")
ANOMALIES = "/drums/anomalies"
IDLE = 60.0  # seconds without a message after which a channel is closed (its process ended, its edge went)


def topic(view: str, key: str) -> str:
    """A row's channel: its view and its key's parts (host, name, ...) as a path."""
    parts = [p.strip("/") for p in key.split("|")[1:]]
    return "/".join([f"/drums/{view}", *(p for p in parts if p)])


def schema(table: Table) -> dict:
    """A JSON schema of the view's rows: a name is a string, any other value a number; either may
    be unknown (null) while a rate needs a second poll."""
    return {"type": "object", "title": f"drums.{table.view}",
            "properties": {c.key: {"type": ["string" if c.name else "number", "null"]} for c in table.columns}}


@dataclass
class Message:
    topic: str
    schema: dict
    value: dict
    at_ns: int


@dataclass
class Channels:
    """Turns frames into messages: each row once per poll of its agent, each anomaly once."""

    views: Views = field(default_factory=Views)
    _polled: dict = field(default_factory=dict)  # agent's host -> the time of its poll last turned into messages
    _said: set = field(default_factory=set)  # the anomalies logged

    def messages(self, frame: Frame) -> list[Message]:
        # When each agent read the graph's counters, of which most rates are made.
        polled = {a.host: a.latest.graph_at for a in frame.live() if a.before is not None}
        fresh = {host for host, at in polled.items() if self._polled.get(host) != at}
        self._polled.update(polled)
        latest = max((polled[h] for h in fresh), default=frame.at)  # for rows of no one host (topics, edges)
        out = []
        for view in VIEWS if fresh else ():
            table = self.views.table(frame, view)
            shape = schema(table)
            keys = [c.key for c in table.columns]
            for row in table.rows:
                host = row.values.get("host")
                if host not in fresh and not (host is None and fresh):
                    continue  # a row of an agent that has not polled since, or of a host no agent watches
                at = polled.get(host, latest)
                out.append(Message(topic(view, row.key), shape, {k: row.values.get(k) for k in keys}, int(at * 1e9)))
        out.extend(self._anomalies(frame))
        return out

    def _anomalies(self, frame: Frame) -> list[Message]:
        """The anomalies that started since the last frame, as the fields of foxglove.Log messages
        (a Message without a schema is one)."""
        out, now = [], set()
        for incident in (frame.anomalies or {}).get("incidents", []):
            for e in incident["entities"]:
                entity = e["entity"]
                for a in e["anomalies"]:
                    key = (entity["host"], a["series"], a["start"])
                    now.add(key)
                    if key in self._said:
                        continue
                    text = a.get("text") or f"{entity['kind']} {entity['name']}: {a['what']} {a['change']}"
                    out.append(Message(ANOMALIES, {}, {"timestamp": a["start"], "level": "Warning", "message": text,
                                                       "name": entity["host"]}, int(a["start"] * 1e9)))
        if frame.anomalies is not None:
            self._said = now  # those the detector no longer lists are done: what is said is bounded
        return out


def follow(collector: Collector, context, interval: float, each: Callable[[Frame], None] = lambda frame: None) -> None:
    """Log the channels of each frame of top's model (the collector's, started here and closed at the
    end) into a Foxglove context (whose sinks are an MCAP file, a WebSocket server) until SIGINT or
    SIGTERM; `each` also sees every frame."""
    import foxglove
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    channels, made = Channels(), {}  # topic -> (its channel, when it last logged)
    collector.start()
    try:
        while not stop.wait(min(interval, 0.2)):
            frame = collector.model.frame()
            each(frame)
            for m in channels.messages(frame):
                channel = made[m.topic][0] if m.topic in made else (
                    foxglove.Channel(m.topic, schema=m.schema, message_encoding="json", context=context)
                    if m.schema else foxglove.channels.LogChannel(m.topic, context=context))
                channel.log(m.value if m.schema else log_message(m.value), log_time=m.at_ns)
                made[m.topic] = channel, frame.at
            for topic_, (channel, at) in list(made.items()):
                if frame.at - at > max(IDLE, 3 * interval):
                    channel.close()
                    del made[topic_]
    finally:
        collector.close()


def log_message(fields: dict):
    from foxglove.messages import Log, LogLevel, Timestamp
    return Log(timestamp=Timestamp.from_epoch_secs(fields["timestamp"]), level=getattr(LogLevel, fields["level"]),
               message=fields["message"], name=fields["name"])
