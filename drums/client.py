"""The client library: jobs on many agents, their streams merged into one live view, and their
graphs merged into one graph of the whole system.

    from drums.client import Client
    with Client(["http://robot1:9969", "http://base:9969"], token="...") as c:
        c.start("host")                      # a host job on every agent
        c.start("pid", "4242", agent=c.agents[0])
        c.keep("host", lease=10)              # used if running, else made; c.renew() within 10 s
        while True:
            for sample in c.poll(1.0):        # decoded stream messages as they arrive
                print(sample.key, sample.missed, sample.series)
            c.view                            # the latest sample of every key

A sample knows what its subscriber missed: `missed` counts the messages between it and the one
before it on the same key (sequence numbers), `late` that the subscriber joined after the first.
"""
from __future__ import annotations

import json
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import msgpack
import zmq

from drums.errors import DrumsError, UsageError
from drums.exporters import READ_AT
from drums.exporters.stream import client_keys, layout_id

if TYPE_CHECKING:
    import networkx as nx


class AgentError(DrumsError):
    """An agent did not answer, or refused a request (its reason is in the message)."""

    def __init__(self, message: str, status: int | None = None):
        super().__init__(message)
        self.status = status  # the HTTP status of a refusal; None if the agent was not reached


@dataclass
class Sample:
    key: str  # <host>:<kind>:<target>
    seq: int
    time: float
    series: dict[tuple[str, tuple[tuple[str, str], ...]], object]  # (name, sorted labels) -> value
    missed: int = 0  # messages of this key lost between the previous sample and this one
    late: bool = False  # the first sample this subscriber got, and not the key's first

    def value(self, name: str, **labels: str):
        """The value of the first series of `name` that has these labels (it may have more), or None."""
        wanted = set(labels.items())
        return next((v for (n, ls), v in self.series.items() if n == name and wanted <= set(ls)), None)


class Agent:
    """One agent's HTTP API."""

    def __init__(self, url: str, token: str = "", timeout: float = 10):
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout

    def __repr__(self) -> str:
        return f"Agent({self.url!r})"

    def request(self, method: str, path: str, body: dict | None = None):
        """The JSON answer of /drums/v1/<path>, or an AgentError with the agent's reason."""
        return self.call(method, path, body)[1]

    def call(self, method: str, path: str, body: dict | None = None) -> tuple[int, object]:
        """(status, JSON answer) of /drums/v1/<path>, or an AgentError with the agent's reason."""
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(f"{self.url}/drums/v1/{path}", data=data, method=method)
        if data is not None:
            request.add_header("Content-Type", "application/json")
        if self.token:
            request.add_header("Authorization", f"Bearer {self.token}")
        status, text, _ = self._open(request, f"{method} {path}: ")
        return status, json.loads(text) if text else None

    def page(self, path: str) -> str:
        """One of the agent's pages (e.g. "/graph?format=dot") as text."""
        return self.read(path)[0]

    def read(self, path: str) -> tuple[str, float]:
        """(text, when its counters were read) of /metrics or /graph: the agent's time, else (an
        older agent) the middle of the request."""
        began = time.time()
        _, body, headers = self._open(urllib.request.Request(self.url + path))
        try:
            at = float(headers.get(READ_AT) or "")
        except ValueError:
            at = (began + time.time()) / 2
        return body.decode(), at

    def _open(self, request: urllib.request.Request, what: str = "") -> tuple[int, bytes, dict]:
        """(status, body, headers) of a request to the agent; an AgentError says why not: the
        agent's reason for a 4xx or 5xx (JSON from the API, text from a page), or why it was not
        reached."""
        try:
            with urllib.request.urlopen(request, timeout=self.timeout) as reply:
                return reply.status, reply.read(), reply.headers
        except urllib.error.HTTPError as e:
            body = e.read().decode(errors="replace").strip()
            try:
                reason = json.loads(body)["error"]
            except (ValueError, KeyError, TypeError):
                reason = body or e.reason
            raise AgentError(f"{self.url}: {what}{e.code} {reason}", e.code) from None
        except (urllib.error.URLError, OSError, ValueError) as e:  # ValueError: not an http URL
            reason = getattr(e, "reason", e)
            raise AgentError(f"{self.url}: {getattr(reason, 'strerror', None) or reason}") from None

    def info(self) -> dict:
        return self.request("GET", "info")

    def start(self, kind: str, target: str = "", **settings) -> dict:
        return self.create(kind, target, **settings)[0]

    def create(self, kind: str, target: str = "", **settings) -> tuple[dict, bool]:
        """(the job, whether this call created it rather than found it)."""
        status, job = self.call("POST", _path(kind, target), settings)
        return job, status == 201

    def stop(self, kind: str, target: str = "") -> None:
        self.request("DELETE", _path(kind, target))

    def job(self, kind: str, target: str = "") -> dict:
        return self.request("GET", _path(kind, target))

    def jobs(self) -> list[dict]:
        return self.request("GET", "jobs")["jobs"]

    def graph(self) -> nx.MultiDiGraph:
        """The agent's graph with its metrics (its /graph)."""
        import networkx as nx  # only here: the detector and the stream's clients do without it
        try:
            return nx.node_link_graph(json.loads(self.page("/graph?format=json")), edges="edges")
        except (ValueError, KeyError, TypeError) as e:
            raise AgentError(f"{self.url}: /graph is not a graph in JSON ({e})") from None


