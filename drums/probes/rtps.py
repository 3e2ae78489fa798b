"""Samples and bytes per DDS writer, sent and received, from the RTPS messages of processes that
load a DDS library (bpf/rtps.bpf.c). The graph join (drums.graph.join) names each writer by its
topic and node.

A writer is its GUID: 12 bytes of participant prefix and 4 of entity id, written here as 32 hex
digits, as the ROS 2 adapter writes endpoint GIDs. A sample is a sequence number seen for the
first time (in whatever order: a repair of a lost sample comes after later ones; within 64 of the
highest seen), and its bytes are its serialized size (CDR with the 4-byte encapsulation header, as
the DATA or DATA_FRAG header says); wire bytes count the payload in every datagram, so copies to
several readers and repairs of lost fragments show as wire bytes above sample bytes.
"""
from __future__ import annotations

import struct

from drums.kernel.btf import Btf
from drums.metrics import COUNTER, Metric, Snapshot
from drums.probes.bpf import DROPPED, AttachPath, BpfProbe, needs_all, needs_tracepoints
from drums.proctable import MappedLibraries, ProcessTable

# Libraries whose processes speak RTPS: Fast DDS (2.x and 3.x), Cyclone DDS, Connext, and rcl for
# any ROS 2 process whatever its RMW.
DDS_LIBRARIES = ("libfastrtps.so", "libfastdds.so", "libddsc.so", "libnddscore.so", "librcl.so")
SYSCALLS = ("sendto", "sendmsg", "recvfrom", "recvmsg")

LABELS = ("pid", "process", "writer")
SAMPLES_SENT = Metric("drums_dds_writer_samples_sent_total", COUNTER,
                      "Samples of this DDS writer this process sent over UDP (each sample once)", LABELS)
SENT_BYTES = Metric("drums_dds_writer_sent_bytes_total", COUNTER,
                    "Serialized size of those samples (each sample once)", LABELS)
SENT_WIRE_BYTES = Metric("drums_dds_writer_sent_wire_bytes_total", COUNTER,
                         "Serialized payload of this writer in every datagram this process sent: a copy "
                         "for each reader, and repairs", LABELS)
SAMPLES_RECEIVED = Metric("drums_dds_writer_samples_received_total", COUNTER,
                          "Samples of this DDS writer this process received over UDP (each sample once)", LABELS)
RECEIVED_BYTES = Metric("drums_dds_writer_received_bytes_total", COUNTER,
                        "Serialized size of those samples (each sample once)", LABELS)
RECEIVED_WIRE_BYTES = Metric("drums_dds_writer_received_wire_bytes_total", COUNTER,
                             "Serialized payload of this writer in every datagram this process received, "
                             "repairs included", LABELS)
_BY_DIRECTION = ((SAMPLES_SENT, SENT_BYTES, SENT_WIRE_BYTES),
                 (SAMPLES_RECEIVED, RECEIVED_BYTES, RECEIVED_WIRE_BYTES))

# Map layouts, as in bpf/rtps.bpf.c.
_KEY = struct.Struct("<II16s")
_COUNTS = struct.Struct("<QQQqQ")
_U32 = struct.Struct("<I")


def decode(keys: bytes, values: bytes) -> list[tuple[int, int, str, tuple[int, int, int]]]:
    """(pid, direction, writer GUID hex, (samples, sample bytes, wire bytes)) of each map entry."""
    return [(pid, direction, guid.hex(), _COUNTS.unpack_from(values, i * _COUNTS.size)[:3])
            for i, (pid, direction, guid) in enumerate(_KEY.iter_unpack(keys))]


_EVENTS = tuple(f"sys_{side}_{call}" for side in ("enter", "exit") for call in SYSCALLS)
_EXITS = tuple(("tracepoint", f"syscalls:sys_exit_{call}", f"on_{call}") for call in SYSCALLS)
_ENTRIES = tuple(("tracepoint", f"syscalls:sys_enter_{call}", f"enter_{call}") for call in SYSCALLS)


def _needs_task_pt_regs(f) -> str | None:
    return None if f.task_pt_regs else "no bpf_task_pt_regs to read a call's arguments at its exit (Linux >= 5.15)"


class RtpsProbe(BpfProbe):
    name = "rtps"
    source = "rtps.bpf.c"
    maps = {"watched": (_U32, 1), "writers": (_KEY, _COUNTS), **DROPPED}
    metrics = _BY_DIRECTION[0] + _BY_DIRECTION[1]
    paths = (
        AttachPath("tracepoint", _EXITS, needs_all(_needs_task_pt_regs, needs_tracepoints(*_EVENTS)),
                   "Linux >= 5.15: each call's exit, its arguments read from the task's registers, pinned as BPF links"),
        AttachPath("tracepoint", _ENTRIES + _EXITS, needs_tracepoints(*_EVENTS),
                   "any kernel: each call's entry and exit, held by the agent before Linux 5.15",
                   defines=(("SYSCALL_ENTRIES", 1),)),
    )

    def __init__(self, features, proctable: ProcessTable, libraries: MappedLibraries | None = None, **kw):
        super().__init__(features, **kw)
        self.proctable = proctable
        self.libraries = libraries or MappedLibraries(proctable, DDS_LIBRARIES)  # shared with rcl by the agent
        self.libraries.listeners.append(self._found)
        self._watched: set[int] = set()

    def offsets(self, btf: Btf) -> dict[str, int]:
        # Only user memory and tracepoint records, whose layouts are ABI.
        return {"PREEMPT_RT": 1} if self.features.preempt_rt else {}

    def start(self) -> None:
        super().start()
        with self.libraries.lock:
            for pid, libs in self.libraries.processes(DDS_LIBRARIES).items():  # found before the map was here
                self._found(pid, libs)

    def _found(self, pid: int, libs: dict[str, str]) -> None:
        """A process maps libraries it did not before (under the libraries' lock): parse its
        datagrams from now on if one of them speaks DDS."""
        if "watched" in self.opened and pid not in self._watched and any(lib in libs for lib in DDS_LIBRARIES):
            self.opened["watched"].update(_U32.pack(pid), b"\x01")
            self._watched.add(pid)

    def watch(self) -> None:
        """Stop parsing the datagrams of processes that ended."""
        self.libraries.refresh()
        with self.libraries.lock:
            for pid in [pid for pid in self._watched if not self.proctable.belongs(pid)]:
                self.opened["watched"].delete(_U32.pack(pid))
                self._watched.discard(pid)

    def collect(self, snap: Snapshot) -> None:
        self.watch()
        keys, values, _ = self.read("writers")
        for i, (pid, direction, writer, counts) in enumerate(decode(keys, values)):
            if pid not in self._watched:  # the process ended
                if not self.proctable.belongs(pid):
                    self.opened["writers"].delete(keys[i * _KEY.size:(i + 1) * _KEY.size])
                continue
            labels = (str(pid), self.proctable.name(pid), writer)
            for metric, value in zip(_BY_DIRECTION[direction], counts):
                snap.add(metric, labels, value)
        self.read_dropped()
