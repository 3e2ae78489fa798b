"""The agent process, assembled: the probes and the graph's adapter (where data enters), the
agent that joins them (drums.agent), and what serves it (exporters: HTTP, jobs, stream,
/diagnostics). `drums agent` parses its flags and calls run()."""
from __future__ import annotations

import faulthandler
import gc
import os
import logging
import signal
import socket
import threading
import time
from urllib.parse import urlsplit

from drums.netfmt import is_loopback

log = logging.getLogger("drums")


def run(args, token: str) -> int:
    """The agent, as `drums agent` ARGS asks: until SIGINT or SIGTERM."""
    from drums.selfcost import on_first_use, without_openssl
    without_openssl()
    # The ping mesh's icmplib and the stream's msgpack: 0.35 MB held by an agent that runs neither.
    on_first_use("icmplib", "msgpack")
    from drums.agent import Agent, Selection
    from drums.budget import Budget
    from drums.exporters import prometheus
    from drums.exporters.http import HttpServer
    from drums.exporters.jobs import Jobs
    from drums.exporters import health
    from drums.exporters.stream import Stream
    from drums.graph import registry
    from drums.graph.adapter import Follower
    from drums.graph.draw import Rates
    from drums.graph.export import document
    from drums.graph.model import Graph
    from drums.kernel import pinlock
    from drums.kernel.features import Features
    from drums.probes.latency import TCP_PORT
    from drums.probes.registry import PROBES, ROS2_PROBES, build
    from drums.proctable import OWN_NETNS, ProcessTable

    logging.basicConfig(level=args.log_level.upper(), format="drums: %(message)s")
    if args.own_netns:
        os.environ[OWN_NETNS] = "1"  # for the process table, here and in the graph reader child
    selection = Selection.parse(args.pid, args.process_name, args.cgroup)
    diagnostics = None
    if args.diagnostics or args.diagnostics_config:  # only then: it loads YAML (20 ms of a start)
        from drums.exporters.diagnostics import Diagnostics, load_config
        diagnostics = Diagnostics(load_config(args.diagnostics_config))
    adapter_name = args.graph or registry.default()
    adapter = registry.build(adapter_name, args.graph_file, announcement(args))
    if diagnostics and adapter_name == "ros2":
        diagnostics.publisher.ride(adapter)  # one rclpy child, one DDS participant, for both
    default = [p for p in PROBES if adapter_name == "ros2" or p not in ROS2_PROBES]
    names = [p for p in (args.probe or default) if p not in args.no_probe]
    proctable = ProcessTable()
    features = Features(args.btf or "")
    probes = build(features, proctable, names, args.pin_dir, args.ros_timing, dict(args.attach),
                   args.splice_tracepoints)
    pins = pinlock.hold(args.pin_dir)  # held while the agent runs
    budget = Budget({"process": args.max_processes, "thread": args.max_threads,
                     "socket": args.max_sockets, "connection": args.max_connections})
    graph = Graph()
    follower = Follower(adapter, graph)
    agent = Agent(probes, proctable, selection, budget, graph, adapter_name)
    adapter.hear_from(agent.tcp_changes, proctable.cpu_seconds)
    done = threading.Event()  # set by SIGINT or SIGTERM, even while the probes are still loading
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    faulthandler.register(signal.SIGUSR2, all_threads=True)  # kill -USR2: what each thread is doing, to the log
    host = socket.gethostname()
    latency = next((p for p in probes if p.name == "latency"), None)

    def agent_port(url: str) -> int:  # as another host's agent announced it; a port it may not be is none
        try:
            return urlsplit(url).port or TCP_PORT
        except ValueError:
            return TCP_PORT

    def mesh() -> dict[str, int]:  # the other hosts of the graph, where they are reached: their agents' ports
        return {h.address or h.name: agent_port(h.agent) for h in graph.entities("host") if h.name != host}

    def latency_targets() -> set[str]:  # the graph's hosts by name or address, and the operator's
        return {t for h in graph.entities("host") for t in (h.name, h.address) if t} | set(args.latency_target)
    stream = Stream(args.address, args.stream_port, curve=not is_loopback(args.address), token=token)
    jobs = Jobs(agent.collect_raw, host, stream, latency, latency_targets, mesh if args.latency_mesh else None,
                lambda: {t.name for t in graph.entities("topic")})
    agent.wanted_pids = jobs.pids

    def info() -> dict:
        return {"host": host, "time": time.time(), "api": "v1", "graph": adapter_name, "token_required": bool(token),
                "probes": {p.name: {"attached": p.status.attached, "attach_type": p.status.attach_type,
                                    "reason": p.status.reason} for p in agent.probes}}
    rates = Rates()  # the counters of the last picture of the graph, for the rates on the next
    render = prometheus.Renderer()
    pictures = {"/metrics": lambda snap, _query: (render.chunks(snap), prometheus.CONTENT_TYPE),
                "/graph": lambda snap, query: document(graph, snap, query.get("format", "json"),
                                                       query.get("all") == "1", rates)}
    pages = {"/healthz": lambda _query: health.healthz(agent.probes, graph, adapter_name),
             "/readyz": lambda _query: health.readyz(graph, adapter_name)}
    server = HttpServer(args.address, args.port, pages, pictures, agent.collect, jobs, info, token, stream)
    try:
        start = time.perf_counter()
        agent.start(strict=args.strict)
        follower.start(wait=args.strict)  # without --strict a graph that fails is logged and marked stale
        features.release_btf()
        # What startup made (modules, probes, the graph) lives as long as the agent: frozen out of
        # the collector's scans. A scrape makes and drops tens of thousands of rows, freed by their
        # reference counts; at the default threshold (700) the collector ran twice a scrape at
        # 1,000 processes, rescanning the rows in flight: 2 ms of a 25 ms scrape.
        gc.freeze()
        gc.set_threshold(10_000, 10, 10)
        server.start()
        jobs.start()
        if diagnostics:
            diagnostics.start(agent.recent)
        attached = ", ".join(f"{p.name} ({p.status.attach_type})" for p in agent.probes if p.status.attached)
        log.info("serving http://%s:%d/metrics after %.2f s; probes: %s; graph: %s", args.address, server.port,
                 time.perf_counter() - start, attached or "none", adapter_name)
        # Woken each second: the kernel may hand SIGTERM to another thread, and Python runs the
        # handler only when the main thread runs again. An untimed wait then slept through it (an
        # agent that ignored SIGTERM until killed, seen once under load, its main thread here).
        while not done.wait(timeout=1):
            pass
    finally:
        if diagnostics:
            diagnostics.stop()
        jobs.stop()
        stream.close()
        server.stop()
        follower.stop()
        agent.stop(unload=not args.keep_loaded)
        if pins is not None:
            pins.close()
    return 0


def announcement(args):
    """This agent's host as the ros2 reader announces it: name, where to reach it, its URL."""
    from drums.graph.model import Host
    from drums.netfmt import hostport, primary_address

    address = args.advertise or (primary_address() if args.address in ("", "0.0.0.0", "::") else args.address)
    # With --port 0 the port is known only once bound: the URL is left out rather than wrong.
    return Host(socket.gethostname(), address, f"http://{hostport(address, args.port)}" if args.port else "")
