"""host: the probe's values against the kernel's own files, and against traffic and writes the test makes."""
import mmap
import os
import socket
import subprocess
import threading
import time

import psutil
import pytest

from drums.metrics import Snapshot
from drums.probes import host
from drums.probes.host import HostProbe
from tests.conftest import wait_until

MIB = 1 << 20


@pytest.fixture
def probe():
    probe = HostProbe()
    probe.start()
    return probe


def collect(probe: HostProbe) -> Snapshot:
    snap = Snapshot()
    probe.collect(snap)
    return snap


def meminfo() -> dict:
    with open("/proc/meminfo") as f:
        return {line.split(":")[0]: int(line.split()[1]) * 1024 for line in f}


CPU_MODES = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")  # /proc/stat's order


def proc_stat_cpu() -> dict:
    with open("/proc/stat") as f:
        ticks = f.readline().split()[1:9]
    return {mode: int(t) / os.sysconf("SC_CLK_TCK") for mode, t in zip(CPU_MODES, ticks)}


def diskstats(device: str) -> tuple:
    """(read bytes, written bytes, reads, writes) of a device; /proc/diskstats counts 512-byte sectors."""
    with open("/proc/diskstats") as f:
        fields = next(line.split() for line in f if line.split()[2] == device)
    return int(fields[5]) * 512, int(fields[9]) * 512, int(fields[3]), int(fields[7])


# Metric -> its column in a /proc/net/dev row: 8 receive columns, then the transmit ones.
NET_COLUMNS = {
    host.NET_RECEIVED_BYTES: 0,
    host.NET_RECEIVED_PACKETS: 1,
    host.NET_RECEIVE_ERRORS: 2,
    host.NET_RECEIVE_DROPS: 3,
    host.NET_SENT_BYTES: 8,
    host.NET_SENT_PACKETS: 9,
    host.NET_TRANSMIT_ERRORS: 10,
    host.NET_TRANSMIT_DROPS: 11,
}


def net_dev() -> dict:
    with open("/proc/net/dev") as f:
        rows = [line.split(":") for line in f.readlines()[2:]]
    return {nic.strip(): [int(x) for x in data.split()] for nic, data in rows}


def loadavg() -> tuple:
    with open("/proc/loadavg") as f:
        return tuple(float(x) for x in f.read().split()[:3])


def test_status_and_declared_metrics(probe):
    assert probe.name == "host"
    assert (probe.status.attached, probe.status.attach_type) == (True, "psutil")
    snap = collect(probe)
    assert probe.status.reason == ""
    assert set(snap.series) == set(probe.metrics)
    for metric, rows in snap.series.items():
        assert all(len(labels) == len(metric.labels) for labels, _ in rows), metric.name
        assert len({labels for labels, _ in rows}) == len(rows), f"duplicate series in {metric.name}"


def test_memory_matches_meminfo(probe):
    snap = collect(probe)
    info = meminfo()
    total = snap.values(host.MEMORY_TOTAL)[()]
    assert total == info["MemTotal"] == psutil.virtual_memory().total
    assert 0 < snap.values(host.MEMORY_AVAILABLE)[()] <= total
    assert 0 < snap.values(host.MEMORY_USED)[()] < total
    assert snap.values(host.MEMORY_USED)[()] == total - snap.values(host.MEMORY_AVAILABLE)[()]  # as psutil's
    swap_total = snap.values(host.SWAP_TOTAL)[()]
    assert swap_total == info["SwapTotal"]
    assert 0 <= snap.values(host.SWAP_USED)[()] <= swap_total


def test_cpu_seconds_lie_between_two_reads_of_proc_stat(probe):
    before = proc_stat_cpu()
    snap = collect(probe)
    after = proc_stat_cpu()
    seconds = {labels[0]: value for labels, value in snap.values(host.CPU_SECONDS).items()}
    assert set(seconds) == set(CPU_MODES)  # guest and guest_nice are already inside user and nice
    for mode, value in seconds.items():
        assert before[mode] - 1e-6 <= value <= after[mode] + 1e-6, mode
    assert seconds["idle"] > 0


def test_network_lies_between_two_reads_of_proc_net_dev(probe):
    before = net_dev()
    snap = collect(probe)
    after = net_dev()
    assert {nic for nic, in snap.values(host.NET_SENT_BYTES)} == set(before)
    for metric, column in NET_COLUMNS.items():
        for (nic,), value in snap.values(metric).items():
            assert before[nic][column] <= value <= after[nic][column], (metric.name, nic)


