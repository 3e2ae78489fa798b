"""The `drums` command: agent, graph, sd, top, record, foxglove, detect, report, doctor, unload. Errors become one line on stderr and exit code 2."""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time

from drums.errors import DrumsError, GraphError, UsageError
from drums.netfmt import is_loopback

# A one-shot graph is complete once it has not changed for this long (and its adapter's settle).
QUIET = 1.0

log = logging.getLogger("drums")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, not argparse's usage block
        raise UsageError(f"{message} (see {self.prog} --help)")


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative")
    return value


def _foxglove_sources(parser: argparse.ArgumentParser) -> None:
    """The agents (and detector) whose channels `drums record` and `drums foxglove` carry."""
    from drums.exporters.prometheus import DEFAULT_PORT
    parser.add_argument("--agent", metavar="URL", action="append", default=None,
                        help=f"an agent to follow (repeatable; default http://127.0.0.1:{DEFAULT_PORT})")
    parser.add_argument("--token-file", default="",
                        help="file holding the agents' API token, for agents off loopback ($DRUMS_TOKEN also works)")
    parser.add_argument("--interval", type=_seconds, default=1.0, help="seconds between polls (0.1-3600, default 1)")
    parser.add_argument("--detector", metavar="URL", default="",
                        help="a `drums detect` whose anomalies go on /drums/anomalies (default none)")


def _port(text: str) -> int:
    value = _positive(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"{value} is not a port (0-65535)")
    return value


def _address(text: str) -> str:
    from drums.netfmt import is_address
    if not is_address(text):
        raise argparse.ArgumentTypeError(f"{text!r} is neither an IP address nor a DNS name")
    return text


def _attach(text: str) -> tuple[str, str]:
    probe, sep, path = text.partition("=")
    if not (sep and probe and path):
        raise argparse.ArgumentTypeError(f"{text!r} is not PROBE=PATH (e.g. sockets=kprobe)")
    return probe, path


def _seconds(text: str) -> float:
    from drums.exporters.jobs import MAX_INTERVAL, MIN_INTERVAL
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not MIN_INTERVAL <= value <= MAX_INTERVAL:
        raise argparse.ArgumentTypeError(f"{text} s is outside {MIN_INTERVAL:g}-{MAX_INTERVAL:g} s")
    return value


class _Version(argparse.Action):
    """--version, looked up only when asked: importlib.metadata costs every start 15 ms and a MB."""

    def __init__(self, option_strings, dest, **kw):
        super().__init__(option_strings, argparse.SUPPRESS, nargs=0, help="show the version and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib.metadata import PackageNotFoundError, version
        try:
            print(f"drums {version('drums')}")
        except PackageNotFoundError:  # run from a checkout that was never installed
            print("drums unknown")
        parser.exit()


def _graph_flags(parser: argparse.ArgumentParser) -> None:
    from drums.graph.registry import ADAPTERS
    parser.add_argument("--graph", choices=ADAPTERS, default=None,
                        help="where the graph comes from (default: ros2 where ROS 2 is set up, else auto)")
    parser.add_argument("--graph-file", default="", help="the YAML description for --graph static")


def _pin_flag(parser: argparse.ArgumentParser) -> None:
    from drums.kernel.bpffs import PIN_ROOT
    parser.add_argument("--pin-dir", default=PIN_ROOT,
                        help=f"where the BPF programs are pinned (default {PIN_ROOT}); agents that share a "
                             "kernel (one per network namespace or container) each need their own")


def _btf_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--btf", metavar="FILE", type=_btf_file, default=None,
                        help="this kernel's BTF, for a kernel without /sys/kernel/btf/vmlinux "
                             "(pahole --btf_encode_detached FILE vmlinux, or BTFHub's file for the kernel)")


def _btf_file(path: str) -> str:
    from drums.errors import KernelError
    from drums.kernel.btf import names
    try:
        names(path)
    except KernelError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return path


