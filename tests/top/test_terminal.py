"""`drums top` in a real terminal (tmux, 80x24): rows that never wrap, with a node name of 40
characters and a process of 30 nodes; no colors when asked; the terminal restored on `q`; and
its jobs on the agent gone however it ends (SIGTERM, a closed terminal, and kill -9 by their
lease)."""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from drums.client import Agent
from drums.top.collector import LEASE_INTERVALS, MIN_LEASE
from tests.agentproc import running_agent, scrape
from tests.conftest import eventually
from tests.graph.test_hosts import named

LONG = "/perception/front_camera_rectify_node_01"
JOINTS = [f"/arm/joint_{i:02}" for i in range(30)]
SLEEP = "import time\nwhile True: time.sleep(1)"
TMUX = ("tmux", "-L", f"drums-top-test-{os.getpid()}")  # a server of our own: our environment, no one else's
GREYS = {0, 7, 8, 15, 16, 231, *range(232, 256)}  # 256-color indices without a hue
INTERVAL = 0.5
LEASE = max(MIN_LEASE, LEASE_INTERVALS * INTERVAL)  # what top asks for its jobs


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    """An agent (host top-t) whose static graph has a node of 40 characters, a process of 30 nodes,
    and a host to measure the round trip to; yields (its base URL, {node: PID})."""
    assert len(LONG) == 40
    path = tmp_path_factory.mktemp("graph") / "graph.yaml"
    path.write_text("\n".join(["hosts: [{name: top-peer, address: 127.0.0.1}]", "nodes:",
                               f"  - {{name: {LONG}, process: long-marker}}",
                               *(f"  - {{name: {j}, process: thirty-marker}}" for j in JOINTS), "topics: []", ""]))
    procs = {marker: subprocess.Popen([sys.executable, "-c", SLEEP, marker]) for marker in ("long-marker", "thirty-marker")}
    try:
        with running_agent("--graph", "static", "--graph-file", str(path), "--probe", "host", "--probe", "process",
                           "--probe", "latency", under=named("top-t")) as url:
            yield url.rsplit("/", 1)[0], {LONG: procs["long-marker"].pid, **{j: procs["thirty-marker"].pid for j in JOINTS}}
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
        subprocess.run([*TMUX, "kill-server"], capture_output=True)


