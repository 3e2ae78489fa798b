"""A probe that fails to collect costs its series one scrape, and nothing after: the real sched
probe fails once, midway through its collect (after its processes' rows, before its threads'),
and the agent's budget goes on from the collect before it."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from drums.agent import Agent, Selection
from drums.budget import Budget
from drums.errors import KernelError
from drums.metrics import Snapshot
from tests.conftest import series

OTHER_THREADS = ("other", "other", "other")


# Eight threads burn 0.3 s of CPU each under the probe, then sleep: most are summed into `other`.
BURNERS = """
import threading, time
burnt = threading.Barrier(9)
def burn():
    end = time.thread_time() + 0.3
    while time.thread_time() < end:
        pass
    burnt.wait()
    threading.Event().wait()
for _ in range(8):
    threading.Thread(target=burn, daemon=True).start()
burnt.wait()
print("burnt", flush=True)
time.sleep(60)
"""


@pytest.fixture
def burners():
    child = subprocess.Popen([sys.executable, "-c", BURNERS], stdout=subprocess.PIPE, text=True)
    yield child
    child.kill()
    child.wait()


def test_a_probe_that_fails_once_shows_none_of_its_rows_then_counts_nothing_twice(sched_probe, proctable, burners,
                                                                                monkeypatch):
    sched_probe.collect(Snapshot())  # the burners' threads are counted from their start
    assert burners.stdout.readline() == "burnt\n"
    agent = Agent([sched_probe], proctable, Selection(), Budget({"process": 3, "thread": 3}))
    t1 = time.monotonic()  # before the first collect: its reads of the maps come after
    first = agent.collect()
    real = sched_probe._thread_columns

    def fail(*args):
        raise KernelError("the thread map could not be read")
    monkeypatch.setattr(sched_probe, "_thread_columns", fail)
    failed = agent.collect()
    monkeypatch.setattr(sched_probe, "_thread_columns", real)
    last, t3 = agent.collect(), time.monotonic()

    # The failed scrape says so, and shows no row of the probe: none half made.
    assert series(failed, "drums_probe_collect_success", probe="sched") == {("sched",): 0}
    for name in ("drums_process_cpu_seconds_total", "drums_thread_cpu_seconds_total"):
        assert series(failed, name) == {} and series(last, name)
    # Thread CPU summed into `other` grew by what the host's CPUs could run between the two good
    # scrapes, and by all of what each thread that lost its series had (it enters `other` whole).
    # Had the budget taken the failed scrape's missing threads as ended, every folded thread would
    # have come back as new and added all its CPU time again: the burners' 0.3 s each.
    (before, kept), (after, _) = ((rows.pop(OTHER_THREADS), rows) for rows in
                                  (series(s, "drums_thread_cpu_seconds_total") for s in (first, last)))
    shown = series(last, "drums_thread_cpu_seconds_total")
    demoted = [cpu for labels, cpu in kept.items() if labels not in shown]
    # A thread on a CPU at the first read is counted as /proc has it, up to date at the last tick:
    # up to a tick (4 ms at 250 Hz) a CPU more shows at the last read.
    ran = os.cpu_count() * (t3 - t1)
    ticks = os.cpu_count() * 0.004
    assert 0 <= after - before <= ran * (1 + len(demoted)) + sum(demoted) + ticks + 0.01, (before, after, demoted)
    assert before >= 1.0 > 2 * ran  # the burners folded: what counting them twice would add, and more