def build_parser() -> argparse.ArgumentParser:
    from drums.exporters.prometheus import DEFAULT_PORT
    from drums.exporters import STREAM_PORT
    from drums.detect import DEFAULT_PORT as DETECT_PORT
    from drums.detect import GRACE
    from drums.graph import FORMATS
    from drums.probes.registry import PROBES

    parser = _Parser(prog="drums", description="Middleware-aware monitoring for distributed robots.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    agent = sub.add_parser("agent", help="run the host agent and serve Prometheus metrics")
    agent.add_argument("--address", default="127.0.0.1",
                       help="address to serve /metrics on (default 127.0.0.1; 0.0.0.0 for Prometheus "
                            "on another host)")
    agent.add_argument("--advertise", metavar="ADDRESS", type=_address, default=None,
                       help="the IP address or DNS name other hosts reach this host and agent at, which "
                            "the ros2 graph announces to the other agents (default: --address unless it "
                            "is a wildcard, else the source address of the default route)")
    agent.add_argument("--token-file", default="",
                       help="file holding the token that POST and DELETE on the job API must carry "
                            "(Authorization: Bearer ...); needed off loopback ($DRUMS_TOKEN also works)")
    agent.add_argument("--port", type=_port, default=DEFAULT_PORT, help=f"port for /metrics (default {DEFAULT_PORT})")
    agent.add_argument("--stream-port", type=_port, default=STREAM_PORT,
                       help=f"port of the ZeroMQ stream of job samples, on --address (default {STREAM_PORT}; 0: any "
                            "free port, as /drums/v1/info says; CURVE-encrypted off loopback)")
    agent.add_argument("--latency-target", action="append", default=[], metavar="HOST",
                       help="a host latency jobs may probe, besides the hosts of the graph (repeatable)")
    agent.add_argument("--latency-mesh", action="store_true",
                       help="probe the round-trip time to every other host of the graph, every second")
    _graph_flags(agent)
    agent.add_argument("--probe", action="append", choices=PROBES, default=None,
                       help="run only these probes (repeatable; default all, rtps and rcl only with the "
                            "ros2 graph)")
    agent.add_argument("--no-probe", action="append", choices=PROBES, default=[],
                       help="do not run this probe (repeatable)")
    agent.add_argument("--attach", type=_attach, action="append", default=[], metavar="PROBE=PATH",
                       help="hold a probe to one attach path that `drums doctor` lists for it, or to "
                            "fallback (its counters without eBPF); repeatable. A path this kernel refuses "
                            "leaves the probe to its fallback (an error with --strict)")
    agent.add_argument("--no-ros-timing", dest="ros_timing", action="store_false",
                       help="count ROS 2 messages without timing them (no periods, deadlines, reactions or "
                            "delivery times): less work in the kernel for each message")
    agent.add_argument("--splice-tracepoints", action="store_true",
                       help="on a kernel without kprobes, count splice(2) reads from TCP and unix stream sockets "
                            "through the syscall tracepoints, which slow every system call on the host")
    agent.add_argument("--strict", action="store_true",
                       help="refuse to start unless every probe attaches with eBPF and the graph adapter starts")
    agent.add_argument("--keep-loaded", action="store_true",
                       help="leave the BPF programs pinned on exit, so a restart needs no compile")
    _pin_flag(agent)
    _btf_flag(agent)
    agent.add_argument("--pid", type=_positive, action="append", default=[], help="monitor this process")
    agent.add_argument("--process-name", action="append", default=[],
                       help="monitor processes whose name, command line or ROS node names match this "
                            "regular expression (RE2)")
    agent.add_argument("--cgroup", action="append", default=[],
                       help="monitor processes in this cgroup (path prefix, e.g. /system.slice)")
    agent.add_argument("--own-netns", action="store_true",
                       help="monitor only processes in the agent's network namespace (one agent per "
                            "namespace or container standing for a host)")
    # A socket's own series are six, with seven labels each, a connection's five: 100 of either are
    # already 500-600 series a scrape. The rest still count in their process's rows, the host's TCP
    # counters and the graph's edges.
    for kind, default in (("processes", 100), ("threads", 200), ("sockets", 100), ("connections", 100)):
        agent.add_argument(f"--max-{kind}", type=_positive, default=default,
                           help=f"{kind} with series of their own; the rest are summed as other "
                                f"(default {default})")
    agent.add_argument("--diagnostics", action="store_true",
                       help="publish a diagnostic_msgs/DiagnosticArray on the ROS 2 topic /diagnostics: a "
                            "status per node of this host and one for the host, OK, WARN or ERROR by thresholds")
    agent.add_argument("--diagnostics-config", metavar="FILE", default="",
                       help="YAML file of thresholds and interval for --diagnostics, which it implies "
                            "(format and defaults in the README)")
    agent.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))

    graph = sub.add_parser("graph", help="print the computation graph: nodes, topics, connections")
    _graph_flags(graph)
    graph.add_argument("--format", choices=FORMATS, default="text", help="output format (default text)")
    graph.add_argument("--output", default="-", help="file to write (default standard output)")
    graph.add_argument("--watch", action="store_true", help="after the graph, print each change as it happens")
    graph.add_argument("--all", action="store_true",
                       help="dot and svg: also draw /rosout, /parameter_events and Drums' own nodes")
    graph.add_argument("--agent", metavar="URL", default="",
                       help="ask the agent at URL (e.g. http://localhost:9969) for its graph, with the "
                            "metrics of its nodes, topics and edges, instead of discovering it here")

    sd = sub.add_parser("sd", help="write the hosts of the graph as a Prometheus file_sd target file",
                        description="One target group per host of the graph, labelled host=<name>: the "
                                    "address and port its agent announced, else its address and --port, else "
                                    "its name and --port (resolved by Prometheus through DNS).")
    _graph_flags(sd)
    sd.add_argument("--output", metavar="FILE", required=True,
                    help="the file for Prometheus's file_sd_configs, replaced whole (by rename) when written")
    sd.add_argument("--port", type=_port, default=DEFAULT_PORT,
                    help=f"the agents' port, for hosts that did not announce their agent (default {DEFAULT_PORT})")
    sd.add_argument("--agent", metavar="URL", default="",
                    help="take the hosts of the graph of the agent at URL (e.g. http://localhost:9969) "
                         "instead of discovering them here")
    sd.add_argument("--watch", action="store_true", help="keep running: write the file again when the hosts change")

    from drums.top import VIEWS as TOP_VIEWS
    top = sub.add_parser("top", help="the nodes, topics, edges, connections and hosts of one or more agents, live",
                         description="Full screen, live: n t e c h switch views, < > sort, / filter, ? help, "
                                     "q quit. --once and --json print one complete view for scripts.")
    top.add_argument("--agent", metavar="URL", action="append", default=None,
                     help=f"an agent to show (repeatable; default http://127.0.0.1:{DEFAULT_PORT})")
    top.add_argument("--token-file", default="",
                     help="file holding the agents' API token, for agents off loopback ($DRUMS_TOKEN also works)")
    top.add_argument("--interval", type=_seconds, default=1.0, help="seconds between updates (0.1-3600, default 1)")
    top.add_argument("--view", choices=TOP_VIEWS, default="nodes",
                     help="the view to start with, or to print (default nodes)")
    top.add_argument("--once", action="store_true", help="print the first complete view as text and exit")
    top.add_argument("--json", action="store_true", help="print the first complete view as JSON and exit")
    top.add_argument("--no-color", action="store_true", help="draw without colors (as $NO_COLOR does)")
    top.add_argument("--detector", metavar="URL", default=f"http://127.0.0.1:{DETECT_PORT}",
                     help=f"the `drums detect` whose anomalies the Anomalies view (a) lists (default "
                          f"http://127.0.0.1:{DETECT_PORT}; '' for none)")

    record = sub.add_parser("record", help="record what top shows of one or more agents to an MCAP file, for Foxglove",
                            description="A channel per node, topic, edge and host (JSON whose fields plot in "
                                        "Foxglove's Plot panel) and the detector's anomalies as log messages, stamped "
                                        "with the agents' clocks, until SIGINT or SIGTERM.")
    record.add_argument("--output", metavar="FILE.mcap", required=True, help="the file to write (must not exist)")
    _foxglove_sources(record)

    fox = sub.add_parser("foxglove", help="serve what top shows of one or more agents to Foxglove, live (WebSocket)",
                         description="The channels of drums record, and the ROS graph as the agents see it (Foxglove's "
                                     "Topic Graph), over the Foxglove WebSocket protocol until SIGINT or SIGTERM.")
    fox.add_argument("--address", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    fox.add_argument("--port", type=_port, default=8765, help="port to listen on (default 8765, Foxglove's)")
    _foxglove_sources(fox)

    detect = sub.add_parser("detect", help="watch every series of one or more agents and name the few that changed",
                            description="Judges each new point of every series (a counter's rate) against its "
                                        "recent history by five statistical checks, and prints a line per anomaly "
                                        "(by the host, process, node, topic or edge it belongs to) and per change "
                                        "of the graph.")
    detect.add_argument("--agent", metavar="URL", action="append", default=None,
                        help=f"an agent to watch (repeatable; default http://127.0.0.1:{DEFAULT_PORT} unless "
                             "--prometheus is given)")
    detect.add_argument("--prometheus", metavar="URL", default="",
                        help="watch every drums_ series this Prometheus server holds, for a whole fleet")
    detect.add_argument("--token-file", default="",
                        help="file holding the agents' API token, for agents off loopback ($DRUMS_TOKEN also works)")
    detect.add_argument("--interval", type=_seconds, default=1.0, help="seconds between reads (0.1-3600, default 1)")
    detect.add_argument("--log", metavar="FILE", default="", help="append each event to FILE as a JSON line")
    detect.add_argument("--address", default="127.0.0.1", help="address of the detector's /metrics and /anomalies")
    detect.add_argument("--port", type=_port, default=DETECT_PORT,
                        help=f"port of the detector's /metrics and /anomalies (default {DETECT_PORT}; 0: any)")
    detect.add_argument("--ignore", action="append", choices=("host", "process", "connection", "link"), default=[],
                        help="do not flag series of this kind of entity (repeatable): host for the host's own "
                             "totals, as the paper did; process for processes that run no node")
    detect.add_argument("--grace", type=float, default=GRACE, metavar="SECONDS",
                        help=f"how long the series of a node that started, restarted or gained an edge are left "
                             f"alone while it settles (default {GRACE:g}); a process's memory that grows steadily, "
                             f"a leak from birth, is named even then, from its 16th second")
    detect.add_argument("--ros", action="store_true",
                        help="also publish the anomalies now on the ROS 2 topic /drums/anomalies "
                             "(diagnostic_msgs/DiagnosticArray, a WARN status per anomaly), every interval")
    detect.add_argument("--detail", action="store_true",
                        help="also watch per-thread and per-socket series (their process's totals, in detail) "
                             "and the scheduler's: context switches and run-queue waits")
    detect.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))

    report = sub.add_parser("report", help="an HTML page of the anomalies `drums detect --log` wrote in a time range",
                            description="A figure per flagged entity, a plot per anomalous series around its "
                                        "anomaly. Times are Unix seconds or ISO 8601 (2026-11-25T13:42).")
    report.add_argument("log", help="the JSON-lines file of `drums detect --log`")
    report.add_argument("--output", required=True, help="the HTML file to write")
    report.add_argument("--from", dest="begin", default="", help="the range's start (default: the log's first)")
    report.add_argument("--to", dest="end", default="", help="the range's end (default: now)")

    _btf_flag(sub.add_parser("doctor", help="say what this host offers each probe, and what to fix"))
    _pin_flag(sub.add_parser("unload", help="detach and remove BPF programs left pinned by --keep-loaded"))
    return parser


