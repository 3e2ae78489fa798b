"""Loss is never silent: the agent says in one line, at most once a minute per probe, when a probe
lost events to a full BPF map or to runs of its programs the kernel skipped, or a map of it is
nearly full. A stand-in probe reports the loss: filling the kernel's maps here would take 16,384
live processes."""
from __future__ import annotations

import logging

from drums import agent as agentmod
from drums.agent import Agent
from drums.metrics import Snapshot
from drums.probes.base import Probe
from drums.proctable import ProcessTable


class Lossy(Probe):
    """Reports what the test sets, as a BPF probe's status would after a read of its maps."""
    name = "lossy"

    def start(self) -> None:
        self.status.attached = True

    def collect(self, snap: Snapshot) -> None:
        pass


def test_drops_and_full_maps_are_said_once_a_minute(caplog, monkeypatch):
    clock = [1000.0]
    monkeypatch.setattr(agentmod.time, "monotonic", lambda: clock[0])
    probe = Lossy()
    agent = Agent([probe], ProcessTable())
    agent.start()
    caplog.set_level(logging.WARNING, logger="drums")

    def said() -> list[str]:
        lines = [r.getMessage() for r in caplog.records]
        caplog.clear()
        return lines

    agent.collect()
    assert said() == []  # nothing lost, nothing full: nothing to say
    probe.status.dropped = 7
    probe.status.map_fill = {"threads": 0.95, "sockets": 0.5}
    agent.collect()
    assert said() == ["probe lossy: 7 events lost to full BPF maps; map threads 95% full "
                      "(drums_probe_dropped_events_total, drums_probe_missed_runs_total, drums_probe_map_fill_ratio)"]
    probe.status.dropped = 9
    clock[0] += 30
    agent.collect()
    assert said() == []  # within the minute: counted, not said again
    clock[0] += 31
    agent.collect()
    assert said() == ["probe lossy: 2 events lost to full BPF maps; map threads 95% full "
                      "(drums_probe_dropped_events_total, drums_probe_missed_runs_total, drums_probe_map_fill_ratio)"]
    probe.status.map_fill = {"threads": 0.2}
    clock[0] += 61
    agent.collect()
    assert said() == []  # no new loss, nothing full
    probe.status.missed = 3  # a preempted program's CPU skipped three runs
    clock[0] += 61
    agent.collect()
    assert said() == ["probe lossy: 3 runs skipped by the kernel "
                      "(drums_probe_dropped_events_total, drums_probe_missed_runs_total, drums_probe_map_fill_ratio)"]
    assert agent.collect().values(agentmod.PROBE_MISSED) == {("lossy",): 3}
