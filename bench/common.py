"""Shared helpers of the benchmarks: start and stop the agent, read a process's CPU and memory,
scrape /metrics, and print results as one markdown table per benchmark.

The benchmarks are not tests: they measure, print, clean up and exit 0 whether or not a goal is met.
"""
from __future__ import annotations

import gzip
import http.client
import json
import os
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass, field

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHON = sys.executable
PIN_ROOT = "/sys/fs/bpf/drums"  # where `drums agent` pins (drums.kernel.bpffs.PIN_ROOT)
READY_LINE = 'drums_probe_attached{probe="sockets",attach_type="tp_btf"} 1'
_CLK_TCK = os.sysconf("SC_CLK_TCK")

if ROOT not in sys.path:  # the scripts run as `python bench/<name>.py`, not as a package
    sys.path.insert(0, ROOT)


class BenchError(Exception):
    """A benchmark could not run (not root, a tool missing, the agent did not start)."""


def require_root() -> None:
    if os.geteuid() != 0:
        raise BenchError("run as root: the agent and the probes need CAP_BPF and CAP_PERFMON")


def require_tool(name: str) -> str:
    path = shutil.which(name)
    if not path:
        raise BenchError(f"{name} is not installed (make setup-test installs it)")
    return path


def stop_on_sigterm() -> None:
    """Turn SIGTERM into KeyboardInterrupt so that each script's finally-blocks clean up."""
    def handler(*_):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, handler)


def main_wrapper(run) -> None:
    """Run a benchmark's main(); one line and exit 1 if it cannot run at all."""
    from drums.errors import DrumsError

    stop_on_sigterm()
    try:
        run()
    except (BenchError, DrumsError) as e:  # DrumsError: a probe that would not load, for one
        print(f"bench: {e}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        print("bench: interrupted", file=sys.stderr)
        sys.exit(130)


# --- numbers -------------------------------------------------------------------------------------

def median(values) -> float:
    values = list(values)
    return statistics.median(values) if values else float("nan")


def percentile(values, p: float) -> float:
    """Nearest-rank percentile (p in 0..100)."""
    values = sorted(values)
    if not values:
        return float("nan")
    k = max(0, min(len(values) - 1, int(round(p / 100 * len(values) + 0.5)) - 1))
    return values[k]


def ratio(ours: float, peer: float) -> str:
    if ours != ours or peer != peer or peer <= 0:
        return "n/a"  # a floor measured at or below zero is noise, not a basis
    return f"{ours / peer:.2f}x"


def fmt(value: float, digits: int = 2) -> str:
    if value != value:
        return "n/a"
    return f"{value:,.{digits}f}"


# --- output --------------------------------------------------------------------------------------

TABLES = "DRUMS_BENCH_TABLES"  # a file each table is added to as a JSON line (bench/run_all.py reads it)


def print_table(title: str, headers: list[str], rows: list[list], notes: list[str] = ()) -> None:
    """A markdown table under a `### title` heading, then notes as a bullet list; and the same
    as a JSON line in $DRUMS_BENCH_TABLES, from which the README's tables are made."""
    cells = [[str(c) for c in row] for row in rows]
    if os.environ.get(TABLES):
        with open(os.environ[TABLES], "a") as f:
            f.write(json.dumps({"title": title, "headers": [str(h) for h in headers], "rows": cells,
                                "notes": list(notes)}) + "\n")
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]

    def line(values):
        return "| " + " | ".join(v.ljust(w) for v, w in zip(values, widths)) + " |"

    print(f"\n### {title}\n")
    print(line(headers))
    print("| " + " | ".join("-" * w for w in widths) + " |")
    for row in cells:
        print(line(row))
    if notes:
        print()
        for n in notes:
            print(f"- {n}")
    sys.stdout.flush()


def progress(message: str) -> None:
    """Progress goes to stderr, so that stdout holds only the tables."""
    print(f"  .. {message}", file=sys.stderr, flush=True)


# --- processes -----------------------------------------------------------------------------------

