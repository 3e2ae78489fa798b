"""Library loads as they happen (bpf/loads.bpf.c): a uprobe on the dynamic linker's
_dl_debug_state tells, through a ring buffer, which process just started or loaded a library, and
a thread of this probe reads that process's memory map at once (drums.proctable.MappedLibraries).
The rcl and rtps probes listen there, so a node that loads ROS 2 at any time has its librcl
uprobed and its datagrams parsed before its first message, without waiting for a scrape.

The uprobe goes on each dynamic linker file (ld-linux*, ld-musl*) the processes map: the host's
when the probe starts, a container's when a process of it is first listed.
"""
from __future__ import annotations

import logging
import os
import struct
import threading
import time

from drums.errors import ProbeError
from drums.kernel import elf, perflink
from drums.kernel.btf import Btf
from drums.kernel.ringbuf import RingBuffer
from drums.metrics import Snapshot
from drums.probes.bpf import DROPPED, AttachPath, BpfProbe, needs_uprobes
from drums.proctable import MappedLibraries, mapped_file

log = logging.getLogger("drums")

LINKERS = ("ld-linux", "ld-musl")  # glibc's dynamic linker on every architecture, and musl's
HOOK = "_dl_debug_state"
RESCAN_EVERY = 1.0  # seconds: the least time between two readings of every map after lost notices


class LoadsProbe(BpfProbe):
    name = "loads"
    source = "loads.bpf.c"
    maps = {"loads": None, **DROPPED}  # a ring buffer
    metrics = ()
    paths = (
        AttachPath("uprobe", (("program", "", "on_debug_state"),), needs_uprobes,
                   "glibc or musl; uprobes pinned as BPF links (Linux >= 5.15) or held by the agent"),
    )

    def __init__(self, features, libraries: MappedLibraries, **kw):
        super().__init__(features, **kw)
        self.libraries = libraries
        libraries.listeners.append(self._found)
        self._ring: RingBuffer | None = None
        self._linkers: dict[tuple[int, int], str] = {}  # dynamic linker files -> why not uprobed, or ""
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._dropped_seen = 0

    def offsets(self, btf: Btf) -> dict[str, int]:
        return {}  # no kernel structs

    def start(self) -> None:
        super().start()
        try:
            self._ring = RingBuffer(os.path.join(self.pin_dir, "loads"))
        except ProbeError:
            self.stop()
            raise
        self._stopping.clear()
        self._thread = threading.Thread(target=self._run, name="drums-loads", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        self._linkers = {}
        super().stop()

    def _found(self, pid: int, libs: dict[str, str]) -> None:
        """A process maps a dynamic linker: uprobe it if it is a file not seen before."""
        for prefix in LINKERS:
            if prefix in libs and "on_debug_state" in self.programs:
                self._attach(pid, libs[prefix])

    def _attach(self, pid: int, path: str) -> None:
        found = mapped_file(self.libraries.table.proc, pid, path)
        if found is None or found[1] in self._linkers:
            return
        host_path, key = found
        pin = os.path.join(self.pin_dir, "linker-{}-{}".format(*key))
        try:
            if not os.path.exists(pin):  # else uprobed by an agent before this one
                offset = elf.symbol_offsets(host_path, (HOOK,)).get(HOOK)
                if offset is None:
                    raise ProbeError(f"{path}: no {HOOK} symbol")
                self.attached(perflink.uprobe(self.programs["on_debug_state"], host_path, offset,
                                              link=self.features.perf_links), pin)
            self._linkers[key] = ""
        except ProbeError as e:
            self._linkers[key] = str(e)
            log.warning("probe loads: %s; libraries this linker loads are found at the next scrape", e)
        self.status.reason = "; ".join(sorted({why for why in self._linkers.values() if why}))

    def _run(self) -> None:
        # Every process's map once, which also finds the dynamic linkers to uprobe; from then on
        # only the processes that say they loaded something.
        self.libraries.rescan()
        last_rescan = time.monotonic()
        while not self._stopping.is_set():
            self._ring.wait(0.5)
            try:
                for pid in sorted({struct.unpack_from("<I", record)[0] for record in self._ring.drain()}):
                    self.libraries.look(pid)
                _, values, _ = self.read("dropped")
                dropped = struct.unpack_from("<Q", values)[0]
                if dropped != self._dropped_seen and time.monotonic() - last_rescan >= RESCAN_EVERY:
                    log.warning("probe loads: %d notices of library loads lost (ring buffer full); "
                                "reading every process's map again", dropped - self._dropped_seen)
                    self._dropped_seen = dropped
                    self.libraries.rescan()
                    last_rescan = time.monotonic()
            except Exception as e:  # the thread must outlive one bad turn: the next notice may succeed
                log.warning("probe loads: %s", e, exc_info=log.isEnabledFor(logging.DEBUG))

    def collect(self, snap: Snapshot) -> None:
        self.read_dropped()
