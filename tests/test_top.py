"""`drums top` over two agents that stand for two hosts (host names of their own), each with a
static graph of one node: a process that burns a core on one, one that mostly sleeps on the other."""
import contextlib
import subprocess
import sys

from tests.agentproc import running_agent, scrape
from tests.graph.test_hosts import named

PROBES = ("--probe", "host", "--probe", "process", "--probe", "sched", "--graph", "static")
BURN = "import time\nwhile True: pass"
SLEEP = "import time\nwhile True: time.sleep(0.1)"  # idle, but it runs now and then


def graph(tmp_path, node: str, marker: str) -> str:
    path = tmp_path / f"{node}.yaml"
    path.write_text(f"nodes:\n  - name: /{node}\n    process: '{marker}'\ntopics: []\n")
    return str(path)


def test_top_shows_every_host_and_node_with_rates_and_cleans_up(tmp_path):
    with contextlib.ExitStack() as stack:
        procs = {name: subprocess.Popen([sys.executable, "-c", code, f"{name}-marker"])
                 for name, code in (("burner", BURN), ("sleeper", SLEEP))}
        for p in procs.values():
            stack.callback(p.wait)
            stack.callback(p.kill)
        urls = [stack.enter_context(running_agent(*PROBES, "--graph-file", graph(tmp_path, name, f"{name}-marker"),
                                                  under=named(host))).rsplit("/", 1)[0]
                for host, name in (("top-a", "burner"), ("top-b", "sleeper"))]
        out = subprocess.run([sys.executable, "-m", "drums", "top", "--once", "--interval", "0.5",
                              *(a for u in urls for a in ("--agent", u))],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0 and out.stderr == "", out.stderr
        lines = out.stdout.splitlines()
        assert lines[0] == "drums top  2 hosts, 2 nodes, every 0.5 s  (Ctrl-C to quit)"
        hosts = {line.split()[0]: line.split()[1:] for line in lines[3:5]}
        assert set(hosts) == {"top-a", "top-b"}
        assert all(0 <= float(h[0]) <= 100 and 0 < float(h[1]) < 100 for h in hosts.values()), hosts
        nodes = {line.split()[1]: line.split() for line in lines[7:9]}
        # Sorted by CPU: the burner first, with a core's worth (less what other work took from it).
        assert [line.split()[1] for line in lines[7:9]] == ["/burner", "/sleeper"]
        assert nodes["/burner"][0] == "top-a" and nodes["/burner"][2] == str(procs["burner"].pid)
        assert 60 <= float(nodes["/burner"][3]) <= 105, nodes
        assert nodes["/sleeper"][0] == "top-b" and float(nodes["/sleeper"][3]) < 5, nodes
        assert float(nodes["/sleeper"][4]) > 1  # resident MB of a Python process
        # The jobs it made are gone with it.
        assert all('"jobs": []' in scrape(u + "/drums/v1/jobs") for u in urls)


def test_top_of_an_agent_that_is_not_there_is_one_line():
    out = subprocess.run([sys.executable, "-m", "drums", "top", "--once", "--agent", "http://127.0.0.1:1"],
                         capture_output=True, text=True, timeout=30)
    assert (out.returncode, out.stdout, out.stderr) == (2, "", "drums: http://127.0.0.1:1: Connection refused\n")
