"""Selection of processes by PID, name pattern and cgroup, through the agent and the real sched probe."""
import os
import subprocess

import pytest

from drums.agent import Agent, Selection
from drums.budget import Budget
from drums.errors import UsageError
from tests.conftest import eventually, series, wait_until

# A hierarchy to make a test group in: v1's pids controller here, else the cgroup2 root. The
# selection matches a process's path in any hierarchy it is in.
CGROUP_ROOT = next(d for d in ("/sys/fs/cgroup/pids", "/sys/fs/cgroup/unified", "/sys/fs/cgroup")
                   if os.path.exists(os.path.join(d, "cgroup.procs")))


def pids_with_series(snap) -> set[int]:
    return {int(labels[0]) for labels in series(snap, "drums_process_cpu_seconds_total") if labels[0] != "other"}


@pytest.fixture
def sleepers():
    procs = [subprocess.Popen(["sleep", "60"]) for _ in range(2)]
    procs.append(subprocess.Popen(["cat"], stdin=subprocess.PIPE))
    # Popen returns once exec closed its pipe, which the kernel does just before it names the
    # process: until then /proc says "python" (the agent reads the name again after the exec).
    for p in procs:
        wait_until(lambda: open(f"/proc/{p.pid}/comm").read().strip() == p.args[0], f"{p.args[0]}'s exec")
    yield procs
    for p in procs:
        p.kill()
        p.wait()


def collect(sched_probe, proctable, selection):
    return Agent([sched_probe], proctable, selection, Budget({"process": 1000, "thread": 1000})).collect()


def test_by_pid(sched_probe, proctable, sleepers):
    target = sleepers[0].pid
    assert pids_with_series(collect(sched_probe, proctable, Selection.parse(pids=[target]))) == {target}


def test_by_name_pattern(sched_probe, proctable, sleepers):
    rows = series(collect(sched_probe, proctable, Selection.parse(names=["^cat$"])), "drums_process_cpu_seconds_total")
    rows.pop(("other", "other"), None)  # what the processes counted before their series began
    got = {int(pid) for pid, _ in rows}
    assert sleepers[2].pid in got and sleepers[0].pid not in got
    # Names as the collect read them: another "cat" on the host may have exited since.
    assert {name for _, name in rows} == {"cat"}


def test_by_command_line_and_by_node_name(sched_probe, proctable, sleepers):
    """A Python node's process is named "python": its command line and its nodes name it better."""
    import sys

    from drums.graph.model import Graph, GraphState, Node
    marker = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()", "planner-5e1c"],
                              stdin=subprocess.PIPE)
    try:
        graph = Graph()
        graph.update(GraphState(nodes=[Node("/driver", "here", sleepers[1].pid, "static")]))

        def chosen(names, pids):
            def check():  # a process just started may not have run yet: no CPU row until it has
                agent = Agent([sched_probe], proctable, Selection.parse(names=names),
                              Budget({"process": 1000, "thread": 1000}), graph)
                assert pids_with_series(agent.collect()) == pids
            eventually(check, timeout=5)
        chosen(["planner-5e1c"], {marker.pid})
        chosen(["^/driver$"], {sleepers[1].pid})
    finally:
        marker.kill()
        marker.wait()


def test_by_cgroup(sched_probe, proctable, sleepers, tmp_path):
    group = os.path.join(CGROUP_ROOT, f"drums-test-{os.getpid()}")
    os.mkdir(group)
    try:
        with open(os.path.join(group, "cgroup.procs"), "w") as f:
            f.write(str(sleepers[1].pid))
        got = pids_with_series(collect(sched_probe, proctable, Selection.parse(cgroups=[group[len(CGROUP_ROOT):]])))
        assert got == {sleepers[1].pid}
    finally:
        with open(os.path.join(CGROUP_ROOT, "cgroup.procs"), "w") as f:
            f.write(str(sleepers[1].pid))
        os.rmdir(group)


def test_bad_selections_are_usage_errors():
    with pytest.raises(UsageError, match="no such process"):
        Selection.parse(pids=[2 ** 22 + 7])
    with pytest.raises(UsageError, match="not a regular expression"):
        Selection.parse(names=["(["])
