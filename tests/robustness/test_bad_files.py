"""Bad and hostile files and patterns given to `drums agent`: one line and exit 2 at start, in
bounded time and memory, or (a pattern) matched in linear time while the agent keeps answering."""
from __future__ import annotations

import resource
import subprocess
import sys
import time

import pytest

from tests.agentproc import running_agent, scrape
from tests.conftest import eventually

BOMB = "\n".join(["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"] +
                 [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, "
                  f"*a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 10)]) + "\nnodes: *a9\n"


def limited() -> None:
    """512 MiB of heap: an expanded bomb would need gigabytes, and end in a MemoryError traceback."""
    resource.setrlimit(resource.RLIMIT_DATA, (512 << 20, 512 << 20))


def agent(*argv: str) -> tuple[subprocess.CompletedProcess, float]:
    """`drums agent ARGV` to its end, with its heap limited: (result, seconds)."""
    began = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "drums", "agent", "--port", "0", "--stream-port", "0", *argv],
                          capture_output=True, text=True, timeout=60, preexec_fn=limited)
    return done, time.monotonic() - began


@pytest.mark.parametrize("text, says", [
    (BOMB, "not YAML (anchors and aliases are not taken (line 1))"),
    ("nodes: [{name: /a}]\n" + "#" * (2 << 20), "not YAML (over 1024 KiB)"),
    ("nodes: [{name: /a}]\ntopics: [{name: /t, publishers: [[/a]]}]", "topics[0]: node ['/a'] is not among the nodes"),
    ("nodes: [{name: /a, process: '(a)\\1'}]", "nodes[0]: process is not a regular expression RE2 takes"),
    ("nodes: [{name: /a, process: [x]}]", "nodes[0]: process is a regular expression, not list"),
])
def test_a_bad_static_graph_is_one_line_at_start(tmp_path, text, says):
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    done, seconds = agent("--graph", "static", "--graph-file", str(path), "--probe", "host")
    assert (done.returncode, done.stdout, done.stderr.count("\n")) == (2, "", 1), done.stderr
    assert done.stderr.startswith(f"drums: {path}: ") and says in done.stderr, done.stderr
    assert seconds < 10


def test_a_backtracking_pattern_is_matched_in_linear_time(tmp_path):
    """(a+)+$ against a command line of 60 a's and a '!' takes a backtracking engine longer than
    the age of the universe; the agent's graph must still come, and its scrapes answer."""
    marker = "a" * 60 + "!"
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()", marker], stdin=subprocess.PIPE)
    path = tmp_path / "robot.yaml"
    path.write_text("nodes: [{name: /greedy, process: '(a+)+$'}, {name: /worker, process: 'a{60}!'}]\n")
    try:
        with running_agent("--graph", "static", "--graph-file", str(path), "--probe", "host",
                           "--process-name", "(a+)+$") as url:
            def mapped():
                text = scrape(url.rsplit("/", 1)[0] + "/graph?format=text")
                assert f"process {child.pid} python" in text and "node /worker (mapped by static)" in text, text
            eventually(mapped, timeout=10)
    finally:
        child.kill()
        child.wait()
