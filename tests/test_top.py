"""`drums top` over agents that stand for hosts of their own (host names of their own), each with
a static graph: one node that burns a core, one that mostly sleeps. What --once and --json print
against what the processes do; one agent of two that stops; bad input in one line."""
from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time

import psutil
import pytest

from tests.agentproc import running_agent, scrape
from tests.graph.test_hosts import named
from tests.top.pilot import number, row, run, shown, until

PROBES = ("--probe", "host", "--probe", "process", "--probe", "sched", "--graph", "static")
BURN = "while True: pass"
SLEEP = "import time\nwhile True: time.sleep(0.1)"  # idle, but it runs now and then


def graph(tmp_path, node: str) -> str:
    path = tmp_path / f"{node}.yaml"
    path.write_text(f"nodes:\n  - name: /{node}\n    process: '{node}-marker'\ntopics: []\n")
    return str(path)


@contextlib.contextmanager
def agent_with(tmp_path, host: str, node: str, code: str):
    """An agent named `host` whose graph is one node, a process of its own running `code`;
    yields (the agent's base URL, the node's PID)."""
    proc = subprocess.Popen([sys.executable, "-c", code, f"{node}-marker"])
    try:
        with running_agent(*PROBES, "--graph-file", graph(tmp_path, node), under=named(host)) as url:
            yield url.rsplit("/", 1)[0], proc.pid
    finally:
        proc.kill()
        proc.wait()


@pytest.fixture(scope="module")
def agents(tmp_path_factory):
    """{host: (URL, the PID of its node)}: top-a with /burner, top-b with /sleeper."""
    tmp = tmp_path_factory.mktemp("graphs")
    with agent_with(tmp, "top-a", "burner", BURN) as a, agent_with(tmp, "top-b", "sleeper", SLEEP) as b:
        yield {"top-a": a, "top-b": b}


def top(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "drums", "top", *argv], capture_output=True, text=True, timeout=60)


def urls(agents) -> list[str]:
    return [a for url, _ in agents.values() for a in ("--agent", url)]


def no_jobs_left(agents) -> bool:
    return all(json.loads(scrape(url + "/drums/v1/jobs")) == {"jobs": []} for url, _ in agents.values())


def test_once_prints_every_host_and_node_with_what_their_processes_do(agents):
    burning = psutil.Process(agents["top-a"][1])
    before, started = sum(burning.cpu_times()[:2]), time.monotonic()
    out = top("--once", "--interval", "0.5", *urls(agents))
    share = 100 * (sum(burning.cpu_times()[:2]) - before) / (time.monotonic() - started)
    assert out.returncode == 0 and out.stderr == "", out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].endswith("hosts: top-a up, top-b up  every 0.5 s"), lines[0]
    assert lines[1].split() == ["HOST", "NAME", "PID", "CPU▼", "MEM", "RUNQ99", "PUB", "TAKE", "TX", "RX"]
    nodes = {cells[1]: cells for cells in (line.split() for line in lines[2:]) if cells[1].startswith("/")}
    assert set(nodes) == {"/burner", "/sleeper"}, nodes
    burner, sleeper = nodes["/burner"], nodes["/sleeper"]
    assert burner[0] == "top-a" and burner[2] == str(agents["top-a"][1])
    assert sleeper[0] == "top-b" and sleeper[2] == str(agents["top-b"][1])
    # What the kernel counted for the burner over top's run, within which top's half second lies:
    # a core's worth, less what the other work of this 2-core machine took from it (a loaded
    # fresh-clone run read 27%); never more than a core. A sleeping process reads under 5.
    assert share / 2 <= number(burner[3]) <= 105 and number(sleeper[3]) < 5, (burner, share, sleeper)
    assert number(" ".join(sleeper[4:6])) > 1 << 20  # resident memory of a Python process
    assert no_jobs_left(agents)  # the jobs it made are gone with it


def test_json_prints_one_view_for_scripts(agents):
    out = top("--json", "--view", "hosts", "--interval", "0.5", *urls(agents))
    assert out.returncode == 0 and out.stderr == "", out.stderr
    doc = json.loads(out.stdout)
    assert doc["view"] == "hosts" and doc["interval"] == 0.5
    assert [(a["host"], a["state"], a["error"]) for a in doc["agents"]] == [("top-a", "up", None), ("top-b", "up", None)]
    hosts = {r["host"]: r for r in doc["rows"] if not r.get("group")}
    memory = psutil.virtual_memory()
    for name in ("top-a", "top-b"):  # two names, one machine
        assert 0 < hosts[name]["cpu_percent"] <= 100
        assert abs(hosts[name]["memory_percent"] - 100 * memory.used / memory.total) < 3, hosts[name]
        assert any(r["interface"] == "lo" for r in doc["rows"] if r.get("group") == f"host|{name}")
    assert no_jobs_left(agents)


def test_one_agent_of_two_that_stops_leaves_the_others_rows_and_shows_down(agents, tmp_path):
    url_a, _ = agents["top-a"]
    with contextlib.ExitStack() as third:
        url_c, _ = third.enter_context(agent_with(tmp_path, "top-c", "third", SLEEP))

        async def scenario(app, pilot):
            await until(pilot, lambda: row(app, NAME="/third") and row(app, NAME="/burner"), timeout=10)
            third.close()  # top-c's agent stops
            await until(pilot, lambda: not [r for r in shown(app) if r["NAME"] == "/third"], timeout=10)
            assert row(app, NAME="/burner")["HOST"] == "top-a"
            await pilot.press("h")
            await until(pilot, lambda: row(app, HOST="top-c", IFACE="all")["STATE"] == "down", timeout=5)
            assert row(app, HOST="top-a", IFACE="all")["STATE"] == "up"
        run([url_a, url_c], 0.5, scenario, size=(100, 30))


def test_an_agent_that_is_not_there_is_one_line():
    out = top("--once", "--agent", "http://127.0.0.1:1")
    assert (out.returncode, out.stdout, out.stderr) == (2, "", "drums: http://127.0.0.1:1: Connection refused\n")


@pytest.mark.parametrize("argv, error", [
    (["--interval", "0"], "argument --interval: 0 s is outside 0.1-3600 s (see drums top --help)"),
    (["--view", "pods"], "argument --view: invalid choice: 'pods' (choose from 'nodes', 'topics', 'edges', "
                         "'connections', 'hosts', 'anomalies') (see drums top --help)"),
    (["--once", "--json"], "--once prints text and --json JSON: one of them"),
    (["--once", "--agent", "ftp://127.0.0.1:1"], "--agent ftp://127.0.0.1:1: an agent's URL is http://HOST:PORT"),
    ([], "the live view needs a terminal: --once or --json print one view for scripts"),
])
def test_bad_input_is_one_line(argv, error):
    out = top(*argv)
    # Python 3.13's argparse names the choices without quotes
    said = out.stderr if sys.version_info < (3, 13) or "choose from" not in error else \
        out.stderr.replace("choose from ", "choose from '").replace(", ", "', '").replace(") (see", "') (see")
    assert (out.returncode, out.stdout, said) == (2, "", f"drums: {error}\n")