@contextlib.contextmanager
def terminal(*argv: str, env: str = ""):
    """`drums top ARGV` in an 80x24 tmux pane, after a line of the shell's own; yields the
    session's name. The pane stays after top ends, saying how it ended."""
    name = f"top{time.monotonic_ns()}"
    command = (f"printf 'before top\\n'; {env} {sys.executable} -m drums top {' '.join(argv)}; "
               f"echo \"top ended: $?\"; sleep 600")
    subprocess.run([*TMUX, "new-session", "-d", "-s", name, "-x", "80", "-y", "24", "sh", "-c", command], check=True,
                   cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    try:
        yield name
    finally:  # a closed terminal: a top still running ends (and deletes its jobs) before the next test
        shell = subprocess.run([*TMUX, "display", "-p", "-t", name, "#{pane_pid}"], capture_output=True, text=True)
        tops = subprocess.run(["pgrep", "-P", shell.stdout.strip(), "-f", "drums top"], capture_output=True,
                              text=True).stdout.split() if shell.returncode == 0 else []

        def ended():
            assert not [pid for pid in tops if os.path.exists(f"/proc/{pid}")], "top still runs"
        subprocess.run([*TMUX, "kill-session", "-t", name], capture_output=True)
        eventually(ended, timeout=10)


def screen(session: str, *flags: str) -> list[str]:
    return subprocess.run([*TMUX, "capture-pane", "-p", *flags, "-t", session], capture_output=True, text=True,
                          check=True).stdout.split("\n")[:24]


def pane(session: str, what: str) -> str:
    return subprocess.run([*TMUX, "display", "-p", "-t", session, f"#{{{what}}}"], capture_output=True, text=True,
                          check=True).stdout.strip()


def top_pid(session: str) -> int:
    """The PID of top, the child of the pane's shell."""
    return int(subprocess.run(["pgrep", "-P", pane(session, "pane_pid"), "-f", "drums top"], capture_output=True,
                              text=True).stdout.split()[0])


def up(session: str) -> None:
    assert screen(session)[0].startswith("drums top  Nodes: ")


def keys(session: str, *typed: str) -> None:
    subprocess.run([*TMUX, "send-keys", "-t", session, *typed], check=True)


def jobs(base: str) -> list[dict]:
    return json.loads(scrape(base + "/drums/v1/jobs"))["jobs"]


def test_at_80x24_rows_never_wrap_and_q_gives_the_terminal_back(graph):
    base, pids = graph
    with terminal("--agent", base, "--interval", str(INTERVAL)) as session:
        eventually(lambda: up(session), timeout=10)  # keys typed before would be echoed by the shell's terminal

        def rows_of(text: str) -> list[str]:
            keys(session, "Escape")  # the filter cleared
            time.sleep(0.3)
            keys(session, "/", text, "Enter")  # and typed again

            def shown():
                lines = screen(session, "-J")  # wrapped lines come back joined: longer than 80
                assert len(lines) == 24 and all(len(line) <= 80 for line in lines), lines
                assert f"filter: {text}" in lines[0]
                return lines
            return eventually(shown, timeout=5)

        def joints():
            lines = rows_of("/arm/")
            found = [line for line in lines if re.search(rf"/arm/joint_\d\d\s+{pids[JOINTS[0]]}\s", line)]
            assert len(found) >= 15 and lines[0].startswith("drums top  Nodes: 30 of "), lines  # 30 rows, 15+ on screen
            return found
        eventually(joints, timeout=15)

        def long():
            lines = rows_of("front_camera")
            row, = [line for line in lines if f" {pids[LONG]} " in line]
            name = row.split()[0]
            assert name == LONG or (len(name) < len(LONG) and "…" in name and LONG.startswith(name.split("…")[0])
                                    and LONG.endswith(name.split("…")[1])), row
            return row
        eventually(long, timeout=10)
        assert pane(session, "alternate_on") == "1"
        keys(session, "q")

        def restored():
            lines = screen(session)
            assert pane(session, "alternate_on") == "0"
            assert lines[:2] == ["before top", "top ended: 0"], lines
        eventually(restored, timeout=10)


@pytest.mark.parametrize("env, flag, colored", [("", "", True), ("NO_COLOR=1", "", False), ("", "--no-color", False)])
def test_no_color_draws_in_greys_only(graph, env, flag, colored):
    base, _ = graph
    with terminal("--agent", base, "--interval", str(INTERVAL), flag, env=env) as session:
        def drawn():
            text = "\n".join(screen(session, "-e"))
            assert "/arm/joint" in text
            return {int(i) for i in re.findall(r"\x1b\[(?:[0-9;]*;)?[34]8;5;(\d+)", text)}
        colors = eventually(drawn, timeout=10)
        assert bool(colors - GREYS) == colored, colors


def started_jobs(base: str) -> list[dict]:
    """Top's jobs on the agent, once it made them: the host job and a latency job to top-peer."""
    def made():
        found = jobs(base)
        assert {j["id"] for j in found} == {"host", "latency/127.0.0.1"}, found
        return found
    return eventually(made, timeout=15)


def test_sigterm_leaves_the_agents_jobs_as_they_were_and_the_terminal_restored(graph):
    base, _ = graph
    # Someone else's host job, without a lease: top uses it and leaves it alone.
    Agent(base).create("host", interval=INTERVAL)
    before = jobs(base)
    try:
        with terminal("--agent", base, "--interval", str(INTERVAL)) as session:
            during = started_jobs(base)
            assert next(j for j in during if j["id"] == "latency/127.0.0.1")["lease"] == LEASE
            os.kill(top_pid(session), signal.SIGTERM)
            ended = time.monotonic()

            def as_before():
                after = jobs(base)
                assert [(j["id"], j.get("lease"), j["interval"]) for j in after] == \
                    [(j["id"], j.get("lease"), j["interval"]) for j in before]
            eventually(as_before, timeout=LEASE)
            assert time.monotonic() - ended < 5  # deleted on the way out, not by the lease

            def restored():
                assert screen(session)[:2] == ["before top", f"top ended: {128 + signal.SIGTERM}"]
                assert pane(session, "alternate_on") == "0"
            eventually(restored, timeout=10)
    finally:
        Agent(base).stop("host")


def test_a_closed_terminal_deletes_the_jobs(graph):
    base, _ = graph
    with terminal("--agent", base, "--interval", str(INTERVAL)) as session:
        started_jobs(base)
        pid = top_pid(session)
        subprocess.run([*TMUX, "kill-session", "-t", session], check=True)  # SIGHUP, as a closed window

        def gone():
            assert jobs(base) == [] and not os.path.exists(f"/proc/{pid}")
        eventually(gone, timeout=5)


def test_a_top_killed_9_leaves_no_job_after_its_lease(graph):
    base, _ = graph
    with terminal("--agent", base, "--interval", str(INTERVAL)) as session:
        started_jobs(base)
        os.kill(top_pid(session), signal.SIGKILL)
        killed = time.monotonic()
        assert {j["id"] for j in jobs(base)} == {"host", "latency/127.0.0.1"}  # nothing could delete them

        def expired():
            assert jobs(base) == []
        eventually(expired, timeout=LEASE + 2)
        assert time.monotonic() - killed <= LEASE + 1
