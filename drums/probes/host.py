"""Host-wide CPU, memory, filesystem, disk, network and load metrics, read through psutil (memory from
/proc/meminfo itself).

Needs no BPF and no privileges, so it is the probe that still reports when every kernel probe fails.
"""
from __future__ import annotations

import select
import time

import psutil

from drums.metrics import COUNTER, GAUGE, Metric, Snapshot
from drums.probes.base import Probe, ProbeStatus

CPU_SECONDS = Metric(
    "drums_host_cpu_seconds_total", COUNTER, "CPU time spent in each mode, all CPUs summed", ("mode",)
)
MEMORY_TOTAL = Metric("drums_host_memory_total_bytes", GAUGE, "Physical memory")
MEMORY_AVAILABLE = Metric(
    "drums_host_memory_available_bytes", GAUGE, "Memory that can be given to processes without swapping"
)
MEMORY_USED = Metric("drums_host_memory_used_bytes", GAUGE, "Memory in use, excluding buffers and page cache")
SWAP_TOTAL = Metric("drums_host_swap_total_bytes", GAUGE, "Swap space")
SWAP_USED = Metric("drums_host_swap_used_bytes", GAUGE, "Swap space in use")

FS = ("mountpoint", "fstype")
FS_SIZE = Metric("drums_host_filesystem_size_bytes", GAUGE, "Size of a mounted filesystem", FS)
FS_FREE = Metric("drums_host_filesystem_free_bytes", GAUGE, "Space an unprivileged user can still write", FS)

DEV = ("device",)
DISK_READ_BYTES = Metric("drums_host_disk_read_bytes_total", COUNTER, "Bytes read from a block device", DEV)
DISK_WRITTEN_BYTES = Metric(
    "drums_host_disk_written_bytes_total", COUNTER, "Bytes written to a block device", DEV
)
DISK_READS = Metric("drums_host_disk_reads_total", COUNTER, "Completed reads from a block device", DEV)
DISK_WRITES = Metric("drums_host_disk_writes_total", COUNTER, "Completed writes to a block device", DEV)

NIC = ("interface",)
NET_RECEIVED_BYTES = Metric("drums_host_network_received_bytes_total", COUNTER, "Bytes received", NIC)
NET_SENT_BYTES = Metric("drums_host_network_sent_bytes_total", COUNTER, "Bytes sent", NIC)
NET_RECEIVED_PACKETS = Metric("drums_host_network_received_packets_total", COUNTER, "Packets received", NIC)
NET_SENT_PACKETS = Metric("drums_host_network_sent_packets_total", COUNTER, "Packets sent", NIC)
NET_RECEIVE_ERRORS = Metric("drums_host_network_receive_errors_total", COUNTER, "Receive errors", NIC)
NET_TRANSMIT_ERRORS = Metric("drums_host_network_transmit_errors_total", COUNTER, "Transmit errors", NIC)
NET_RECEIVE_DROPS = Metric("drums_host_network_receive_drops_total", COUNTER, "Received packets dropped", NIC)
NET_TRANSMIT_DROPS = Metric("drums_host_network_transmit_drops_total", COUNTER, "Sent packets dropped", NIC)

LOAD = Metric("drums_host_load", GAUGE, "Run queue load average over a period", ("period",))

# Linux counts guest time inside user and guest_nice inside nice; exporting them as modes too would
# make the modes add up to more than the elapsed CPU time.
_CPU_MODES = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")
# A device that is gone this long is forgotten: Prometheus has long since called its series stale.
FORGET_AFTER = 600.0


class Carry:
    """Keeps a device's counters going forward when the device is made again under its name (a
    veth or USB disk removed and re-added starts again from 0): what it had counted is carried
    on. A device is another one when its counter went down, or when it was missing from a listing
    of its kind that came after it was last seen (a listing that failed lists nothing)."""

    def __init__(self):
        self._kept: dict[tuple, list] = {}  # (metric, device) -> [carried, last value, collect, time last seen]
        self._collect = 0
        self._listed: dict[Metric, tuple[int, int]] = {}  # metric -> (the last collect that read it, the one before)
        self._now = 0.0

    def start(self) -> None:
        """Before a collect: forget the devices gone longer than FORGET_AFTER."""
        self._collect += 1
        self._now = time.monotonic()
        self._kept = {k: e for k, e in self._kept.items() if self._now - e[3] < FORGET_AFTER}

    def __call__(self, metric: Metric, device: str, value: float) -> float:
        last, before = self._listed.get(metric, (0, 0))
        if last != self._collect:
            last, before = self._listed[metric] = self._collect, last
        entry = self._kept.setdefault((metric, device), [0, 0, self._collect, 0.0])
        if value < entry[1] or entry[2] < before:
            entry[0] += entry[1]
        entry[1:] = value, self._collect, self._now
        return entry[0] + value


class Mounts:
    """The filesystems mounted from a device, listed again only after the mount table changed: the
    kernel flags an open /proc/self/mounts with POLLPRI at each mount and unmount (proc(5)), where a
    listing reads two /proc files at every collect."""

    def __init__(self):
        self._table = None
        self._changed = select.poll()
        self._listed: list | None = None

    def __call__(self) -> list:
        if self._table is None:  # opened before the first listing; unreadable, it fails only this reader
            self._table = open("/proc/self/mounts", "rb")  # kept open: the flag is on this file
            self._changed.register(self._table, select.POLLPRI)
        elif self._listed is not None and not self._changed.poll(0):
            return self._listed
        # A mountpoint mounted over is listed twice; statvfs sees the top one, listed last.
        self._listed = list({p.mountpoint: p for p in psutil.disk_partitions(all=False)}.values())
        return self._listed

    def close(self) -> None:
        if self._table is not None:
            self._table.close()