def _path(kind: str, target: str) -> str:
    return f"monitor/{kind}/{target}" if target else f"monitor/{kind}"


@dataclass
class _Key:
    """What a subscriber remembers of one stream key."""

    seq: int = 0  # the last one received
    first: int = 0  # the first one received
    decoded: bool = False
    layouts: dict[int, list] = field(default_factory=dict)


class Client:
    """Jobs on many agents and one subscriber to all their streams."""

    def __init__(self, urls: list[str], token: str = ""):
        if not urls:
            raise UsageError("a client needs at least one agent URL")
        for url in urls:
            parts = urllib.parse.urlsplit(url)
            if parts.scheme not in ("http", "https") or not parts.hostname:
                raise UsageError(f"--agent {url}: an agent's URL is http://HOST:PORT")
        self.agents = [Agent(u, token) for u in urls]
        self.token = token  # which also opens the agents' streams off loopback
        self.view: dict[str, Sample] = {}  # key -> its latest sample
        self.undecodable = 0  # messages that came before their layout (a late subscriber's first few)
        self._context = zmq.Context()
        self._sockets: dict[str, zmq.Socket] = {}  # stream address -> SUB socket
        self._poller = zmq.Poller()
        self._keys: dict[str, _Key] = {}
        # The jobs this client made, with the settings they were made with: renew() asks for them
        # again (which renews their leases), stop_all() deletes them.
        self._created: dict[tuple[Agent, str, str], dict] = {}

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def start(self, kind: str, target: str = "", agent: Agent | None = None, **settings) -> list[dict]:
        """Start a job on `agent` (default: every agent) and subscribe to its samples."""
        jobs = []
        for a in [agent] if agent else self.agents:
            job, created = self._create(a, kind, target, settings)
            if created:
                self._created[a, kind, target] = settings
            self._follow(job)
            jobs.append(job)
        return jobs

    def keep(self, kind: str, target: str = "", agent: Agent | None = None, **settings) -> dict:
        """Have a job run on `agent` (default: the first) and subscribe to it. A job this client
        made is asked for again, which renews its lease (and makes it again if it had ended); one
        that someone else runs is used as it is, untouched, since its owner renews and ends it;
        where there is none, this client makes one with `settings` (with a lease: keep or renew it
        again within the lease)."""
        agent = agent or self.agents[0]
        made = self._created.get((agent, kind, target))
        if made is None:
            try:
                job = agent.job(kind, target)
                self._follow(job)
                return job
            except AgentError as e:
                if e.status != 404:
                    raise
        settings = made if made is not None else settings
        job, _ = self._create(agent, kind, target, settings)
        self._created[agent, kind, target] = settings
        self._follow(job)  # an agent that restarted may stream from another port
        return job

    def _create(self, agent: Agent, kind: str, target: str, settings: dict) -> tuple[dict, bool]:
        """POST a job, subscribed to its key beforehand: its first sample, sent at once, is the one
        that names its series, and a subscriber that misses it decodes nothing until the next
        keyframe, ten samples later."""
        info = agent.info()
        if info.get("stream"):
            self.subscribe({**info["stream"], "key": f"{info['host']}:{kind}:{target}"})
        return agent.create(kind, target, **settings)

    def renew(self) -> list[AgentError]:
        """Ask again for every job this client made, which renews their leases; the errors of
        agents that did not answer (their jobs are asked for again at the next renew)."""
        errors = []
        for agent, kind, target in list(self._created):
            try:
                self.keep(kind, target, agent)
            except AgentError as e:
                errors.append(e)
        return errors

    def release(self, kind: str, target: str = "", agent: Agent | None = None) -> None:
        """No longer need a job: deleted if this client made it (an agent that does not answer
        lets its lease end it), left alone if someone else runs it."""
        agent = agent or self.agents[0]
        if self._created.pop((agent, kind, target), None) is not None:
            try:
                agent.stop(kind, target)
            except AgentError:
                pass

    def stop(self, kind: str, target: str = "", agent: Agent | None = None) -> None:
        for a in [agent] if agent else self.agents:
            a.stop(kind, target)
            self._created.pop((a, kind, target), None)

    def stop_all(self) -> None:
        """Delete the jobs this client created (not those it found running); an agent that has
        gone away meanwhile is passed over (their leases, if any, end them)."""
        for agent, kind, target in self._created:
            try:
                agent.stop(kind, target)
            except AgentError:
                pass
        self._created = {}

    def subscribe(self, stream: dict) -> None:
        """Receive the messages of one stream key ({"address", "key", "curve_public_key"}, as a
        job names its stream)."""
        sock = self._sockets.get(stream["address"])
        if sock is None:
            sock = self._context.socket(zmq.SUB)
            sock.linger = 0
            if stream.get("curve_public_key"):
                sock.curve_publickey, sock.curve_secretkey = client_keys(self.token)
                sock.curve_serverkey = stream["curve_public_key"].encode()
            sock.connect(stream["address"])
            self._sockets[stream["address"]] = sock
            self._poller.register(sock, zmq.POLLIN)
        # ZeroMQ filters by prefix; "h:pid:12" would also take "h:pid:123": poll() keeps exact keys.
        sock.setsockopt(zmq.SUBSCRIBE, stream["key"].encode())
        self._keys.setdefault(stream["key"], _Key())

    def _follow(self, job: dict) -> None:
        """Subscribe to a job's key, and learn the names of its series from its latest sample (the
        API's rows are in the stream's order): its messages decode at once, not from the next
        keyframe on."""
        self.subscribe(job["stream"])
        if job.get("sample"):
            series = [[row["name"], row["labels"]] for row in job["sample"]["series"]]
            self._keys[job["stream"]["key"]].layouts.setdefault(layout_id(series), series)

    def unsubscribe(self, stream: dict) -> None:
        """Stop receiving a key; what it sends meanwhile counts as missed when it is subscribed again."""
        self._sockets[stream["address"]].setsockopt(zmq.UNSUBSCRIBE, stream["key"].encode())

    def poll(self, timeout: float) -> list[Sample]:
        """The samples that arrive within `timeout` s (at least one wait; all that are queued)."""
        out = []
        if not self._sockets:  # zmq would return at once: wait as asked, there is nothing to get
            time.sleep(timeout)
            return out
        ready = dict(self._poller.poll(timeout * 1000))
        while ready:
            for sock in ready:
                key, payload = sock.recv_multipart()
                sample = self._decode(key.decode(errors="replace"), payload)
                if sample is not None:
                    out.append(sample)
            ready = dict(self._poller.poll(0))
        return out

    def _decode(self, key: str, payload: bytes) -> Sample | None:
        known = self._keys.get(key)
        if known is None:
            return None  # a longer key that shares a subscribed prefix
        message = msgpack.unpackb(payload)
        seq = message["seq"]
        missed = 0 if not known.seq or seq <= known.seq else seq - known.seq - 1  # lower: the job began again
        known.seq, known.first = seq, known.first or seq
        if "series" in message:
            known.layouts = {message["layout"]: message["series"]}
        series = known.layouts.get(message["layout"])
        if series is None:
            self.undecodable += 1
            return None
        values = {(name, tuple(sorted(labels.items()))): value for (name, labels), value in zip(series, message["values"])}
        sample = Sample(key, seq, message["time"], values, missed, late=not known.decoded and known.first > 1)
        known.decoded = True
        self.view[key] = sample
        return sample

    def graph(self) -> nx.MultiDiGraph:
        """One graph of the whole system from every agent's graph. Each agent knows the nodes of its
        own host (with their process and metrics) and sees the others only through the middleware:
        a node's attributes come from the agent whose host it is on; an edge's metrics from every
        agent that measured one end of it."""
        import networkx as nx
        merged = nx.MultiDiGraph()
        for agent in self.agents:
            g = agent.graph()
            for vid, data in g.nodes(data=True):
                if vid not in merged:
                    merged.add_node(vid, **data)
                elif data.get("kind") != "node" or data.get("host"):  # the node's own agent knows it best
                    merged.nodes[vid].update(data)
            for u, v, key, data in g.edges(keys=True, data=True):
                if merged.has_edge(u, v, key):
                    merged.edges[u, v, key].update(data)
                else:
                    merged.add_edge(u, v, key=key, **data)
        return merged

    def watch_nodes(self, interval: float = 1.0) -> dict[str, dict]:
        """A process job for every node of the whole graph, on the agent of the node's own host
        (what the paper's ROS adapter did); node name -> its job. Nodes that share a process
        share its job."""
        by_host = {agent.info()["host"]: agent for agent in self.agents}
        jobs = {}
        for _, d in self.graph().nodes(data=True):
            if d["kind"] == "node" and d.get("pid") and d.get("host") in by_host:
                jobs[d["name"]], = self.start("pid", str(d["pid"]), agent=by_host[d["host"]], interval=interval)
        return jobs

    def close(self) -> None:
        for sock in self._sockets.values():
            sock.close()
        self._context.term()