def _read_token(path: str) -> str:
    """The API token, from --token-file or $DRUMS_TOKEN ("" if neither)."""
    if not path:
        return os.environ.get("DRUMS_TOKEN", "")
    try:
        with open(path) as f:
            mode = os.fstat(f.fileno()).st_mode
            if mode & 0o077:  # as ssh refuses such keys: anyone who reads it may change the jobs
                raise UsageError(f"--token-file {path}: readable by others (mode {mode & 0o777:o}); "
                                 f"chmod 600 {path}")
            token = f.read().strip()
    except OSError as e:
        raise UsageError(f"--token-file {path}: {e.strerror}") from None
    if not token:
        raise UsageError(f"--token-file {path}: the file is empty")
    return token


def _token(address: str, path: str) -> str:
    """The agent's API token; required to listen off loopback."""
    token = _read_token(path)
    if not is_loopback(address) and not token:
        raise UsageError(f"--address {address}: off loopback the job API needs a token "
                         "(--token-file FILE or $DRUMS_TOKEN)")
    return token


def _settled(args):
    """(graph, follower) of the graph --graph names, followed from here, once discovery has settled:
    the first answer is rarely all of it. The caller stops the follower."""
    from drums.graph import registry
    from drums.graph.adapter import Follower
    from drums.graph.model import Graph

    logging.basicConfig(level="WARNING", format="drums: %(message)s")
    adapter = registry.build(args.graph or registry.default(), args.graph_file)
    graph = Graph()
    follower = Follower(adapter, graph)
    drums_log = logging.getLogger("drums")
    try:
        # Until the first graph, a failure is the one line main() prints; after it, each is logged.
        level = drums_log.level
        drums_log.setLevel(logging.ERROR)
        try:
            follower.start(wait=True)
            deadline = time.monotonic() + 2 * adapter.interval + 5
            while not graph.updated_at and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            drums_log.setLevel(level)
        if not graph.updated_at:
            raise GraphError(graph.error or "no graph within the time allowed")
        # Discovery goes on after the first answer: done `settle` s later, once nothing changes.
        _, cursor = graph.changes_since(0)
        first = changed = time.monotonic()
        while time.monotonic() < first + 4 * adapter.settle and (
                time.monotonic() < first + adapter.settle or time.monotonic() < changed + QUIET):
            time.sleep(0.05)
            changes, cursor = graph.changes_since(cursor)
            if changes:
                changed = time.monotonic()
    except BaseException:
        follower.stop()
        raise
    return graph, follower


