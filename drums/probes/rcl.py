"""Messages published and taken per ROS 2 process and topic, the time between two publishes of
each publisher, the deadlines publishers and subscriptions missed, each delivery's transport and
age from the stamps the RMW gives rcl_take, and each node's reaction time from a take to its
publishes, from uprobes on librcl (bpf/rcl.bpf.c): what shared memory hides from every socket.

The programs are loaded once; each librcl.so file that a process maps is found in
/proc/<pid>/maps (as soon as it is mapped: drums.probes.loads) and gets its own pinned uprobe
links, attached from this process without bcc. A handle (rcl_publisher_t or rcl_subscription_t)
is named by reading the process's memory once: the handle points to rcl's private impl struct,
whose layout changes between ROS distributions, so the rmw handle inside it is found by its shape
(rmw_publisher_t and rmw_subscription_t, public and stable, begin with the RMW's name, a data
pointer and the topic name); the endpoint's GID is found the same way behind the data pointer.
"""
from __future__ import annotations

import glob
import os
import struct
import time

import numpy as np

from drums.errors import ProbeError
from drums.kernel import elf, perflink
from drums.kernel.btf import Btf
from drums.metrics import COUNTER, HISTOGRAM, Histogram, Metric, Monotonic, Snapshot
from drums.probes.bpf import DROPPED, AttachPath, BpfProbe, comm_text, needs_uprobes
from drums.proctable import MappedLibraries, ProcessTable, mapped_file

LIBRARY = "librcl.so"
# (function, program, return probe): every way a message enters or leaves rcl.
UPROBES = (
    ("rcl_publish", "on_publish", False),
    ("rcl_publish_serialized_message", "on_publish", False),
    ("rcl_publish_loaned_message", "on_publish", False),
    ("rcl_take", "on_take", False),
    ("rcl_take", "on_take_return", True),
    ("rcl_take_serialized_message", "on_take", False),
    ("rcl_take_serialized_message", "on_take_return", True),
    ("rcl_take_loaned_message", "on_take", False),
    ("rcl_take_loaned_message", "on_take_return", True),
    # What a thread publishes after these reacts to a timer or a service, not to its last take.
    *((fn, "on_idle", False) for fn in ("rcl_timer_call", "rcl_timer_call_with_info", "rcl_take_request",
                                        "rcl_take_request_with_info", "rcl_take_response",
                                        "rcl_take_response_with_info")),
)
PROGRAMS = ("on_publish", "on_take", "on_take_return", "on_idle")
OP_TAKEN = 1  # handle_key_t.op of a take (TAKEN in rcl.bpf.c; a publish is 0)
UNKNOWN_TOPIC = "unknown"  # a handle whose topic could not be read (yet: it is tried again)

LABELS = ("pid", "process", "topic", "endpoint")  # endpoint: the publisher's or subscription's GID
PUBLISHED = Metric("drums_ros_messages_published_total", COUNTER,
                   "Messages this process published on the topic (rcl_publish), whatever the transport", LABELS)
TAKEN = Metric("drums_ros_messages_taken_total", COUNTER,
               "Messages this process took from the topic (rcl_take), whatever the transport", LABELS)
PERIOD_HELP = ("Time between two messages of the publisher (rcl_publish): its buckets are the edges of "
               "the kernel's slots (1.6% wide, 131 us to 17.2 s) that counted any, so a quantile is within 1%")
PERIOD = Metric("drums_ros_publish_period_seconds", HISTOGRAM, PERIOD_HELP, LABELS)
MISSED = Metric("drums_ros_deadlines_missed_total", COUNTER,
                "Deadlines (the Deadline QoS the publisher offers) that passed without a message from it, as "
                "the kernel saw its messages; counted while the silence lasts; only publishers with a deadline",
                LABELS)
TAKE_MISSED = Metric("drums_ros_take_deadlines_missed_total", COUNTER,
                     "Deadlines (the Deadline QoS the subscription requests) that passed without a message "
                     "taken by it (rcl_take), as the kernel saw its takes; counted while the silence lasts; only "
                     "subscriptions with a deadline", LABELS)
