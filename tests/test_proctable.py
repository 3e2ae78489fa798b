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


def test_the_table_says_whose_names_may_have_changed_since_a_refresh():
    """What the sched probe asks so as not to compare every process's name at each collect."""
    from drums.proctable import RENAMES_KEPT
    table = ProcessTable()
    table.refresh(None)
    first = table.refreshes
    assert table.renamed_since(first - 1) is None  # that refresh read every name
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.readline(); "
                              "open('/proc/self/comm', 'w').write('dozer'); sys.stdin.read()"],
                             stdin=subprocess.PIPE, text=True)
    try:
        table.refresh(set())
        assert table.renamed_since(first) == {child.pid}  # new
        name = table.name(child.pid)
        child.stdin.write("rename\n")
        child.stdin.flush()
        wait_until(lambda: open(f"/proc/{child.pid}/comm").read() == "dozer\n")
        table.refresh(set())
        assert table.renamed_since(first + 1) == set() and table.name(child.pid) == name != "dozer"  # not told
        table.refresh({child.pid}, complete=True)
        assert table.renamed_since(first + 1) == {child.pid} and table.name(child.pid) == "dozer"
        assert table.renamed_since(first) == {child.pid}
        table.refresh(set(), complete=True)  # nothing came or changed: /proc not even listed
        assert table.renamed_since(table.refreshes - 1) == set()
        for _ in range(RENAMES_KEPT):
            table.refresh(set(), complete=True)
        assert table.renamed_since(first + 1) is None  # too long ago to say
        assert table.alive_among([child.pid, 2 ** 22 + 1]) == {child.pid}
    finally:
        child.kill()
        child.wait()
        child.stdin.close()