def run_graph(args) -> int:
    if args.agent:
        if args.watch or args.graph or args.graph_file:
            raise UsageError("--agent takes the agent's graph as it is: not with --watch, --graph or --graph-file")
        _write(args.output, _agent_graph(args.agent, args.format, args.all))
        return 0

    from drums.graph.export import render

    graph, follower = _settled(args)
    try:
        _write(args.output, render(graph.snapshot(), args.format, stale=graph.error, everything=args.all))
        if args.watch:
            _, cursor = graph.changes_since(0)
            while True:
                time.sleep(0.2)
                changes, cursor = graph.changes_since(cursor)
                for c in changes:
                    print(f"{time.strftime('%H:%M:%S', time.localtime(c.at))} {c.action} {c.id}", flush=True)
    finally:
        follower.stop()
    return 0


def run_sd(args) -> int:
    from drums.exporters import file_sd

    logging.basicConfig(level="WARNING", format="drums: %(message)s")
    follower = None
    if args.agent:
        if args.graph or args.graph_file:
            raise UsageError("--agent takes the hosts of the agent's graph: not with --graph or --graph-file")

        def hosts():
            return file_sd.hosts_of(_agent_graph(args.agent, "json"), f"--agent {args.agent}")
    else:
        graph, follower = _settled(args)

        def hosts():
            return graph.entities("host")
    try:
        written, failed = None, ""
        while True:
            try:
                groups = file_sd.target_groups(hosts(), args.port)
            except DrumsError as e:
                if written is None:
                    raise
                if str(e) != failed:  # an agent that restarts: the file stays as it was meanwhile
                    log.warning("%s; keeping %s as it is", e, args.output)
                failed = str(e)
            else:
                failed = ""
                if groups != written:
                    file_sd.write(args.output, groups)
                    written = groups
                    print(f"{args.output}: {', '.join(g['targets'][0] for g in groups) or 'no hosts'}", flush=True)
            if not args.watch:
                return 0
            time.sleep(1)
    finally:
        if follower is not None:
            follower.stop()