def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (its threads included, its children not)."""
    with open(f"/proc/{pid}/stat") as f:
        # The command name may hold spaces and parentheses: split after its last ')'.
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK  # fields 14 and 15 of proc(5)


def tree(pid: int) -> list[int]:
    """The process and its children (the agent's helpers), as they run now."""
    pids = [pid]
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                pids += [int(p) for p in f.read().split()]
        except OSError:
            pass
    return pids


def memory(pid: int) -> dict[str, int]:
    """Rss, Pss, Private_Clean, Private_Dirty, ... of a process in bytes (smaps_rollup)."""
    out = {}
    with open(f"/proc/{pid}/smaps_rollup") as f:
        for line in f:
            key, _, rest = line.partition(":")
            parts = rest.split()
            if len(parts) == 2 and parts[1] == "kB":
                out[key] = int(parts[0]) * 1024
    return out


def uss_bytes(pid: int) -> int:
    """Unique set size: the private pages, what stopping the process would free."""
    m = memory(pid)
    return m.get("Private_Clean", 0) + m.get("Private_Dirty", 0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def terminate(proc: subprocess.Popen, timeout: float = 10) -> None:
    """SIGTERM, then SIGKILL if it has not ended within timeout seconds."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def pin_cpu(cpu: int | None) -> list[str]:
    """A command prefix that runs a program on one CPU (empty when cpu is None)."""
    if cpu is None:
        return []
    return ["taskset", "-c", str(cpu)]


# --- HTTP ----------------------------------------------------------------------------------------

def fetch(url: str, timeout: float = 5) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()
    except (urllib.error.URLError, ConnectionError, TimeoutError, OSError):
        return 0, b""


class Scraper:
    """GETs one URL as Prometheus scrapes a target: over a connection kept alive between requests
    (a new TCP connection per scrape would be a change of the host's connections each time),
    taking the body gzipped. Gives it back as it was before compression."""

    def __init__(self, url: str, timeout: float = 30):
        parts = urllib.parse.urlsplit(url)
        self.address, self.path, self.timeout = (parts.hostname, parts.port), parts.path, timeout
        self._conn: http.client.HTTPConnection | None = None

    def get(self) -> tuple[int, bytes]:
        for _ in range(2):  # the server may have closed an idle connection: once more on a new one
            try:
                if self._conn is None:
                    self._conn = http.client.HTTPConnection(*self.address, timeout=self.timeout)
                self._conn.request("GET", self.path, headers={"Accept-Encoding": "gzip"})
                response = self._conn.getresponse()
                body = response.read()
                if response.getheader("Content-Encoding") == "gzip":
                    body = gzip.decompress(body)
                return response.status, body
            except (http.client.HTTPException, OSError):
                self.close()
        return 0, b""

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None


_SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{.*\})?\s+(\S+)$')


def samples(body: bytes, name: str) -> dict[str, float]:
    """label text -> value of every sample of one metric name in a /metrics body."""
    out = {}
    for line in body.decode(errors="replace").splitlines():
        if not line.startswith(name):
            continue
        m = _SAMPLE.match(line)
        if m and m.group(1) == name:
            out[m.group(2) or ""] = float(m.group(3))
    return out


def series_count(body: bytes) -> int:
    return sum(1 for line in body.splitlines() if line and not line.startswith(b"#"))


# --- the agent -----------------------------------------------------------------------------------

def drums_unload() -> None:
    """Remove every pin of `drums agent --keep-loaded` (and so detach its programs)."""
    subprocess.run([PYTHON, "-m", "drums", "unload"], cwd=ROOT, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, check=False)


@dataclass
class Agent:
    """`python -m drums agent` on a free port, its log in a temporary file."""

    keep_loaded: bool = False
    extra: list[str] = field(default_factory=list)
    under: list[str] = field(default_factory=list)  # a command that execs the agent (prlimit ...)
    port: int = 0
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    _log: object = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/metrics"

    def start(self) -> "Agent":
        self.port = self.port or free_port()
        # The host agent as measured in the README: the auto graph, so no ROS 2 reader and no
        # per-topic probes (bench/topic_latency.py measures those).
        cmd = [PYTHON, "-m", "drums", "agent", "--port", str(self.port), "--log-level", "info", "--graph", "auto"]
        if self.keep_loaded:
            cmd.append("--keep-loaded")
        self._log = tempfile.TemporaryFile(mode="w+")
        self.started_at = time.perf_counter()
        self.proc = subprocess.Popen(self.under + cmd + self.extra, cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT)
        return self

    def wait_ready(self, timeout: float = 60, interval: float = 0.01) -> float:
        """Seconds from start() until /metrics shows the sockets probe attached."""
        deadline = self.started_at + timeout
        while time.perf_counter() < deadline:
            if self.proc.poll() is not None:
                raise BenchError(f"the agent exited with {self.proc.returncode}: {self.log()[-500:]}")
            status, body = fetch(self.url, timeout=2)
            if status == 200 and READY_LINE.encode() in body:
                return time.perf_counter() - self.started_at
            time.sleep(interval)
        raise BenchError(f"the agent did not attach its sockets probe within {timeout:.0f} s: "
                         f"{self.log()[-500:]}")

    def log(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        return self._log.read()

    def reported_startup(self) -> float:
        """The agent's own 'serving ... after X s' figure (its probe start, without imports)."""
        m = re.search(r"after ([0-9.]+) s", self.log())
        return float(m.group(1)) if m else float("nan")

    def stop(self) -> None:
        if self.proc is not None:
            terminate(self.proc, timeout=20)
        if self._log is not None:
            self._log.close()
            self._log = None

    def __enter__(self) -> "Agent":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


# --- BPF programs --------------------------------------------------------------------------------

def bpftool_json(*args: str):
    proc = subprocess.run(["bpftool", "-j", *args], capture_output=True, text=True, check=False)
    if proc.returncode != 0 or not proc.stdout.strip():
        return None
    return json.loads(proc.stdout)


def attached_programs(tracepoints) -> list[str]:
    """'name@tracepoint' of every BPF program attached to one of these raw tracepoints: what else
    on the host costs time on the events a benchmark measures."""
    links = bpftool_json("link", "show") or []
    progs = {p["id"]: p.get("name", "?") for p in bpftool_json("prog", "show") or []}
    out = []
    for link in links:
        tp = link.get("tp_name")
        if tp in tracepoints:
            out.append(f"{progs.get(link.get('prog_id'), '?')}@{tp}")
    return sorted(out)


class ForeignWatch:
    """Programs of others on the measured tracepoints, looked for whenever none of ours is
    attached: they tax every condition, the baseline included, and make a run noisier."""

    def __init__(self, tracepoints):
        self.tracepoints = tuple(tracepoints)
        self.found: set[str] = set()
        self.looks = self.hits = 0
        self.load_at_start = os.getloadavg()[0]

    def look(self) -> None:
        found = attached_programs(self.tracepoints)
        self.looks += 1
        self.hits += bool(found)
        self.found.update(found)

    def notes(self) -> list[str]:
        out = [f"host load average (1 min): {self.load_at_start:.2f} at the start, "
               f"{os.getloadavg()[0]:.2f} at the end"]
        if self.found:
            out.append(f"other BPF programs were attached to the measured events at {self.hits} of "
                       f"{self.looks} looks (another session's probes?), in the baseline too: "
                       + ", ".join(sorted(self.found)))
        return out
