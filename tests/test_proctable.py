"""The process table of an agent that reports only its own network namespace (--own-netns)."""
import os
import subprocess
import sys
import time

import pytest

from drums.proctable import OWN_NETNS, SETTLE, ProcessTable, netns


def wait_until(check, within: float = 10):
    deadline = time.monotonic() + within
    while not check():
        assert time.monotonic() < deadline
        time.sleep(0.01)


@pytest.fixture
def table(monkeypatch):
    monkeypatch.setenv(OWN_NETNS, "1")
    return ProcessTable()


def test_a_process_listed_before_it_moved_into_our_network_namespace_is_ours_once_it_has(table):
    # As `nsenter --net=... node` starts a node: the process exists, in another namespace, for a
    # moment before it joins ours (here until told to). A listing in that moment must not keep it out.
    ours = f"/proc/{os.getpid()}/ns/net"
    mover = subprocess.Popen(["unshare", "--net", "sh", "-c", f"read go; exec nsenter --net={ours} sleep 60"],
                             stdin=subprocess.PIPE, text=True)
    stayer = subprocess.Popen(["unshare", "--net", "sleep", "60"])
    try:
        wait_until(lambda: netns("/proc", mover.pid) not in (None, table.netns))
        wait_until(lambda: netns("/proc", stayer.pid) not in (None, table.netns))
        table.refresh()
        assert mover.pid not in table.pids() and stayer.pid not in table.pids()
        mover.stdin.write("go\n")
        mover.stdin.flush()
        wait_until(lambda: netns("/proc", mover.pid) == table.netns and table.name(mover.pid) == "" and
                   open(f"/proc/{mover.pid}/comm").read() == "sleep\n")
        table.refresh()
        assert table.name(mover.pid) == "sleep" and stayer.pid not in table.pids()
        time.sleep(SETTLE)  # settled: the one that stayed is not looked at again, and still not ours
        table.refresh()
        table.refresh()
        assert mover.pid in table.pids() and stayer.pid not in table.pids()
    finally:
        for p in (mover, stayer):
            p.kill()
            p.wait()


def test_the_table_says_whose_names_may_have_changed_since_a_refresh(tmp_path):
    """What the sched probe asks so as not to compare every process's name at each collect. A /proc
    of our own: on a busy host any process may start between two refreshes of the real one."""
    from drums.proctable import RENAMES_KEPT

    def process(pid: int, name: str) -> None:
        (tmp_path / str(pid)).mkdir(exist_ok=True)
        (tmp_path / str(pid) / "comm").write_text(name + "\n")

    process(1, "init")
    table = ProcessTable(str(tmp_path))
    table.refresh(None)
    first = table.refreshes
    assert table.renamed_since(first - 1) is None  # that refresh read every name
    process(42, "python3")
    table.refresh(set())
    assert table.renamed_since(first) == {42} and table.name(42) == "python3"  # new
    process(42, "dozer")
    table.refresh(set())
    assert table.renamed_since(first + 1) == set() and table.name(42) == "python3"  # not told
    table.refresh({42}, complete=True)
    assert table.renamed_since(first + 1) == {42} and table.name(42) == "dozer"
    assert table.renamed_since(first) == {42}
    process(43, "ghost")  # not listed: the sched probe said nothing came, went or changed its name
    table.refresh(set(), complete=True)
    assert table.renamed_since(table.refreshes - 1) == set() and not table.alive(43)
    for _ in range(RENAMES_KEPT):
        table.refresh(set(), complete=True)
    assert table.renamed_since(first + 1) is None  # too long ago to say
    assert table.alive_among([42, 43, 2 ** 22 + 1]) == {42}