def _write(output: str, text: str) -> None:
    try:
        if output == "-":
            sys.stdout.write(text)
        else:
            with open(output, "w") as f:
                f.write(text)
    except OSError as e:
        raise UsageError(f"--output {output}: {e.strerror}") from None


def _agent_graph(url: str, fmt: str, everything: bool = False) -> str:
    """The graph an agent serves, with its metrics on it."""
    from drums.client import Agent, AgentError

    try:
        return Agent(url, timeout=30).page(f"/graph?format={fmt}" + ("&all=1" if everything else ""))
    except AgentError as e:
        raise UsageError(f"--agent {e}") from None


def run_detect(args) -> int:
    from drums.detect.detector import Detector
    from drums.detect.run import Loop, serve
    from drums.detect.sources import AgentSource, PrometheusSource
    from drums.exporters.prometheus import DEFAULT_PORT

    logging.basicConfig(level=args.log_level.upper(), format="drums: %(message)s")
    token = _read_token(args.token_file)
    urls = args.agent or ([] if args.prometheus else [f"http://127.0.0.1:{DEFAULT_PORT}"])
    sources = [AgentSource(url, token, args.detail) for url in urls]
    if args.prometheus:
        sources.append(PrometheusSource(args.prometheus, args.detail))
    if not 0 <= args.grace <= 3600:
        raise UsageError(f"--grace {args.grace:g}: seconds from 0 to 3600")
    loop = Loop(sources, Detector(grace=args.grace, ignore=set(args.ignore)), args.interval, args.log,
                echo=lambda line: print(line, flush=True), ros=args.ros)
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    server = serve(loop, args.address, args.port)
    log.info("detect: watching %s; /metrics and /anomalies on port %d", ", ".join(s.address for s in sources), server.port)
    try:
        loop.run(done)
    finally:
        server.stop()
        loop.close()
    return 0