def test_loopback_counts_bytes_sent_over_tcp(probe):
    """What the probe counts is what the kernel counts on lo, read around both collects: at least
    this test's own traffic, and no more than lo carried meanwhile (make test's other lane uses it)."""
    size = 4 * MIB
    stats = ("tx_bytes", "rx_bytes", "tx_packets", "rx_packets", "rx_errors", "tx_errors", "rx_dropped", "tx_dropped")

    def kernel() -> dict[str, int]:
        out = {}
        for name in stats:
            with open(f"/sys/class/net/lo/statistics/{name}") as f:
                out[name] = int(f.read())
        return out
    first = kernel()
    before = collect(probe)
    with socket.create_server(("127.0.0.1", 0)) as server:
        out = socket.create_connection(server.getsockname())
        conn, _ = server.accept()
        with out, conn:
            sender = threading.Thread(target=out.sendall, args=(b"x" * size,))
            sender.start()
            received = 0
            while received < size:
                received += len(conn.recv(MIB))
            sender.join()
    after = collect(probe)
    last = kernel()

    def delta(metric):
        return after.values(metric)[("lo",)] - before.values(metric)[("lo",)]

    # Loopback counts each packet once as sent and once as received; headers and ACKs add a little.
    for metric, stat in ((host.NET_SENT_BYTES, "tx_bytes"), (host.NET_RECEIVED_BYTES, "rx_bytes")):
        assert size <= delta(metric) <= last[stat] - first[stat], metric.name
    for metric, stat in ((host.NET_SENT_PACKETS, "tx_packets"), (host.NET_RECEIVED_PACKETS, "rx_packets")):
        assert size // 65536 <= delta(metric) <= last[stat] - first[stat], metric.name  # lo's MTU is 65536
    for metric, stat in ((host.NET_RECEIVE_ERRORS, "rx_errors"), (host.NET_TRANSMIT_ERRORS, "tx_errors"),
                         (host.NET_RECEIVE_DROPS, "rx_dropped"), (host.NET_TRANSMIT_DROPS, "tx_dropped")):
        assert 0 <= delta(metric) <= last[stat] - first[stat], metric.name


def test_root_filesystem_and_no_pseudo_filesystems(probe):
    snap = collect(probe)
    sizes = snap.values(host.FS_SIZE)
    with open("/proc/self/mounts") as f:
        root_type = [line.split()[2] for line in f if line.split()[1] == "/"][-1]
    st = os.statvfs("/")
    assert sizes[("/", root_type)] == st.f_blocks * st.f_frsize
    free = snap.values(host.FS_FREE)[("/", root_type)]
    assert abs(free - st.f_bavail * st.f_frsize) < 64 * MIB
    assert not {fstype for _, fstype in sizes} & {"proc", "sysfs", "tmpfs", "devtmpfs", "cgroup", "cgroup2"}
    assert set(snap.values(host.FS_FREE)) == set(sizes)


def test_a_filesystem_mounted_or_unmounted_shows_at_the_next_collect_and_the_mounts_are_listed_only_then(
        probe, tmp_path, monkeypatch):
    listings = []
    listing = psutil.disk_partitions
    monkeypatch.setattr(psutil, "disk_partitions", lambda **kw: listings.append(kw) or listing(**kw))
    with open("/proc/self/mounts") as f:
        root_type = [line.split()[2] for line in f if line.split()[1] == "/"][-1]
    mountpoint = (str(tmp_path), root_type)  # the root filesystem bound again: a device's, listed
    assert mountpoint not in collect(probe).values(host.FS_SIZE)
    subprocess.run(["mount", "--bind", "/", str(tmp_path)], check=True)
    try:
        assert collect(probe).values(host.FS_SIZE)[mountpoint] == os.statvfs("/").f_blocks * os.statvfs("/").f_frsize
        listed = len(listings)
        for _ in range(10):
            collect(probe)
        # Other tests' network namespaces (mounts of their own) may come meanwhile: a few listings.
        assert len(listings) - listed <= 3, listings
    finally:
        subprocess.run(["umount", str(tmp_path)], check=True)
    assert mountpoint not in collect(probe).values(host.FS_SIZE)
    probe.stop()


def test_disk_counts_direct_writes_and_reads(probe, tmp_path):
    st = os.stat(tmp_path)
    sys_dev = f"/sys/dev/block/{os.major(st.st_dev)}:{os.minor(st.st_dev)}"
    if not os.path.exists(sys_dev):
        pytest.skip(f"{tmp_path} is not on a block device")
    device = os.path.basename(os.path.realpath(sys_dev))
    size = 4 * MIB
    before = collect(probe)

    # O_DIRECT skips the page cache, so both transfers reach the device before the next collect.
    fd = os.open(tmp_path / "data", os.O_RDWR | os.O_CREAT | os.O_DIRECT)
    with mmap.mmap(-1, size) as buf:  # page aligned, as O_DIRECT requires
        buf.write(b"x" * size)
        try:
            assert os.pwritev(fd, [buf], 0) == size
            os.fsync(fd)
            assert os.preadv(fd, [buf], 0) == size
        finally:
            os.close(fd)
    proc_before = diskstats(device)
    after = collect(probe)
    proc_after = diskstats(device)

    metrics = (host.DISK_READ_BYTES, host.DISK_WRITTEN_BYTES, host.DISK_READS, host.DISK_WRITES)
    values = tuple(after.values(metric)[(device,)] for metric in metrics)
    assert all(b <= v <= a for b, v, a in zip(proc_before, values, proc_after)), (proc_before, values)
    assert values[0] - before.values(host.DISK_READ_BYTES)[(device,)] >= size
    assert values[1] - before.values(host.DISK_WRITTEN_BYTES)[(device,)] >= size
    assert values[2] > before.values(host.DISK_READS)[(device,)]
    assert values[3] > before.values(host.DISK_WRITES)[(device,)]