def _cpu(snap: Snapshot, _probe: HostProbe) -> None:
    times = psutil.cpu_times()
    for mode in _CPU_MODES:
        snap.add(CPU_SECONDS, (mode,), getattr(times, mode))


def _memory(snap: Snapshot, _probe: HostProbe) -> None:
    # One read of meminfo, where psutil's virtual and swap memory read it twice and vmstat besides.
    kib = {}
    with open(f"{psutil.PROCFS_PATH}/meminfo", "rb") as f:
        for line in f:
            name, _, value = line.partition(b":")
            words = value.split()
            if words and words[0].isdigit():
                kib[name] = int(words[0])
    missing = {b"MemTotal", b"MemFree", b"Buffers", b"Cached", b"SwapTotal", b"SwapFree"} - kib.keys()
    if missing:  # a container's stand-in: as a file that cannot be read, this reader alone fails
        raise OSError(f"/proc/meminfo has no {', '.join(sorted(m.decode() for m in missing))}")
    total = kib[b"MemTotal"]
    # Linux 3.14 added MemAvailable; above the total, a container's view is distorted (as psutil).
    available = kib.get(b"MemAvailable", kib[b"MemFree"] + kib[b"Buffers"] + kib[b"Cached"])
    available = kib[b"MemFree"] if available > total else available
    snap.add(MEMORY_TOTAL, (), total * 1024)
    snap.add(MEMORY_AVAILABLE, (), available * 1024)
    snap.add(MEMORY_USED, (), (total - available) * 1024)
    snap.add(SWAP_TOTAL, (), kib[b"SwapTotal"] * 1024)
    snap.add(SWAP_USED, (), (kib[b"SwapTotal"] - kib[b"SwapFree"]) * 1024)


def _filesystems(snap: Snapshot, probe: HostProbe) -> None:
    # all=False leaves out filesystems without a device (proc, sysfs, tmpfs, cgroup...).
    for part in probe.mounts():
        try:
            usage = psutil.disk_usage(part.mountpoint)
        except OSError:  # e.g. a stale network mount; the other filesystems are still worth reporting
            continue
        labels = (part.mountpoint, part.fstype)
        snap.add(FS_SIZE, labels, usage.total)
        snap.add(FS_FREE, labels, usage.free)


# Counter -> the psutil field it is read from, per disk and per network interface.
_DISK = {DISK_READ_BYTES: "read_bytes", DISK_WRITTEN_BYTES: "write_bytes", DISK_READS: "read_count",
         DISK_WRITES: "write_count"}
_NIC = {NET_RECEIVED_BYTES: "bytes_recv", NET_SENT_BYTES: "bytes_sent", NET_RECEIVED_PACKETS: "packets_recv",
        NET_SENT_PACKETS: "packets_sent", NET_RECEIVE_ERRORS: "errin", NET_TRANSMIT_ERRORS: "errout",
        NET_RECEIVE_DROPS: "dropin", NET_TRANSMIT_DROPS: "dropout"}


def _disks(snap: Snapshot, probe: HostProbe) -> None:
    # Partitions are listed next to their disk, so summing over devices counts their I/O twice.
    for device, io in psutil.disk_io_counters(perdisk=True).items():
        for metric, field in _DISK.items():
            snap.add(metric, (device,), probe.carry(metric, device, getattr(io, field)))


def _network(snap: Snapshot, probe: HostProbe) -> None:
    for nic, io in psutil.net_io_counters(pernic=True).items():
        for metric, field in _NIC.items():
            snap.add(metric, (nic,), probe.carry(metric, nic, getattr(io, field)))


def _load(snap: Snapshot, _probe: HostProbe) -> None:
    for period, value in zip(("1m", "5m", "15m"), psutil.getloadavg()):
        snap.add(LOAD, (period,), value)


_READERS = (_cpu, _memory, _filesystems, _disks, _network, _load)


class HostProbe(Probe):
    name = "host"
    metrics = (
        CPU_SECONDS,
        MEMORY_TOTAL,
        MEMORY_AVAILABLE,
        MEMORY_USED,
        SWAP_TOTAL,
        SWAP_USED,
        FS_SIZE,
        FS_FREE,
        DISK_READ_BYTES,
        DISK_WRITTEN_BYTES,
        DISK_READS,
        DISK_WRITES,
        NET_RECEIVED_BYTES,
        NET_SENT_BYTES,
        NET_RECEIVED_PACKETS,
        NET_SENT_PACKETS,
        NET_RECEIVE_ERRORS,
        NET_TRANSMIT_ERRORS,
        NET_RECEIVE_DROPS,
        NET_TRANSMIT_DROPS,
        LOAD,
    )

    def __init__(self):
        super().__init__()
        self.carry = Carry()
        self.mounts = Mounts()

    def start(self) -> None:
        self.status = ProbeStatus(attached=True, attach_type="psutil")

    def stop(self) -> None:
        self.mounts.close()

    def collect(self, snap: Snapshot) -> None:
        # One unreadable source (no disks, a /proc file hidden by a container) must not cost the
        # others; what was skipped is kept in status.reason so it stays visible.
        failed = []
        self.carry.start()
        for read in _READERS:
            try:
                read(snap, self)
            except (OSError, NotImplementedError, psutil.Error) as exc:
                failed.append(f"{read.__name__[1:]}: {exc}")
        self.status.reason = "; ".join(failed)