REACTION = Metric("drums_ros_reaction_seconds", HISTOGRAM,
                  "Time from a thread's take of a message on the input topic to its publish on the output topic "
                  "before it takes another or runs a timer or service: the node's reaction (buckets as the "
                  "periods', 16 us to 2.1 s); endpoint is the output's publisher",
                  ("pid", "process", "input", "output", "endpoint"))
DELIVERY = ("pid", "process", "topic", "endpoint", "publisher")  # endpoint: the subscription's GID
TRANSPORT = Metric("drums_ros_delivery_transport_seconds", HISTOGRAM,
                   "Time from the publisher's stamp of a message to its reception by the subscription's RMW "
                   "(received less source timestamp of rmw_message_info_t; buckets as the periods', 4 us to "
                   "537 ms); both stamps are the realtime clocks of their hosts: across hosts, as close as "
                   "those clocks are (PTP or chrony)", DELIVERY)
AGE = Metric("drums_ros_delivery_age_seconds", HISTOGRAM,
             "Time from the publisher's stamp of a message to the subscriber's take of it (rcl_take): transport "
             "and queueing in the subscriber's executor; buckets and clocks as the transport's", DELIVERY)
SKEWED = Metric("drums_ros_delivery_skewed_total", COUNTER,
                "Messages stamped after the subscriber received or took them: their publisher's clock is ahead "
                "(another host's), and their delivery times are not counted", DELIVERY)

# bpf/rcl.bpf.c's time slots: 2^SUB_LOG2 a power of two of nanoseconds over OCTAVES powers of two
# from 2^min_log2, one slot under and one over.
SUB_LOG2, OCTAVES = 6, 17
SLOTS = (OCTAVES << SUB_LOG2) + 2
PERIOD_MIN_LOG2, REACTION_MIN_LOG2, DELIVERY_MIN_LOG2 = 17, 14, 12  # from 131 us, 16 us and 4 us