def test_load_matches_proc_loadavg(probe):
    before = loadavg()
    snap = collect(probe)
    after = loadavg()
    load = tuple(snap.values(host.LOAD)[(period,)] for period in ("1m", "5m", "15m"))
    # getloadavg(3) has more precision than /proc/loadavg, which rounds to hundredths.
    assert load == pytest.approx(before, abs=0.006) or load == pytest.approx(after, abs=0.006)


def test_unreadable_sources_are_skipped_and_named(probe, tmp_path, monkeypatch):
    # An empty directory as /proc: every /proc reader fails. Disk I/O falls back to /sys/block and the
    # load average comes from getloadavg(3), so those two still report.
    monkeypatch.setattr(psutil, "PROCFS_PATH", str(tmp_path))
    snap = collect(probe)
    assert {metric.name for metric in snap.series} == {
        "drums_host_disk_read_bytes_total",
        "drums_host_disk_written_bytes_total",
        "drums_host_disk_reads_total",
        "drums_host_disk_writes_total",
        "drums_host_load",
    }
    failed = [part.split(":")[0] for part in probe.status.reason.split("; ")]
    assert failed == ["cpu", "memory", "filesystems", "network"]


def test_a_meminfo_without_its_fields_fails_the_memory_reader_alone(probe, tmp_path, monkeypatch):
    """A container's stand-in for /proc may give a meminfo of its own: one without the fields read
    is said as such, and the other readers still report."""
    for name in os.listdir("/proc"):
        if name in ("stat", "diskstats", "filesystems", "self", "net"):
            os.symlink(f"/proc/{name}", tmp_path / name)
    (tmp_path / "meminfo").write_text("MemTotal:       1000 kB\ngarbage line\nMemFree: x kB\n")
    monkeypatch.setattr(psutil, "PROCFS_PATH", str(tmp_path))
    snap = collect(probe)
    assert probe.status.reason == "memory: /proc/meminfo has no Buffers, Cached, MemFree, SwapFree, SwapTotal"
    assert not snap.values(host.MEMORY_TOTAL) and snap.values(host.CPU_SECONDS) and snap.values(host.NET_SENT_BYTES)


NS, NIC, PEER = "drums-host-test", "drumshost0", "drumshost1"


def _link_with_traffic(datagrams: int) -> None:
    """NIC, a veth whose peer is in the namespace NS, made anew, and `datagrams` UDP datagrams sent
    across it (the peer answers each with an ICMP port unreachable)."""
    run = lambda *cmd: subprocess.run(cmd, check=True, capture_output=True)  # noqa: E731
    run("ip", "link", "add", NIC, "type", "veth", "peer", "name", PEER, "netns", NS)
    run("ip", "addr", "add", "10.251.0.1/30", "dev", NIC)
    run("ip", "link", "set", NIC, "up")
    run("ip", "netns", "exec", NS, "ip", "addr", "add", "10.251.0.2/30", "dev", PEER)
    run("ip", "netns", "exec", NS, "ip", "link", "set", PEER, "up")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(datagrams):
            s.sendto(b"x" * 100, ("10.251.0.2", 9))
            time.sleep(0.1)

    def sent() -> int:
        with open(f"/sys/class/net/{NIC}/statistics/tx_packets") as f:
            return int(f.read())
    # Datagrams wait in the neighbour queue until ARP has the peer's address: on a busy host they
    # left after the sends returned (1 packet counted of 6 and an ARP request).
    wait_until(lambda: sent() >= datagrams, f"{datagrams} datagrams out of {NIC}", timeout=10)


@pytest.fixture
def namespace():
    subprocess.run(["ip", "netns", "del", NS], capture_output=True)
    subprocess.run(["ip", "netns", "add", NS], check=True)
    yield
    subprocess.run(["ip", "link", "del", NIC], capture_output=True)
    subprocess.run(["ip", "netns", "del", NS], capture_output=True)


def test_an_interface_made_again_under_its_name_counts_on(probe, namespace):
    """A veth deleted and made again restarts its counters at 0 in the kernel: the probe's go on
    from what the first one had counted, so no counter goes backwards. The second one sends more
    than the first: its counters never go below the first's, and only its absence from a listing
    tells it is another."""
    _link_with_traffic(2)
    first = collect(probe)
    subprocess.run(["ip", "link", "del", NIC], check=True)
    assert (NIC,) not in collect(probe).values(host.NET_SENT_BYTES)
    _link_with_traffic(6)
    before = net_dev()[NIC]
    again = collect(probe)
    after = net_dev()[NIC]
    assert before[NET_COLUMNS[host.NET_SENT_PACKETS]] >= 2  # the datagrams, and what IPv6 sends on its own
    for metric, column in NET_COLUMNS.items():
        carried = first.values(metric)[(NIC,)]
        assert carried + before[column] <= again.values(metric)[(NIC,)] <= carried + after[column], metric.name
    assert again.values(host.NET_SENT_BYTES)[(NIC,)] > first.values(host.NET_SENT_BYTES)[(NIC,)] > 0
