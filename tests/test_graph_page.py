"""The agent's /graph page and `drums graph --agent`: the graph with the agent's metrics on it."""
import json
import os
import subprocess
import sys
import urllib.error
import urllib.request

import networkx as nx
import pytest

from tests.agentproc import free_port, running_agent, samples, scrape
from tests.conftest import eventually

# Burns argv[1] s of CPU, says how much it used, then waits without running.
BURNER = ("import sys, time\nwhile time.process_time() < float(sys.argv[1]): pass\n"
          "print(time.process_time(), flush=True)\nsys.stdin.read()")


def test_graph_page_carries_node_metrics(tmp_path):
    """/graph is the agent's graph with its metrics on the nodes: the same values as /metrics, in
    every format, and through `drums graph --agent`."""
    marker = f"burner-{os.getpid()}"
    (tmp_path / "robot.yaml").write_text(f"nodes:\n  - name: /burner\n    process: {marker}\n"
                                         "topics:\n  - name: /t\n    publishers: [/burner]\n")
    with running_agent("--graph", "static", "--graph-file", str(tmp_path / "robot.yaml"),
                       "--probe", "sched", "--probe", "process") as url:
        base = url.rsplit("/", 1)[0]
        child = subprocess.Popen([sys.executable, "-c", BURNER, "0.3", marker], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True)
        try:
            burned = float(child.stdout.readline())

            def node():
                data = json.loads(scrape(base + "/graph?format=json"))
                found = next((v for v in data["nodes"] if v["id"] == "node:/burner" and v.get("pid")), None)
                assert found and "cpu_seconds_total" in found, f"/burner not mapped with its CPU: {found}"
                # The child then waits on stdin, and its CPU stays put from one collect to the next;
                # until it is blocked there (a busy host may leave it a few more us), two may differ.
                metrics = samples(scrape(url), "drums_node_cpu_seconds_total")
                assert metrics == {(("node", "/burner"),): found["cpu_seconds_total"]}
                return found
            found = eventually(node, timeout=10)
            assert found["pid"] == child.pid and found["mapped_by"] == "static"
            assert burned <= found["cpu_seconds_total"] <= burned + 0.05
            assert found["resident_memory_bytes"] > 0

            out = subprocess.run([sys.executable, "-m", "drums", "graph", "--agent", base, "--format", "graphml"],
                                 capture_output=True, text=True, timeout=30)
            assert out.returncode == 0, out.stderr
            assert nx.parse_graphml(out.stdout).nodes["node:/burner"]["cpu_seconds_total"] == found["cpu_seconds_total"]
            text = subprocess.run([sys.executable, "-m", "drums", "graph", "--agent", base], capture_output=True,
                                  text=True, timeout=30).stdout
            assert "node /burner (mapped by static) " in text and f"cpu_seconds_total={found['cpu_seconds_total']}" in text

            svg = scrape(base + "/graph?format=svg")  # drawn by Graphviz in the agent
            assert svg.startswith("<?xml") and ">/burner</text>" in svg and ">/t</text>" in svg
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(base + "/graph?format=png", timeout=5)
            assert (e.value.code, e.value.read()) == (400, b"format 'png': one of text, json, dot, svg, graphml\n")
            assert "drums_node_cpu_seconds_total" in scrape(url)
        finally:
            child.kill()
            child.wait()


def test_graph_from_an_agent_that_is_not_there_is_one_line():
    port = free_port()
    out = subprocess.run([sys.executable, "-m", "drums", "graph", "--agent", f"http://127.0.0.1:{port}"],
                         capture_output=True, text=True, timeout=30)
    assert (out.returncode, out.stdout) == (2, "")
    assert out.stderr == f"drums: --agent http://127.0.0.1:{port}: Connection refused\n"