def slot_edges(min_log2: int) -> tuple[np.ndarray, np.ndarray]:
    """The lower and upper edge of each slot, in seconds: slot i holds [lower[i], upper[i])."""
    j = np.arange(OCTAVES << SUB_LOG2)
    lower = 2.0 ** (min_log2 + j // (1 << SUB_LOG2)) * (1 + (j % (1 << SUB_LOG2)) / (1 << SUB_LOG2))
    lower = np.concatenate(([0.0], lower, [2.0 ** (min_log2 + OCTAVES)])) / 1e9
    return lower, np.append(lower[1:], np.inf)


PERIOD_EDGES, REACTION_EDGES = slot_edges(PERIOD_MIN_LOG2), slot_edges(REACTION_MIN_LOG2)
DELIVERY_EDGES = slot_edges(DELIVERY_MIN_LOG2)
_TIMING = np.dtype([("last", "<u8"), ("sum", "<u8"), ("missed", "<u8"), ("messages", "<u8"),
                    ("slots", "<u4", SLOTS)])  # struct timing_t
_REACTION_KEY = struct.Struct("<IIQQ")
_DELIVERY_KEY = struct.Struct("<IIQ16s")
_DELIVERY = np.dtype([("transport_sum", "<u8"), ("age_sum", "<u8"), ("skewed", "<u8"),
                      ("transport", "<u4", SLOTS), ("age", "<u4", SLOTS)])  # struct delivery_t
_S64 = struct.Struct("<q")

_KEY = struct.Struct("<IIQ")
_U64 = struct.Struct("<Q")
_IMPL_WORDS = 64  # how far into rcl's impl struct to look for the rmw handle
_GID_SEARCH = 1024  # how far into the RMW's publisher or subscription struct to look for its GID
GID_BYTES = 16  # a DDS GUID: 12 bytes of participant prefix, 4 of entity id


def _read(mem, address: int, size: int) -> bytes | None:
    try:
        data = os.pread(mem, size, address)
    except (OSError, OverflowError):
        return None
    return data if len(data) == size else None


def _string(mem, address: int, prefix: bytes) -> str | None:
    data = _read(mem, address, 256) if address else None
    if data is None or not data.startswith(prefix) or b"\0" not in data:
        return None
    return comm_text(data)


def endpoint_of(pid: int, handle: int) -> tuple[str, str] | None:
    """The topic of an rcl publisher or subscription handle in a process, and its endpoint's GID
    (32 hex digits, or "" where it is not found), from the process's memory."""
    try:
        mem = os.open(f"/proc/{pid}/mem", os.O_RDONLY)
    except OSError:
        return None
    try:
        head = _read(mem, handle, 8)
        impl = _U64.unpack(head)[0] if head else 0
        words = _read(mem, impl, 8 * _IMPL_WORDS) if impl else None
        for (candidate,) in struct.iter_unpack("<Q", words or b""):
            rmw = _read(mem, candidate, 24) if candidate > 0xFFFF else None
            if rmw is None:
                continue
            identifier, data, name = struct.unpack("<QQQ", rmw)
            if _string(mem, identifier, b"rmw_") is not None:
                topic = _string(mem, name, b"/")
                if topic is not None:
                    return topic, _gid(mem, data, identifier)
        return None
    finally:
        os.close(mem)


def _gid(mem: int, data: int, identifier: int) -> str:
    """The endpoint's GID in the RMW's own struct behind rmw_*_t.data: an rmw_gid_t (public and
    stable: the RMW's identifier pointer, then the GID's bytes) that the RMW keeps there, as
    rmw_fastrtps and rmw_cyclonedds do. The identifier is the one the rmw handle holds."""
    words = _read(mem, data, _GID_SEARCH) if data else None
    if words is None:
        return ""
    tag = _U64.pack(identifier)
    at = words.find(tag)
    while at >= 0:
        gid = words[at + 8:at + 8 + GID_BYTES]
        if at % 8 == 0 and len(gid) == GID_BYTES and any(gid):
            return gid.hex()
        at = words.find(tag, at + 1)
    return ""


def timing_histogram(slots: np.ndarray, total_ns: int, edges: tuple[np.ndarray, np.ndarray]) -> Histogram:
    """Times counted in the kernel's slots (with these edges) as a histogram with a bucket at each
    edge of each slot that holds counts, so the quantiles are as fine as the slots. A slot once
    counted stays, so no bucket goes away and none goes down, also where rows are added on the
    union of their buckets (two publishers of a node, rows of nodes not known yet)."""
    lower, upper = edges
    used = np.flatnonzero(slots)
    counts = slots[used].astype(np.int64)
    cumulative = np.cumsum(counts)
    bounds = np.column_stack((lower[used], upper[used])).ravel()
    at = np.column_stack((cumulative - counts, cumulative)).ravel()
    keep = (bounds > 0) & np.isfinite(bounds)
    bounds, at = bounds[keep], at[keep]
    first = np.concatenate(([True], np.diff(bounds) > 0))  # neighbouring slots share an edge
    total = int(cumulative[-1]) if len(used) else 0
    return Histogram(at[first].tolist(), total_ns / 1e9, total, tuple(bounds[first].tolist()))


class RclProbe(BpfProbe):
    name = "rcl"
    source = "rcl.bpf.c"
    maps = {"handles": (_KEY, _U64), "periods": (_KEY, _TIMING), "deadlines": (_KEY, _U64), "deadlines_known": (4, 4),
            "reactions": (_REACTION_KEY, _TIMING), "deliveries": (_DELIVERY_KEY, _DELIVERY),
            "realtime_offset": (4, _S64), **DROPPED}
    metrics = (PUBLISHED, TAKEN, PERIOD, MISSED, TAKE_MISSED, REACTION, TRANSPORT, AGE, SKEWED)
    paths = (
        AttachPath("uprobe", tuple(("program", "", p) for p in PROGRAMS), needs_uprobes,
                   "any ROS 2 distribution; uprobes pinned as BPF links (Linux >= 5.15) or held by the agent, "
                   "task-local storage per thread (Linux >= 5.12) or a hash"),
    )

    def __init__(self, features, proctable: ProcessTable, libraries: MappedLibraries | None = None,
                 timing: bool = True, **kw):
        """`timing`: time the messages as well as count them (periods, deadlines, reactions, deliveries)."""
        super().__init__(features, **kw)
        self.timing = timing
        self.options = {} if timing else {"DRUMS_COUNT_ONLY": 1}
        self.proctable = proctable
        self.libraries = libraries or MappedLibraries(proctable, (LIBRARY,))  # may follow more libraries
        self.libraries.listeners.append(self._found)
        self._files: dict[tuple[int, int], str] = {}  # librcl files with uprobes -> why not, or ""
        self._endpoints: dict[tuple[int, int], tuple[str, str]] = {}  # (pid, handle) -> (topic, GID)
        self._periods: dict[tuple[int, int], tuple[int, Histogram]] = {}  # (pid, handle) -> (count, histogram)
        self._deadlines: dict[str, int] = {}  # endpoint GID -> the Deadline QoS it offers or requests, ns
        self._written: dict[bytes, int] = {}  # map key of an endpoint -> the deadline the programs know, ns
        self._missed = Monotonic()
        self._reactions: dict[tuple[int, int, int], tuple[int, Histogram]] = {}  # (pid, input, output) -> as periods
        self._deliveries: dict[bytes, tuple[int, Histogram, Histogram]] = {}  # map key -> (count, transport, age)

    def offsets(self, btf: Btf) -> dict[str, int]:
        # Only user memory, through the registers of the calling convention.
        return {"TASK_STORAGE": 1} if self.features.task_storage else {}

    def start(self) -> None:
        super().start()
        self._say_clock()
        keys, _, _ = self.read("deadlines")  # an agent's before this one (--keep-loaded): their handles are old
        for i in range(0, len(keys), _KEY.size):
            self.opened["deadlines"].delete(keys[i:i + _KEY.size])
        self._say_deadlines_known(0)
        for pid, libs in self.libraries.processes((LIBRARY,)).items():  # found before the programs were here
            self._found(pid, libs)

    def _found(self, pid: int, libs: dict[str, str]) -> None:
        """A process maps libraries it did not before (under the libraries' lock)."""
        if LIBRARY in libs and self.programs:
            self._attach(pid, libs[LIBRARY])

    def stop(self) -> None:
        self._files = {}
        super().stop()

    def _attach(self, pid: int, path: str) -> None:
        """Put the uprobes on the librcl file a process maps, once per file (its device and inode:
        the path may name another file in the process's mount namespace)."""
        found = mapped_file(self.proctable.proc, pid, path)
        if found is None or found[1] in self._files:
            return
        host_path, key = found
        prefix = os.path.join(self.pin_dir, "lib-{}-{}-".format(*key))
        if glob.glob(prefix + "*"):  # pinned by an agent before this one
            self._files[key] = ""
            return
        try:
            offsets = elf.symbol_offsets(host_path, {fn for fn, _, _ in UPROBES})
            for i, (fn, program, ret) in enumerate(UPROBES):
                if fn in offsets and (self.timing or program != "on_idle"):  # idle ends a reaction
                    self.attached(perflink.uprobe(self.programs[program], host_path, offsets[fn], ret,
                                                  link=self.features.perf_links), f"{prefix}{i}")
            self._files[key] = "" if "rcl_publish" in offsets else f"{path}: no rcl_publish symbol"
        except ProbeError as e:
            self._files[key] = str(e)
        self.status.reason = "; ".join(sorted({why for why in self._files.values() if why}))

    def collect(self, snap: Snapshot) -> None:
        self.libraries.refresh()
        processes = self.libraries.processes((LIBRARY,))
        # Counted in `handles`; with timing, publishes in their period entry and takes with their
        # delivery (one hash lookup fewer a message), and in `handles` only where those had none.
        keys, values, _ = self.read("handles")
        counted = [(fields, keys[i * _KEY.size:(i + 1) * _KEY.size], "handles", _U64.unpack_from(values, i * 8)[0])
                   for i, fields in enumerate(_KEY.iter_unpack(keys))]
        periods = self._timings("periods", _KEY, _TIMING, "slots") if self.timing else ([], None, ())
        deliveries = self._timings("deliveries", _DELIVERY_KEY, _DELIVERY, "age") if self.timing else ([], None, ())
        entries, table, _ = periods
        counted += [(fields, key, "periods", int(table["messages"][i])) for i, (fields, key) in enumerate(entries)]
        entries, table, timed = deliveries
        counted += [((pid, OP_TAKEN, subscription), key, "deliveries", int(timed[i] + table["skewed"][i]))
                    for i, ((pid, _, subscription, _), key) in enumerate(entries)]
        totals: dict[tuple[int, int, str, str], int] = {}
        written = {}
        for (pid, op, handle), key, map_name, count in counted:
            endpoint = self._endpoint(pid, handle, processes, map_name, key)
            if endpoint is None:
                continue
            if count:
                totals[(pid, op) + endpoint] = totals.get((pid, op) + endpoint, 0) + count
            deadline = self._deadlines.get(endpoint[1], 0) if endpoint[1] else 0
            if deadline:
                written[_KEY.pack(pid, op, handle)] = deadline
        for (pid, op, topic, gid), count in totals.items():
            snap.add(TAKEN if op else PUBLISHED, (str(pid), self.proctable.name(pid), topic, gid), count)
        if self.timing:
            self._write_deadlines(written)
            self._collect_periods(snap, processes, periods)
            self._collect_reactions(snap, processes)
            self._collect_deliveries(snap, processes, deliveries)
        self._endpoints = {k: v for k, v in self._endpoints.items() if k[0] in processes}
        self.read_dropped()

    def _endpoint(self, pid: int, handle: int, processes: dict, map_name: str, key: bytes) -> tuple[str, str] | None:
        """The (topic, GID) of a handle, (UNKNOWN_TOPIC, "") while it cannot be read; None for a
        process not followed yet (it just loaded librcl) or gone, whose entry is then deleted."""
        if pid not in processes:
            if not self.proctable.belongs(pid):
                self.opened[map_name].delete(key)
            return None
        endpoint = self._endpoints.get((pid, handle))
        if endpoint is None:
            endpoint = endpoint_of(pid, handle)
            if endpoint is not None:
                self._endpoints[(pid, handle)] = endpoint
        return endpoint or (UNKNOWN_TOPIC, "")

    def _timings(self, name: str, key: struct.Struct, dtype: np.dtype, slots: str):
        """A map of times in slots: [(its key's fields, the key), ...], its values as one table, and
        how many times each entry counted (in its `slots`)."""
        keys, values, n = self.read(name)
        table = np.frombuffer(values, dtype, count=n)
        counts = table[slots].sum(axis=1, dtype=np.int64) if n else ()
        entries = [(fields, keys[i * key.size:(i + 1) * key.size]) for i, fields in enumerate(key.iter_unpack(keys))]
        return entries, table, counts

    def want_deadlines(self, deadlines: dict[str, int]) -> None:
        """The Deadline QoS (ns) of the graph's endpoints that offer or request one, by GID."""
        self._deadlines = deadlines

    def _write_deadlines(self, written: dict[bytes, int]) -> None:
        """Tell the programs the deadlines of the endpoints that have counted messages (map key ->
        ns): a publisher's count from its next message, a subscription's from its next take."""
        for key, deadline in written.items():
            if self._written.get(key) != deadline:
                self.opened["deadlines"].update(key, _U64.pack(deadline))
        for key in self._written.keys() - written.keys():
            self.opened["deadlines"].delete(key)  # its process ended, or it has no deadline now
        if len(written) != len(self._written):
            self._say_deadlines_known(len(written))
        self._written = written

    def _say_deadlines_known(self, count: int) -> None:
        self.opened["deadlines_known"].update(bytes(4), struct.pack("<I", count))

    def _collect_periods(self, snap: Snapshot, processes: dict, periods: tuple) -> None:
        """One histogram per publisher, made again only for publishers that published since, and
        the deadlines each endpoint with one missed: those the kernel counted between two
        messages, and those that passed since its last. `periods`: the map as _timings read it."""
        entries, table, counts = periods
        now = time.clock_gettime_ns(time.CLOCK_MONOTONIC)  # bpf_ktime_get_ns's clock
        kept = {}
        for i, ((pid, op, handle), key) in enumerate(entries):
            endpoint = self._endpoint(pid, handle, processes, "periods", key)
            if endpoint is None:
                continue
            labels = (str(pid), self.proctable.name(pid)) + endpoint
            deadline = self._written.get(key, 0)
            if deadline:
                # Read with the entry, in which the kernel moves last_ns before it adds to missed: a
                # read between the two sees a smaller sum, which Monotonic holds back.
                silent = (now - int(table["last"][i])) // deadline if table["last"][i] else 0
                snap.add(TAKE_MISSED if op else MISSED, labels,
                         self._missed(key, int(table["missed"][i]) + max(0, silent)))
            if op or not counts[i]:  # a subscription's periods are kept for its deadlines only
                continue
            known = self._periods.get((pid, handle))
            if known is None or known[0] != counts[i]:
                known = (int(counts[i]), timing_histogram(table["slots"][i], int(table["sum"][i]), PERIOD_EDGES))
            kept[(pid, handle)] = known
            snap.add(PERIOD, labels, known[1])
        self._periods = kept
        self._missed.next_collect()

    def _collect_reactions(self, snap: Snapshot, processes: dict) -> None:
        """One histogram per node's input and output, made again only where it reacted since."""
        entries, table, counts = self._timings("reactions", _REACTION_KEY, _TIMING, "slots")
        kept = {}
        for i, ((pid, _, taken, published), key) in enumerate(entries):
            ends = [self._endpoint(pid, h, processes, "reactions", key) for h in (taken, published)]
            if None in ends or not counts[i]:
                continue
            known = self._reactions.get((pid, taken, published))
            if known is None or known[0] != counts[i]:
                known = (int(counts[i]), timing_histogram(table["slots"][i], int(table["sum"][i]), REACTION_EDGES))
            kept[(pid, taken, published)] = known
            (input_topic, _), (output_topic, gid) = ends
            snap.add(REACTION, (str(pid), self.proctable.name(pid), input_topic, output_topic, gid), known[1])
        self._reactions = kept

    def _say_clock(self) -> None:
        """The realtime clock's offset from the monotonic one, with which the programs read the
        RMW's stamps (NTP slews it slowly; set again at each collect)."""
        offset = time.clock_gettime_ns(time.CLOCK_REALTIME) - time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        self.opened["realtime_offset"].update(bytes(4), _S64.pack(offset))

    def _collect_deliveries(self, snap: Snapshot, processes: dict, deliveries: tuple) -> None:
        """Per subscription and publisher: the transport and age histograms, made again only where
        messages came since, and the messages whose stamps were ahead of the subscriber's clock.
        `deliveries`: the map as _timings read it."""
        self._say_clock()
        entries, table, counts = deliveries
        kept = {}
        for i, ((pid, _, subscription, publisher), key) in enumerate(entries):
            endpoint = self._endpoint(pid, subscription, processes, "deliveries", key)
            if endpoint is None:
                continue
            labels = (str(pid), self.proctable.name(pid)) + endpoint + (publisher.hex(),)
            if table["skewed"][i]:
                snap.add(SKEWED, labels, int(table["skewed"][i]))
            if not counts[i]:
                continue
            known = self._deliveries.get(key)
            if known is None or known[0] != counts[i]:
                row = table[i]
                known = (int(counts[i]), timing_histogram(row["transport"], int(row["transport_sum"]), DELIVERY_EDGES),
                         timing_histogram(row["age"], int(row["age_sum"]), DELIVERY_EDGES))
            kept[key] = known
            snap.add(TRANSPORT, labels, known[1])
            snap.add(AGE, labels, known[2])
        self._deliveries = kept
