"""On-CPU time, run-queue latency and context switches per process and thread
(bpf/sched.bpf.c), read from one map per collect instead of thousands of /proc files.

Process totals include threads that exited, so they never go backwards while the process lives.
A process that ended shows its final totals at the next collect, once: the kernel keeps them
(with its name, for one that started and ended between two collects) until the agent has read them.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from drums.arrays import among, distinct, within
from drums.kernel.btf import Btf
from drums.metrics import COUNTER, HISTOGRAM, Changes, Columns, Histogram, Metric, Snapshot, highest
from drums.probes.bpf import (DROPPED, TASK_IDENTITY_FIELDS, AttachPath, BpfProbe, ProcessTotals, change_marks,
                              comm_text, needs_tracepoints, offset_defines, typed)
from drums.probes.entries import Entries, Matched, Remembered
from drums.proctable import ProcessTable

RUNQ_SLOTS = 24
# Slot j of the kernel histogram holds waits under 2^(j+1) us; every other slot is exported.
_EXPORTED_SLOTS = tuple(range(1, 22, 2))
RUNQ_BUCKETS = tuple((2 ** (j + 1)) * 1e-6 for j in _EXPORTED_SLOTS)

PROCESS_CPU = Metric("drums_process_cpu_seconds_total", COUNTER,
                     "Time the process's threads spent on a CPU, as the kernel accounts it for /proc "
                     "(without time stolen by a hypervisor), from sched_switch", ("pid", "process"))
PROCESS_RUNQ = Metric("drums_process_runqueue_latency_seconds", HISTOGRAM,
                      "Time the process's threads waited on a run queue between becoming runnable "
                      "and running", ("pid", "process"), RUNQ_BUCKETS)
PROCESS_SWITCHES = Metric("drums_process_context_switches_total", COUNTER,
                          "Context switches of the process's threads: voluntary (blocked) or "
                          "involuntary (preempted)", ("pid", "process", "kind"))
THREAD_CPU = Metric("drums_thread_cpu_seconds_total", COUNTER, "Time the thread spent on a CPU",
                    ("pid", "tid", "thread"))
THREAD_RUNQ = Metric("drums_thread_runqueue_wait_seconds_total", COUNTER,
                     "Time the thread waited on a run queue", ("pid", "tid", "thread"))
THREAD_RUNQ_WAITS = Metric("drums_thread_runqueue_waits_total", COUNTER,
                           "Times the thread waited on a run queue", ("pid", "tid", "thread"))
THREAD_SWITCHES = Metric("drums_thread_context_switches_total", COUNTER, "Context switches of the thread",
                         ("pid", "tid", "thread", "kind"))
# The threads come as Columns (a host's thousands of threads hold no Python object each): their
# times in nanoseconds, shown in seconds; their switches two rows each, by kind.
THREAD_GROUP = (THREAD_CPU, THREAD_RUNQ, THREAD_RUNQ_WAITS)
_THREAD_UNITS = (1_000_000_000, 1_000_000_000, 1)
SWITCH_KINDS = ("voluntary", "involuntary")
PROCESS_METRICS = (PROCESS_CPU, PROCESS_RUNQ, PROCESS_SWITCHES)  # those made as rows, a process at a time

_SCHED = "5Q24I"  # struct sched_t
_THREAD_VALUE = struct.Struct("<IIQQQQQQ" + _SCHED + "16s")  # struct thread_sched_t
_PROCESS_VALUE = struct.Struct("<Q" + _SCHED + "16s")  # struct exited_sched_t
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
DROP_RENAMED = 2  # the index of bpf/sched.bpf.c's count of marks lost to a full `renamed` map
_ONCPU = struct.Struct("<QIIQQ")  # struct oncpu_t
# Slots of the threads' array (bpf/sched.bpf.c), a power of two: 8,192 hold a host's threads but
# for those whose slot another thread holds (a hash lookup more per switch), in 1.6 MB.
THREAD_SLOTS = 8192
# A whole read maps the slots (1.6 MB) and reads thread_sched; a thread marked changed is looked up
# in its slot (and in thread_sched, one call each): a whole read only when most threads were marked.
MARKED_WHOLE_ABOVE = 2
# A thread's value as 8-byte words: its process's start time, its runtime when its slot was taken,
# its name, and its counts (on-CPU ns, run-queue ns, waits, voluntary and involuntary switches).
_WORD_START, _WORD_BASE, _WORDS_COMM, _WORDS_COUNTS = 2, 3, slice(24, 26), slice(7, 12)


def runq_histogram(slots: list[int], total_ns: int, waits: int) -> Histogram:
    cumulative, running, j = [], 0, 0
    for bound_slot in _EXPORTED_SLOTS:
        while j <= bound_slot:
            running += slots[j]
            j += 1
        cumulative.append(running)
    return Histogram(cumulative, total_ns / 1e9, waits)


@dataclass(slots=True)
class _Made:
    """What one process's entries made at a collect, kept for the next while they stay the same,
    and as the floor of its next values: a total is read as live threads plus exited ones from two
    maps one after the other, and a thread that exits between the two reads is in neither for that
    collect, so a value is never shown below the one made before for the same process start."""
    seen: tuple  # (its exited threads' entry, its name)
    # Tuples, not lists or a set: a thousand processes keep theirs between collects (0.9 MB less).
    rows: tuple  # its rows of each metric, in the probe's order: a row of CPU and run-queue time per
    # process start, two of switches
    starts: tuple  # the process start of each row of CPU time (a PID's exited threads may be of a start before)
    cpu: float  # its CPU seconds, for the process table


# The scheduler tracepoints, with the programs that count them.
_PROGRAMS = (("sched_switch", "on_switch"), ("sched_wakeup", "on_wakeup"), ("sched_wakeup_new", "on_wakeup"),
             ("task_rename", "on_rename"),
             ("sched_process_exec", "on_exec"), ("sched_process_exit", "on_exit"), ("sched_process_fork", "on_fork"))
_RAW = AttachPath("raw_tracepoint", tuple(("raw_tracepoint", tp, fn) for tp, fn in _PROGRAMS),
                  needs_tracepoints(*(tp for tp, _ in _PROGRAMS)),
                  "Linux >= 5.7 (raw tracepoint links that outlive the loader)")


class _ThreadLabels:
    """The label values of threads (pid, tid, name), made when the budget or a reader of the
    snapshot asks for them: of a host's thousands, those with series of their own. What the last
    collect's asked for are taken again while the thread keeps its name, with those of its rows of
    switches (the same tuples each time: a kept idle thread's rows compare by identity)."""

    def __init__(self, ids: np.ndarray, comms: np.ndarray, remembered: Remembered):
        self.ids, self.comms = ids, comms  # each thread's pid << 32 | tid, and its name as two words
        self.remembered = remembered  # by id, checked against the name's words

    def _made(self, at: list[int]) -> list[tuple[tuple[str, ...], ...]]:
        """Per thread at these indices: its labels, then each kind of switch's."""
        return [self.remembered.get(id_, comm, lambda: _thread_labels(id_, comm))
                for id_, comm in zip(self.ids[at].tolist(), map(bytes, self.comms[at]))]

    def __call__(self, at: list[int]) -> list[tuple[str, str, str]]:
        return [made[0] for made in self._made(at)]

    def switches(self, at: list[int]) -> list[tuple[str, str, str, str]]:
        """The labels of the rows of switches at these indices: thread i's are rows i * kinds + kind."""
        kinds = len(SWITCH_KINDS)
        threads = list(dict.fromkeys(i // kinds for i in at))  # a kept thread's rows come together
        made = dict(zip(threads, self._made(threads)))
        return [made[i // kinds][1 + i % kinds] for i in at]


def _thread_labels(id_: int, comm: bytes) -> tuple[tuple[str, ...], ...]:
    thread = str(id_ >> 32), str(id_ & 0xFFFFFFFF), comm_text(comm)
    return (thread, *(thread + (kind,) for kind in SWITCH_KINDS))


class SchedProbe(BpfProbe):
    name = "sched"
    source = "sched.bpf.c"
    maps = {"thread_sched": (_U32, _THREAD_VALUE), "thread_slots": (_U32, _THREAD_VALUE),
            "exited_sched": (_U32, _PROCESS_VALUE), "oncpu": (4, _ONCPU), "renamed": (_U32, _U64),
            **change_marks(_U32), **DROPPED}
    metrics = (PROCESS_CPU, PROCESS_RUNQ, PROCESS_SWITCHES, THREAD_CPU, THREAD_RUNQ, THREAD_RUNQ_WAITS,
               THREAD_SWITCHES)
    paths = (typed(_RAW, without=("sched_wakeup",),
                   serves="; run-queue waits from the kernel's own sched_info (CONFIG_SCHED_INFO), "
                          "no program on wakeups but new tasks'"), _RAW)

    def __init__(self, features, proctable: ProcessTable, **kw):
        super().__init__(features, **kw)
        self.proctable = proctable
        self._made: dict[int, _Made] = {}  # tgid -> what its entries made at the last collect
        self._remake = False  # every process made again at the next collect: the last one failed
        self._rows: list[dict] = [{} for _ in PROCESS_METRICS]  # per metric: labels -> row, of every process made
        self._cpu: dict[int, float] = {}  # tgid -> CPU seconds of every process made, for the process table
        self._refreshed = -1  # the process table's refresh at the last collect
        self._threads = Entries(_THREAD_VALUE.size, 0)  # rows: each thread's tgid
        self._waiting: set[int] = set()  # threads marked whose slot was being taken or given up
        self._hashed: set[int] = set()  # threads whose entry is in thread_sched, for its fill
        # Each thread's CPU time as last shown, by thread ID, ascending, with its process's start:
        # the running slice is estimated, and a thread's time never goes below what it showed.
        self._shown = (np.empty(0, np.uint64), np.empty(0, np.uint64), np.empty(0, np.int64))
        self._labelled = Remembered()  # the labels the last collect's threads were asked for
        self._collects = 0
        self._renames_lost = 0
        self._exited_read: tuple[bytes, bytes, int] | None = None  # exited_sched as ended() read it

    def offsets(self, btf: Btf) -> dict[str, int]:
        d = offset_defines(btf, {
            **TASK_IDENTITY_FIELDS,
            "TASK_COMM_OFF": ("task_struct", "comm"),
            "TASK_RUNTIME_OFF": ("task_struct", "se.sum_exec_runtime"),
        })
        if btf.has_field("task_struct", "sched_info.run_delay"):  # CONFIG_SCHED_INFO: the tp_btf path needs it
            d.update(offset_defines(btf, {"TASK_RUN_DELAY_OFF": ("task_struct", "sched_info.run_delay"),
                                          "TASK_PCOUNT_OFF": ("task_struct", "sched_info.pcount")}))
        d["THREAD_SLOTS"] = THREAD_SLOTS if self.features.bpf_atomics else 1  # slots are taken by compare-and-swap
        args = btf.tracepoint_args("sched_switch") or []
        if len(args) >= 4:
            d["SWITCH_HAS_PREV_STATE"] = 1  # Linux 5.18 added prev_state to the tracepoint
        else:
            state = "__state" if btf.has_field("task_struct", "__state") else "state"
            d.update(offset_defines(btf, {"TASK_STATE_OFF": ("task_struct", state)}))
        return d

    def renamed(self) -> set[int] | None:
        """The processes forked, renamed, exec'd or exited since the last call (for the process
        table); None if some of those notices were lost to a full map."""
        keys, values, _ = self.read("renamed")
        m = self.opened["renamed"]
        m.delete_unchanged([(keys[i * 4:i * 4 + 4], values[i * 8:i * 8 + 8]) for i in range(len(keys) // 4)])
        _, drops, _ = self.read("dropped")
        lost = _U64.unpack_from(drops, DROP_RENAMED * self.opened["dropped"].value_stride)[0]
        if lost != self._renames_lost:
            self._renames_lost = lost
            return None
        return {tgid for (tgid,) in _U32.iter_unpack(keys)}

    def thread_entries(self) -> tuple[bytes, bytes]:
        """Every thread's entry, as (keys, values): thread IDs as 8-byte words, and values. Those in
        slots are read in place; one whose slot a thread is taking or giving up shows its owner but
        not yet its process's start time, and waits for the next collect."""
        keys, values, _ = self.read("thread_sched")
        with self.opened["thread_slots"].mapped() as mapping:
            slots = np.frombuffer(mapping, np.uint64)
            slots = slots[:len(slots) // self._threads.width * self._threads.width].reshape(-1, self._threads.width)
            taken = slots[(slots[:, 0] != 0) & (slots[:, _WORD_START] != 0)]  # a copy, now: they move on
            del slots  # no view of the mapping outlives it (closing it needs none)
        hashed = np.frombuffer(keys, np.uint32).astype(np.uint64)
        # A thread in its slot and in thread_sched too: two CPUs made its entry at once (a new task's
        # wakeup and its first switch-in), which programs built before this check could. The
        # programs update the slot's alone; the other would count the thread twice.
        twice = within(hashed, np.sort(taken[:, 0] >> 32))
        if twice.any():
            for tid in hashed[twice].tolist():
                self.opened["thread_sched"].delete(_U32.pack(tid))
            hashed = hashed[~twice]
            values = np.frombuffer(values, np.uint8).reshape(len(twice), -1)[~twice].tobytes()
        self._hashed = set(hashed.tolist())
        return np.concatenate((hashed, taken[:, 0] >> 32)).tobytes(), values + taken.tobytes()

    def _read_threads(self) -> Matched:
        """The threads' entries matched against the last collect's: those the programs marked
        changed looked up, or all read when most were, when the last collect was not kept, or
        while another process reads the marks."""
        marks = self.marks("thread_sched", MARKED_WHOLE_ABOVE)
        marked = None if marks is None else marks.changed(len(self._threads), whole=not self._threads.kept)
        if marked is None:
            self._waiting = set()
            return self._threads.read(*self.thread_entries())
        tids = self._waiting.union(_U32.unpack(key)[0] for key in marked)
        changes = self._looked_up(sorted(tids))
        self.status.map_fill["thread_sched"] = len(self._hashed) / marks.map.max_entries
        return self._threads.update(changes)

    def _looked_up(self, tids: list[int]) -> list[tuple[bytes, bytes | None]]:
        """(thread ID as 8 bytes, its entry or None if it has none) of each thread: in its slot,
        else in thread_sched. One whose slot is being taken or given up (its owner shown, its
        process's start not yet) waits for the next collect, as a whole read has it."""
        slots, hashed = self.opened["thread_slots"], self.opened["thread_sched"]
        changes, self._waiting = [], set()
        for tid in tids:
            key = _U32.pack(tid)
            value = slots.lookup(_U32.pack(tid % slots.max_entries))
            if value is not None and _U32.unpack_from(value, 4)[0] == tid:
                if not _U64.unpack_from(value, _WORD_START * 8)[0]:
                    self._waiting.add(tid)
                    continue
                hashed.delete(key)  # a twin in thread_sched, if any (see thread_entries), goes
                self._hashed.discard(tid)
            else:
                value = hashed.lookup(key)
                (self._hashed.discard if value is None else self._hashed.add)(tid)
            changes.append((_U64.pack(tid), value))
        return changes

    def _running(self) -> dict[int, int]:
        """Thread id -> its runtime now, for the thread each CPU runs: a thread may keep its CPU for
        seconds without a switch to count it. From /proc/TID/schedstat (one file a CPU, up to date
        at the last tick; the exact CPU clock of a thread is its own process's alone). Read before
        the threads' entries: a thread that leaves its CPU in between has its slice in its entry,
        where read the other way round its slice was in neither (a real-time thread throttled then
        lagged by the hundreds of milliseconds it had run). Without CONFIG_SCHED_INFO the running
        slice waits for the thread's next switch."""
        _, values, _ = self.read("oncpu")
        stride = self.opened["oncpu"].value_size
        out = {}
        for cpu in range(len(values) // stride):
            _, tid, _pad, _delay, _runs = _ONCPU.unpack_from(values, cpu * stride)
            if not tid:
                continue
            try:
                with open(f"/proc/{tid}/schedstat", "rb") as f:
                    out[tid] = int(f.read().split(None, 1)[0])
            except (OSError, ValueError, IndexError):
                pass  # gone, or no schedstat: its time is what its switches counted
        return out

    def collect(self, snap: Snapshot) -> None:
        """Rows are made again only for the processes whose entries changed since the last collect
        (a thread ran, came or went): on a host of a thousand processes most sleep between two."""
        try:
            self._collect(snap)
        except BaseException:
            # Its rows may be half brought up to date: the next collect makes every process's anew
            # (each one's last values stay, as the floor of its next).
            self._rows, self._remake = [{} for _ in PROCESS_METRICS], True
            raise

    def ended(self) -> dict[int, str]:
        pt, out = self.proctable, {}
        keys, values, _ = self._exited_read = self.read("exited_sched")  # the collect that follows takes it
        for (tgid,), (*_, comm) in zip(_U32.iter_unpack(keys), _PROCESS_VALUE.iter_unpack(values)):
            if not pt.alive(tgid) and not pt.belongs(tgid):
                out[tgid] = comm_text(comm)
        return out

    def _collect(self, snap: Snapshot) -> None:
        pt = self.proctable
        self._collects += 1  # first: a collect that fails is one the next cannot be told against
        exited: dict[int, bytes] = {}
        ended: list[tuple[bytes, bytes]] = []  # the entries of processes that ended: read once, then deleted
        keys, values, _ = self._exited_read or self.read("exited_sched")
        self._exited_read = None
        size = _PROCESS_VALUE.size
        for i, (tgid,) in enumerate(_U32.iter_unpack(keys)):
            value = values[i * size:(i + 1) * size]
            if pt.alive(tgid):
                exited[tgid] = value
            elif not pt.belongs(tgid):  # ended (not one that started after the table's listing)
                exited[tgid] = value
                ended.append((keys[4 * i:4 * i + 4], value))
        # The thread entries matched against the last read in bulk: only processes with a thread
        # new, changed, gone or on a CPU now are made again.
        running = self._running()
        m = self._read_threads()
        tgids = m.words[:, 0] & 0xFFFFFFFF
        dirty = set(tgids[~m.same].tolist())
        dirty.update(tgid for tgid in m.gone.tolist() if tgid is not None)
        if running:
            dirty.update(tgids[among(m.keys, running)].tolist())
        new = ~m.same_head  # the others keep the process they had
        m.rows[new] = tgids[new].tolist()  # kept with each thread, for the collect that finds it gone
        self._threads.keep(m, np.ones(len(m.keys), bool))
        made, cpu = self._made, self._cpu
        alive = pt.alive_among(distinct(tgids).tolist())
        shown = alive | exited.keys()  # and the processes that ended since the last collect, once more
        gone = made.keys() - shown
        was = [made.pop(tgid) for tgid in gone]  # gone, and made again: their last rows
        for tgid in gone:
            del cpu[tgid]
        # Made again: a process new, with a thread new, changed, gone or on a CPU, with exited threads
        # whose entry changed, or renamed since the last collect; of a thousand, few.
        renamed = pt.renamed_since(self._refreshed)
        self._refreshed = pt.refreshes
        remake, self._remake = self._remake, False
        suspects = alive if renamed is None or remake else \
            (alive - made.keys()) | (alive & (dirty | exited.keys() | renamed))
        again = {}
        for tgid in suspects | (shown - alive):
            before = made.get(tgid)
            if tgid in alive:
                name = pt.name(tgid)
            else:  # ended: named as it was, or as the kernel last knew it
                name = before.seen[1] if before is not None else pt.ended_name(tgid)
            seen = (exited.get(tgid), name)
            if remake or before is None or tgid in dirty or before.seen != seen:
                again[tgid] = seen
        threads: dict[int, list[tuple[int, bytes]]] = {tgid: [] for tgid in again}
        for i in np.flatnonzero(among(tgids, again)).tolist():
            threads[int(tgids[i])].append((int(m.keys[i]), m.words[i].tobytes()))
        remade = []
        for tgid, seen in again.items():
            before = made.get(tgid)
            process = self._make(tgid, seen, threads[tgid], running, before)
            remade.append(process)
            if before is not None:
                was.append(before)
            made[tgid] = process
            cpu[tgid] = process.cpu
        # Every process's rows, brought up to date with those of the processes made again or gone
        # (a thousand processes, a few of which ran: no walk over all of them).
        for i, metric in enumerate(PROCESS_METRICS):
            rows, changed = self._rows[i], [row for process in remade for row in process.rows[i]]
            gone = [labels for process in was for labels, _ in process.rows[i]]
            for labels in gone:
                rows.pop(labels, None)  # none after a failed collect: the rows are made anew
            rows.update((row[0], row) for row in changed)
            if rows:
                snap.rows(metric).extend(rows.values())
            snap.changes[(metric,)] = Changes(self._collects - 1, self._collects, changed, gone)
        self._thread_columns(snap, m, tgids, among(tgids, alive), running)
        pt.ran(dict(cpu))
        if ended:  # read: the next collect finds them gone (or, if a late thread folded, once more)
            self.opened["exited_sched"].delete_unchanged(ended)
        self.read_dropped()

    def _thread_columns(self, snap: Snapshot, m: Matched, tgids: np.ndarray, alive: np.ndarray,
                        running: dict[int, int]) -> None:
        """The threads' rows, as two groups of Columns: those of the processes alive (`alive`: a
        mask of m's entries). A thread on a CPU now has its running slice counted (`running`)."""
        w = m.words
        counts = w[:, _WORDS_COUNTS].astype(np.int64)
        if running:
            on = np.flatnonzero(among(m.keys, running))
            now = np.fromiter((running[tid] for tid in m.keys[on].tolist()), np.int64, len(on))
            counts[on, 0] = np.maximum(counts[on, 0], now - w[on, _WORD_BASE].astype(np.int64))
        keys, start, cpu = self._shown
        if len(keys):
            at = np.minimum(np.searchsorted(keys, m.keys), len(keys) - 1)
            same = (keys[at] == m.keys) & (start[at] == w[:, _WORD_START])
            counts[same, 0] = np.maximum(counts[same, 0], cpu[at[same]])
        self._shown = (m.keys, w[:, _WORD_START].copy(), counts[:, 0].copy())
        counts, pids = counts[alive], tgids[alive].astype(np.int64)
        ids = pids << 32 | m.keys[alive].astype(np.int64)
        comms = w[alive, _WORDS_COMM]
        labels = _ThreadLabels(ids, comms, self._labelled.turn())
        snap.groups[THREAD_GROUP] = Columns(ids, counts[:, :3], np.zeros(len(ids), np.intp), ("",), pids, labels,
                                            units=_THREAD_UNITS, stamps=comms.__getitem__)
        kinds = len(SWITCH_KINDS)
        snap.groups[(THREAD_SWITCHES,)] = Columns(
            (ids[:, None] * kinds + np.arange(kinds)).ravel(), counts[:, 3:5].reshape(-1, 1),
            np.tile(np.arange(kinds), len(ids)), SWITCH_KINDS, np.repeat(pids, kinds),
            labels.switches, entities=np.repeat(ids, kinds), stamps=lambda at: comms[at // kinds])

    def _make(self, tgid: int, seen: tuple, live: list[tuple[int, bytes]], running: dict[int, int],
              before: _Made | None) -> _Made:
        """The rows of one process, from its threads' entries and its exited threads' in the two maps."""
        exited, name = seen
        kinds = len(SWITCH_KINDS)
        # The values made last time, by process start: each of this start's now is never below its own.
        last = {}
        if before is not None:
            cpus, runqs, switches = before.rows
            for i, start in enumerate(before.starts):
                last[start] = (cpus[i][1], runqs[i][1], *(n for _, n in switches[i * kinds:(i + 1) * kinds]))
        totals = ProcessTotals()
        if exited is not None:
            start, *s, _comm = _PROCESS_VALUE.unpack(exited)
            totals.add_exited(tgid, start, s)
        rows: dict[Metric, list] = {metric: [] for metric in PROCESS_METRICS}
        for tid, raw in live:
            _, _pad, _enqueued, start, base, _delay_base, _runs_base, _marked, *s, _comm = _THREAD_VALUE.unpack(raw)
            if tid in running:
                s[0] = max(s[0], running[tid] - base)
            totals.add_thread(tgid, start, s)
        cpu, starts = 0.0, []
        for (_, start), s in totals.items():
            oncpu, runq_ns, runq_waits, vol, invol = s[:5]
            labels = (str(tgid), name)
            was = last.get(start, (None,) * (2 + kinds))
            cpu = highest(was[0], oncpu / 1e9)
            rows[PROCESS_CPU].append((labels, cpu))
            rows[PROCESS_RUNQ].append((labels, highest(was[1], runq_histogram(s[5:], runq_ns, runq_waits))))
            for kind, n, floor in zip(SWITCH_KINDS, (vol, invol), was[2:]):
                rows[PROCESS_SWITCHES].append((labels + (kind,), highest(floor, n)))
            starts.append(start)
        return _Made(seen, tuple(tuple(rows[metric]) for metric in PROCESS_METRICS), tuple(starts), cpu)