def run_unload(args) -> int:
    import shutil

    from drums.errors import KernelError
    from drums.kernel import pinlock
    lock = pinlock.hold(args.pin_dir)  # refused while an agent runs on these pins
    shutil.rmtree(args.pin_dir, ignore_errors=True)
    if lock is not None:
        lock.close()
    if os.path.exists(args.pin_dir):
        raise KernelError(f"could not remove {args.pin_dir} (root is needed)")
    print(f"removed {args.pin_dir}")
    return 0


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        if args.command == "agent":
            from drums import serve
            return serve.run(args, _token(args.address, args.token_file))
        if args.command == "graph":
            return run_graph(args)
        if args.command == "top":
            from drums.exporters.prometheus import DEFAULT_PORT
            from drums.top.main import run
            if args.once and args.json:
                raise UsageError("--once prints text and --json JSON: one of them")
            return run(args.agent or [f"http://127.0.0.1:{DEFAULT_PORT}"], _read_token(args.token_file), args.interval,
                       args.view, args.once, args.json, color=not args.no_color, detector=args.detector)
        if args.command == "record":
            from drums.exporters.prometheus import DEFAULT_PORT
            from drums.foxglove.record import run
            return run(args.agent or [f"http://127.0.0.1:{DEFAULT_PORT}"], _read_token(args.token_file), args.interval,
                       args.output, args.detector)
        if args.command == "foxglove":
            from drums.exporters.prometheus import DEFAULT_PORT
            from drums.foxglove.serve import run
            return run(args.agent or [f"http://127.0.0.1:{DEFAULT_PORT}"], _read_token(args.token_file), args.interval,
                       args.address, args.port, args.detector)
        if args.command == "sd":
            return run_sd(args)
        if args.command == "detect":
            return run_detect(args)
        if args.command == "report":
            from drums.detect.report import run
            return run(args.log, args.output, args.begin, args.end)
        if args.command == "doctor":
            from drums.doctor import run
            return run(args.btf or "")
        return run_unload(args)
    except DrumsError as e:
        print(f"drums: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
