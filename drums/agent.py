"""The host agent: starts the probes, and on each scrape joins what they read into one snapshot.

A probe that cannot start degrades only itself, visibly (drums_probe_attached), unless the agent
runs with strict=True. A probe that fails while collecting is marked failed for that collect and
the others still export.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from drums import linear_re
from drums.budget import Budget
from drums.errors import DrumsError, UsageError
from drums.graph.join import GID_HEX, INFINITE_NS, join
from drums.graph.model import ENTITIES, Graph
from drums.metrics import COUNTER, GAUGE, Columns, Metric, Snapshot
from drums.probes.base import Probe
from drums.proctable import ProcessTable
from drums.selfcost import BUSY, MEMORY_EVERY, TreeCost

log = logging.getLogger("drums")

PROBE_ATTACHED = Metric("drums_probe_attached", GAUGE,
                        "1 if the probe is collecting, by the attach type in use; 0 and type none if not",
                        ("probe", "attach_type"))
PROBE_DURATION = Metric("drums_probe_collect_duration_seconds", GAUGE,
                        "How long the probe's last collect took", ("probe",))
PROBE_SUCCESS = Metric("drums_probe_collect_success", GAUGE, "1 if the probe's last collect succeeded",
                       ("probe",))
PROBE_MAP_FILL = Metric("drums_probe_map_fill_ratio", GAUGE,
                        "Used fraction of each of the probe's BPF hash maps", ("probe", "map"))
PROBE_MAP_MEMORY = Metric("drums_probe_map_memory_bytes", GAUGE,
                          f"Kernel memory the probe's BPF maps hold (read every {MEMORY_EVERY:g} s; not in "
                          "drums_agent_unique_memory_bytes)", ("probe",))
PROBE_DROPPED = Metric("drums_probe_dropped_events_total", COUNTER,
                       "Events the probe could not count because a BPF map was full", ("probe",))
PROBE_MISSED = Metric("drums_probe_missed_runs_total", COUNTER,
                      "Runs of the probe's BPF programs the kernel skipped, one of them running on that CPU "
                      "already (a preempted one, on PREEMPT_RT): events not counted (counted from Linux 5.12)",
                      ("probe",))
FOLDED_TOTAL = Metric("drums_budget_folded_entities_total", COUNTER,
                      "Entities that went over the cardinality budget into the series labelled other, "
                      "since the agent started", ("kind",))
FOLDED = Metric("drums_budget_folded_entities", GAUGE,
                "Entities over the cardinality budget, summed into the series labelled other", ("kind",))
AGENT_COLLECT = Metric("drums_agent_collect_duration_seconds", GAUGE,
                       "How long this snapshot took to collect: every probe, selection and budget")
# role: agent (the agent process), graph (its ROS 2 graph reader, which publishes /diagnostics too when
# both are on), diag (the /diagnostics publisher of an agent without the ROS 2 graph).
AGENT_CPU = Metric("drums_agent_cpu_seconds_total", COUNTER,
                   "CPU time used by the agent's processes: the agent and each helper it started, by role", ("role",))
AGENT_RSS = Metric("drums_agent_resident_memory_bytes", GAUGE,
                   f"Resident memory of the agent's processes, by role (each read again once it has used {BUSY:g} s "
                   f"of CPU since, else every {MEMORY_EVERY:g} s)", ("role",))
AGENT_USS = Metric("drums_agent_unique_memory_bytes", GAUGE,
                   "Memory only the agent's processes use, by role (private pages: what stopping them would "
                   f"free; each read again once it has used {BUSY:g} s of CPU since, else every {MEMORY_EVERY:g} s)",
                   ("role",))
GRAPH_STALE = Metric("drums_graph_stale", GAUGE,
                     "1 while the graph adapter fails (the last good graph is kept), else 0", ("adapter",))
GRAPH_TRUNCATED = Metric("drums_graph_truncated", GAUGE,
                         "1 while the graph holds only part of what the middleware said (over the adapter's "
                         "limits), else 0", ("adapter",))
GRAPH_ENTITIES = Metric("drums_graph_entities", GAUGE, "Entities in the graph, by kind", ("kind",))
LOSS_SAID_EVERY = 60.0  # seconds: at most one line per probe about lost events or full maps
NEARLY_FULL = 0.9  # a map this full is said to be, before it loses anything
SELF_METRICS = (GRAPH_STALE, GRAPH_TRUNCATED, GRAPH_ENTITIES, PROBE_ATTACHED, PROBE_DURATION, PROBE_SUCCESS, PROBE_MAP_FILL,
                PROBE_MAP_MEMORY, PROBE_DROPPED, PROBE_MISSED, FOLDED, FOLDED_TOTAL, AGENT_COLLECT, AGENT_CPU, AGENT_RSS, AGENT_USS)


@dataclass
class Selection:
    """Which processes are monitored: all by default, else those matching any criterion."""

    pids: set[int] = field(default_factory=set)
    name_patterns: list = field(default_factory=list)  # linear_re patterns
    cgroups: list[str] = field(default_factory=list)

    @classmethod
    def parse(cls, pids=(), names=(), cgroups=()) -> "Selection":
        sel = cls(set(pids), [], list(cgroups))
        for p in pids:
            if p <= 0:
                raise UsageError(f"--pid {p}: a PID is a positive number")
            if not os.path.exists(f"/proc/{p}"):
                raise UsageError(f"--pid {p}: no such process")
        for n in names:
            try:
                sel.name_patterns.append(linear_re.compile(n))
            except ValueError as e:
                raise UsageError(f"--process-name {n!r}: {e}") from None
        return sel

    @property
    def everything(self) -> bool:
        return not (self.pids or self.name_patterns or self.cgroups)

    def matches(self, pid: int, names: list[str]) -> bool:
        """Whether the process is chosen; `names`: what a pattern may match (its name, its command
        line, the middleware nodes it holds)."""
        if pid in self.pids or any(p.search(n) for p in self.name_patterns for n in names):
            return True
        if self.cgroups:
            try:
                with open(f"/proc/{pid}/cgroup") as f:
                    paths = [line.rstrip("\n").split(":", 2)[-1] for line in f]
            except OSError:
                return False
            return any(path.startswith(c) for c in self.cgroups for path in paths)
        return False


def _of_chosen(metric: Metric, rows: list, chosen: set[str]) -> list:
    """The rows of the chosen processes; metrics not about a process pass whole."""
    if "pid" not in metric.labels:
        return rows
    i = metric.labels.index("pid")
    return [row for row in rows if row[0][i] in chosen]


class Agent:
    def __init__(self, probes: list[Probe], proctable: ProcessTable, selection: Selection | None = None,
                 budget: Budget | None = None, graph: Graph | None = None, graph_adapter: str = ""):
        self.probes = probes
        self.graph = graph  # kept current by a Follower; its names label the joined metrics
        self.graph_adapter = graph_adapter
        self.proctable = proctable
        self.selection = selection or Selection()
        self._chose: set[str] = set()  # the PIDs the last collect chose
        self.budget = budget or Budget({})
        self._lock = threading.Lock()
        self._last: Snapshot | None = None  # what collect() or recent() gave last
        self._replaced: list[Probe] = []
        self._reasons: dict[str, str] = {}
        self._durations: dict[str, float] = {}
        self._success: dict[str, int] = {}
        self._tree = TreeCost()
        self._maps_read_at = float("-inf")
        self._loss_said: dict[str, tuple[tuple[int, int], float]] = {}  # probe -> ((drops, runs missed) last said, when)
        self.wanted_pids: Callable[[], set[int]] = set  # processes a client asked for (jobs): always read

    def start(self, strict: bool = False) -> None:
        for i, probe in enumerate(self.probes):
            try:
                probe.start()
                continue
            except DrumsError as e:
                probe.status.attached = False
                probe.status.reason = str(e)
                if strict:
                    raise DrumsError(f"probe {probe.name}: {e} (--strict)") from None
            if probe.fallback is None:
                log.warning("probe %s not attached: %s", probe.name, probe.status.reason)
                continue
            replacement = probe.fallback()
            try:
                replacement.start()
            except DrumsError as e:
                log.warning("probe %s not attached: %s; fallback failed too: %s", probe.name,
                            probe.status.reason, e)
                continue
            log.warning("probe %s uses %s: %s. Missing: %s", probe.name, replacement.status.attach_type,
                        probe.status.reason, replacement.status.reason)
            replacement.status.reason = f"{probe.status.reason}; missing: {replacement.status.reason}"
            self.probes[i] = replacement
            self._replaced.append(probe)  # it may have pinned programs before it failed

    def stop(self, unload: bool) -> None:
        for probe in self.probes + self._replaced:
            if unload:
                probe.unload()
            else:
                probe.stop()

    def collect(self) -> Snapshot:
        """One consistent snapshot; concurrent scrapes wait for each other rather than interleave."""
        with self._lock:
            self._last = self._collect()
            return self._last

    def recent(self, max_age: float, after: float = 0.0) -> Snapshot:
        """The last snapshot if its probes were read at most `max_age` seconds ago and later than
        `after` (a scrape's: /diagnostics takes it rather than collect once more, but not the one
        it took last), else a new one."""
        with self._lock:
            last = self._last
            if last is None or last.read_at <= after or time.time() - last.read_at > max_age:
                self._last = self._collect()
            return self._last

    def collect_raw(self, probes: set[str], joined: bool = False) -> Snapshot:
        """A fresh read of the named probes, before selection and budget: every entity with its
        own rows (what jobs sample; nothing else is read); `joined` adds the graph's rows of them."""
        with self._lock:
            raw = self._read(probes)
            for metric, rows in self._joined(raw).series.items() if joined else ():
                raw.rows(metric).extend(rows)
            return raw

    def _joined(self, raw: Snapshot) -> Snapshot:
        """The graph's rows of `raw`: per node, topic and edge."""
        joined = Snapshot()
        if self.graph is not None:
            join(self.graph.entities("node"), self.graph.entities("endpoint"), self.graph.connections(), raw,
                 joined)
        return joined

    def _collect(self) -> Snapshot:
        """The snapshot to export: every probe, joined onto the graph, selected and budgeted."""
        began = time.perf_counter()
        self._want_rtt()
        self._want_deadlines()
        read_at = time.time()
        raw = self._read({p.name for p in self.probes})
        read_at = (read_at + time.time()) / 2
        everything = self.selection.everything and self.proctable.netns is None
        selected = raw if everything else self._select(raw)
        joined = self._joined(selected)  # the processes not selected are in no node's, topic's or edge's rows
        snap = self.budget.apply(selected)
        for metric, rows in joined.series.items():  # bounded by the graph: not budgeted
            snap.rows(metric).extend(rows)
        self._self_metrics(snap)
        snap.add(AGENT_COLLECT, (), time.perf_counter() - began)
        snap.read_at = read_at
        return snap

    def tcp_changes(self) -> int | None:
        """TCP state changes on the host as the tcp probe counts them; None without it (the auto
        graph dumps the connections again only when this moved)."""
        return next((n for n in (p.transitions() for p in self.probes if p.status.attached) if n is not None), None)

    def _want_rtt(self) -> None:
        """RTT is read for the connections that have series of their own, and the graph's edges."""
        pairs = self.budget.kept("connection")
        if self.graph is not None:
            pairs |= {(c.local, c.remote) for c in self.graph.connections() if c.local and c.remote}
        for probe in self.probes:
            probe.want_rtt(pairs)

    def _want_deadlines(self) -> None:
        """The Deadline QoS of the graph's publishers and subscriptions, for the probe that counts
        their misses."""
        deadlines = {}
        if self.graph is not None:
            for e in self.graph.entities("endpoint"):
                ns = e.qos.get("deadline_ns", 0)
                if 0 < ns < INFINITE_NS:
                    deadlines[e.id[:GID_HEX]] = ns
        for probe in self.probes:
            probe.want_deadlines(deadlines)

    def _read(self, names: set[str]) -> Snapshot:
        """The rows of the probes called `names`."""
        self.proctable.refresh(self._renamed(), complete=True)
        for probe in self.probes:
            if probe.status.attached:
                try:
                    self.proctable.tell_ended(probe.ended())
                except Exception as e:  # noqa: BLE001 - the names only: its collect says what failed
                    log.warning("probe %s: ended processes unread: %s", probe.name, e)
        pids = self._process_pids()
        for probe in self.probes:
            probe.set_pids(pids)
        raw = Snapshot()
        for probe in self.probes:
            if not probe.status.attached or probe.name not in names:
                continue
            start = time.perf_counter()
            try:
                probe.collect(raw)
                self._success[probe.name] = 1
            except Exception as e:  # one probe's failure must not cost the others their scrape
                self._success[probe.name] = 0
                raw.leave_out(probe.metrics)
                log.warning("probe %s failed to collect: %s", probe.name, e,
                            exc_info=log.isEnabledFor(logging.DEBUG))
            self._durations[probe.name] = time.perf_counter() - start
            if probe.status.reason != self._reasons.get(probe.name, probe.status.reason):
                log.warning("probe %s: %s", probe.name, probe.status.reason or "recovered")
            self._reasons[probe.name] = probe.status.reason
            self._say_losses(probe)
        return raw

    def _renamed(self) -> set[int] | None:
        """The processes that came, or whose names may have changed, since the last collect, as the
        sched probe saw them; None (list /proc and read every name) without it, or when it lost
        some."""
        for probe in self.probes:
            if probe.status.attached:
                try:
                    renamed = probe.renamed()
                except Exception as e:  # noqa: BLE001 - as a failed collect: the names are read anew
                    log.warning("probe %s: renamed processes unread: %s", probe.name, e)
                    return None
                if renamed is not None:
                    return renamed
        return None

    def _say_losses(self, probe: Probe) -> None:
        """One line, at most every LOSS_SAID_EVERY seconds, when the probe lost events to a full
        map or to runs the kernel skipped since it last said so, or a map of it is nearly full: loss
        is counted and never silent."""
        st = probe.status
        (dropped, missed), at = self._loss_said.get(probe.name, ((0, 0), -LOSS_SAID_EVERY))
        now = time.monotonic()
        full = sorted((m, f) for m, f in st.map_fill.items() if f >= NEARLY_FULL)
        lost = (st.dropped, st.missed or 0)
        if now - at < LOSS_SAID_EVERY or (lost[0] <= dropped and lost[1] <= missed and not full):
            return
        parts = [f"{lost[0] - dropped} events lost to full BPF maps"] if lost[0] > dropped else []
        parts += [f"{lost[1] - missed} runs skipped by the kernel"] if lost[1] > missed else []
        parts += [f"map {m} {f:.0%} full" for m, f in full]
        log.warning("probe %s: %s (drums_probe_dropped_events_total, drums_probe_missed_runs_total, "
                    "drums_probe_map_fill_ratio)", probe.name, "; ".join(parts))
        self._loss_said[probe.name] = (lost, now)

    def _chosen(self) -> set[int]:
        pt = self.proctable
        if self.selection.everything:
            return pt.pids()
        nodes: dict[int, list[str]] = {}
        if self.selection.name_patterns:  # an rclpy node's process is named "python": its nodes say more
            for n in self.graph.entities("node") if self.graph else ():
                nodes.setdefault(n.pid, []).append(n.name)
        # The agent's own command line names the patterns it was given: it is chosen by PID only.
        own = os.getpid()
        return {pid for pid in pt.pids() if (pid != own or pid in self.selection.pids) and self.selection.matches(
            pid, [pt.name(pid), *(pt.cmdline(pid) if self.selection.name_patterns else ()), *nodes.get(pid, ())])}

    def _process_pids(self) -> list[int]:
        """Processes to read from /proc, which costs per process: the graph's nodes, those the
        budget kept at the last collect, then the newest others up to the budget."""
        chosen = self._chosen()
        limit = self.budget.limit("process")
        nodes = [n.pid for n in self.graph.entities("node") if n.pid in chosen] if self.graph else []
        nodes = sorted(self.wanted_pids() & self.proctable.pids()) + nodes
        kept = nodes + [int(pid) for pid in self.budget.kept("process") if pid.isdigit() and int(pid) in chosen]
        rest = sorted(chosen - set(kept), reverse=True)
        return list(dict.fromkeys(kept + rest))[:limit]

    def _select(self, snap: Snapshot) -> Snapshot:
        pids = self._chosen()
        chosen = {str(pid) for pid in pids}
        chosen |= self._ended_chosen(snap, chosen)
        self._chose = chosen
        out = Snapshot()
        out.unread = snap.unread
        for metric, rows in snap.singles.items():
            out.rows(metric).extend(_of_chosen(metric, rows, chosen))
        for metrics, rows in snap.groups.items():
            if isinstance(rows, Columns):  # as _of_chosen: rows about no process pass whole
                out.groups[metrics] = rows.of_processes(pids) if rows.pids is not None else rows
            else:
                out.group_rows(metrics).extend(_of_chosen(metrics[0], rows, chosen))
        return out

    def _ended_chosen(self, snap: Snapshot, chosen: set[str]) -> set[str]:
        """The processes that ended since the last collect and are chosen, whose rows show their
        final totals: those chosen then, and those whose rows' name is (they started and ended in
        between; their command lines, nodes and cgroups are gone with them)."""
        alive, out = {str(pid) for pid in self.proctable.pids()}, set()
        for metric, rows in snap.singles.items():
            if "pid" not in metric.labels or "process" not in metric.labels:
                continue
            i, j = metric.labels.index("pid"), metric.labels.index("process")
            for labels, _ in rows:
                pid = labels[i]
                if pid in chosen or pid in out or pid in alive or not pid.isdigit():
                    continue
                if pid in self._chose or self.selection.matches(int(pid), [labels[j]]):
                    out.add(pid)
        return out

    def _self_metrics(self, snap: Snapshot) -> None:
        now = time.monotonic()
        maps_due = now - self._maps_read_at >= MEMORY_EVERY
        if maps_due:
            self._maps_read_at = now
        for probe in self.probes:
            st = probe.status
            snap.add(PROBE_ATTACHED, (probe.name, st.attach_type if st.attached else "none"), int(st.attached))
            if not st.attached:
                continue
            snap.add(PROBE_DURATION, (probe.name,), self._durations.get(probe.name, 0.0))
            snap.add(PROBE_SUCCESS, (probe.name,), self._success.get(probe.name, 0))
            for name, fill in sorted(st.map_fill.items()):
                snap.add(PROBE_MAP_FILL, (probe.name, name), fill)
            if "dropped" in getattr(probe, "maps", ()):
                snap.add(PROBE_DROPPED, (probe.name,), st.dropped)
            if st.missed is not None:
                snap.add(PROBE_MISSED, (probe.name,), st.missed)
            if maps_due:
                probe.read_map_memory()
            if st.map_memory:
                snap.add(PROBE_MAP_MEMORY, (probe.name,), st.map_memory)
        if self.graph is not None:
            snap.add(GRAPH_STALE, (self.graph_adapter,), int(bool(self.graph.error)))
            snap.add(GRAPH_TRUNCATED, (self.graph_adapter,), int(bool(self.graph.truncated)))
            for kind in ENTITIES:
                snap.add(GRAPH_ENTITIES, (kind,), len(self.graph.entities(kind)))
        for kind, count in self.budget.folded().items():
            snap.add(FOLDED, (kind,), count)
        for kind, count in self.budget.folded_total().items():
            snap.add(FOLDED_TOTAL, (kind,), count)
        for role, (cpu, rss, uss) in sorted(self._tree.sample().items()):
            snap.add(AGENT_CPU, (role,), cpu)
            snap.add(AGENT_RSS, (role,), rss)
            snap.add(AGENT_USS, (role,), uss)
