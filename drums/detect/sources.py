"""Where the detector's numbers come from: the /metrics page of each agent, or a Prometheus server
that scrapes a whole fleet. Each read gives a Reading: every watched series of one host at one
instant, the families that are counters, and the host's nodes with their processes.
"""
from __future__ import annotations

import json
import time
import urllib.parse
from dataclasses import dataclass, field

from drums.client import Agent, AgentError
from drums import exposition
from drums.detect.series import watched
from drums.errors import DrumsError

NODE_INFO = "drums_node_info"
STARTED = "drums_process_start_time_seconds"  # tells a node that started just before the detector did
COUNTER_SUFFIXES = ("_total", "_count", "_sum")  # a histogram's count and sum are counters too


class SourceError(DrumsError):
    """A source that did not answer, or answered with something that is not metrics."""


@dataclass
class Reading:
    source: str  # the host
    time: float
    series: dict[str, float] = field(default_factory=dict)  # series text -> value
    counters: set[str] = field(default_factory=set)  # names of counter families
    nodes: dict[str, str] = field(default_factory=dict)  # node -> pid
    started: dict[str, float] = field(default_factory=dict)  # pid -> when its process started (Unix s)


def parse_exposition(source: str, at: float, text: str, detail: bool = False) -> Reading:
    """A Reading of a Prometheus text page (the agent's own: no timestamps, one value per line);
    `detail`: with the per-thread and per-socket series."""
    reading = Reading(source, at)
    for family, kind in exposition.types(text).items():
        if kind == "counter":
            reading.counters.add(family)
        elif kind == "histogram":
            reading.counters.update((family + "_count", family + "_sum"))
    try:
        _read_samples(reading, text, detail)
    except ValueError as e:
        raise SourceError(f"{source}: /metrics is not Prometheus text: {e}") from None
    return reading


def _read_samples(reading: Reading, text: str, detail: bool) -> None:
    verdict: dict[str, bool] = {}  # family -> watched
    for name, series, value in exposition.samples(text):
        if name == NODE_INFO:
            labels = exposition.labels(series)
            if labels.get("node") and labels.get("pid"):
                reading.nodes[labels["node"]] = labels["pid"]
            continue
        if name == STARTED:
            pid = exposition.labels(series).get("pid")
            if pid:
                reading.started[pid] = float(value)
            continue
        ok = verdict.get(name)
        if ok is None:
            ok = verdict[name] = watched(name, detail)
        if ok:
            reading.series[series] = float(value)


class AgentSource:
    """One agent's /metrics, named by the host name the agent gives (asked at the first read), else
    by its address."""

    def __init__(self, url: str, token: str = "", detail: bool = False, timeout: float = 5.0):
        self.agent = Agent(url, token, timeout)
        self.detail = detail
        self.address = urllib.parse.urlsplit(self.agent.url).netloc
        self.name = ""

    def read(self) -> list[Reading]:
        try:
            if not self.name:
                self.name = str(self.agent.info().get("host") or self.address)
            text, at = self.agent.read("/metrics")
        except AgentError as e:
            raise SourceError(str(e)) from None
        return [parse_exposition(self.name, at, text, self.detail)]


class PrometheusSource:
    """Every drums_ series a Prometheus server holds, by instant query: a Reading per host (its
    `host` label, else its `instance`)."""

    QUERY = '{__name__=~"drums_.+",__name__!~".+_bucket"}'

    def __init__(self, url: str, detail: bool = False, timeout: float = 10.0):
        self.url = url.rstrip("/")
        self.detail = detail
        self.timeout = timeout
        self.address = self.name = urllib.parse.urlsplit(self.url).netloc

    def read(self) -> list[Reading]:
        import urllib.request
        at = time.time()
        query = urllib.parse.urlencode({"query": self.QUERY, "time": f"{at:.3f}"})
        try:
            with urllib.request.urlopen(f"{self.url}/api/v1/query?{query}", timeout=self.timeout) as answer:
                body = json.load(answer)
            results = body["data"]["result"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SourceError(f"{self.url}: no answer to the query ({e})") from None
        try:
            return self._readings(results)
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise SourceError(f"{self.url}: the query's answer is not Prometheus's vector ({e!r})") from None

    def _readings(self, results: list) -> list[Reading]:
        readings: dict[str, Reading] = {}
        for result in results:
            labels = dict(result["metric"])
            name = labels.pop("__name__")
            host = labels.pop("host", None) or labels.get("instance", self.name)
            labels.pop("job", None)
            labels.pop("instance", None)
            reading = readings.get(host)
            if reading is None:
                reading = readings[host] = Reading(host, 0.0)
            # When the server scraped it: a rate is over the scrapes, not over our reads of them.
            reading.time = max(reading.time, float(result["value"][0]))
            if name == NODE_INFO:
                if labels.get("node") and labels.get("pid"):
                    reading.nodes[labels["node"]] = labels["pid"]
                continue
            if name == STARTED:
                if labels.get("pid"):
                    reading.started[labels["pid"]] = float(result["value"][1])
                continue
            if not watched(name, self.detail):
                continue
            if name.endswith(COUNTER_SUFFIXES):
                reading.counters.add(name)
            text = name + "{" + ",".join(f'{k}="{_escaped(v)}"' for k, v in sorted(labels.items())) + "}"
            reading.series[text] = float(result["value"][1])
        return list(readings.values())


def _escaped(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
