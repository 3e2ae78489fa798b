"""process: a child with known memory, threads and storage I/O, read by the probe and checked with /proc."""
import collections
import contextlib
import json
import os
import subprocess
import sys
import time

import psutil
import pytest

from drums.metrics import Snapshot
from drums.proctable import ProcessTable
from tests.conftest import eventually
from drums.probes.process import (
    OPEN_FDS,
    READ_BYTES,
    RESIDENT_MEMORY,
    START_TIME,
    THREADS,
    UNIQUE_MEMORY,
    WRITTEN_BYTES,
    ProcessProbe,
)

MIB = 1 << 20
IO_BYTES = 4 * MIB

# Holds 64 MiB of touched memory and 3 idle threads, writes IO_BYTES to storage (fsync) and reads them
# back with O_DIRECT so both bypass the page cache, then waits until its stdin is closed.
CHILD = r"""
import mmap, os, sys, threading
size, path = int(sys.argv[1]), sys.argv[2]
memory = bytearray(64 << 20)
memory[::4096] = b"\1" * (len(memory) // 4096)
stop = threading.Event()
for _ in range(3):
    threading.Thread(target=stop.wait, daemon=True).start()
fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
assert os.write(fd, b"x" * size) == size
os.fsync(fd)
os.close(fd)
fd = os.open(path, os.O_RDONLY | os.O_DIRECT)
buf = mmap.mmap(-1, size)  # page aligned, as O_DIRECT requires
assert os.readv(fd, [buf]) == size
os.close(fd)
print("ready", flush=True)
sys.stdin.read()
"""


def collect(probe: ProcessProbe) -> Snapshot:
    probe.proctable.refresh(None)  # as the agent does before every collect, without the sched probe
    snap = Snapshot()
    probe.collect(snap)
    return snap


def comm(pid: int) -> str:
    with open(f"/proc/{pid}/comm") as f:
        return f.read().rstrip("\n")


def start_time(pid: int) -> float:
    """Start time as the kernel gives it: boot time plus the starttime field of /proc/<pid>/stat."""
    with open(f"/proc/{pid}/stat") as f:
        ticks = int(f.read().rsplit(")", 1)[1].split()[19])
    with open("/proc/stat") as f:
        btime = next(int(line.split()[1]) for line in f if line.startswith("btime "))
    return btime + ticks / os.sysconf("SC_CLK_TCK")


def state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0]


def missing_pid() -> int:
    with open("/proc/sys/kernel/pid_max") as f:
        return int(f.read())  # PIDs are allocated below pid_max


def fstype_of(path) -> str:
    """Filesystem type of the mount holding `path`: the last, longest matching mountpoint."""
    best = ("", "")
    with open("/proc/self/mounts") as f:
        for line in f:
            mountpoint, fstype = line.split()[1:3]
            inside = os.path.commonpath([mountpoint, str(path)]) == mountpoint
            if inside and len(mountpoint) >= len(best[0]):
                best = (mountpoint, fstype)
    return best[1]


@pytest.fixture
def probe():
    probe = ProcessProbe(ProcessTable(), interval=0)
    probe.start()
    return probe


@pytest.fixture
def child(tmp_path):
    if fstype_of(tmp_path) in ("tmpfs", "ramfs"):
        pytest.skip(f"{tmp_path} is in memory, so writes to it are not storage I/O")
    argv = [sys.executable, "-c", CHILD, str(IO_BYTES), str(tmp_path / "data")]
    # Leaving the block closes the child's stdin, which ends it, and reaps it.
    with subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout.readline() == "ready\n"
        yield proc


def test_status_once_started(probe):
    assert probe.name == "process"
    assert (probe.status.attached, probe.status.attach_type) == (True, "psutil")


def test_child_values_match_proc(probe, child):
    pid = child.pid
    probe.set_pids([pid])
    snap = collect(probe)
    with open(f"/proc/{pid}/statm") as f:
        resident = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    fds = len(os.listdir(f"/proc/{pid}/fd"))

    labels = (str(pid), comm(pid))
    assert {m: set(snap.values(m)) for m in snap.series} == {m: {labels} for m in probe.metrics}
    one = {metric: snap.values(metric)[labels] for metric in probe.metrics}
    assert one[THREADS] == 4
    assert one[RESIDENT_MEMORY] == resident
    assert 64 * MIB <= one[RESIDENT_MEMORY] <= 96 * MIB  # the interpreter itself takes 10-20 MiB
    assert 64 * MIB <= one[UNIQUE_MEMORY] <= one[RESIDENT_MEMORY]
    assert one[OPEN_FDS] == fds
    # write_bytes is charged when a page is dirtied, so the file's pages count exactly once.
    assert IO_BYTES <= one[WRITTEN_BYTES] <= IO_BYTES + 256 * 1024
    # No upper bound: a cold page cache makes interpreter start-up read from disk too.
    assert one[READ_BYTES] >= IO_BYTES
    assert one[START_TIME] == pytest.approx(start_time(pid), abs=0.01)


def test_only_chosen_pids_are_read(probe, child):
    probe.set_pids([missing_pid(), child.pid])
    snap = collect(probe)
    assert {labels[0] for metric in snap.series for labels in snap.values(metric)} == {str(child.pid)}

    probe.set_pids([os.getpid()])
    snap = collect(probe)
    assert set(snap.values(THREADS)) == {(str(os.getpid()), comm(os.getpid()))}
    assert set(probe._procs) == {os.getpid()}  # PIDs no longer chosen leave the cache


def test_missing_pid_yields_nothing(probe):
    probe.set_pids([missing_pid()])
    assert collect(probe).series == {}


def test_exited_child_is_dropped(probe, child):
    probe.set_pids([child.pid])
    assert collect(probe).values(THREADS)
    child.stdin.close()
    child.wait()
    assert collect(probe).series == {}
    assert probe._procs == {}


def test_zombie_is_skipped(probe):
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        # Not reaped yet: wait for the exit without wait(2), by polling its state.
        while state(proc.pid) != "Z":
            time.sleep(0.01)
        probe.set_pids([proc.pid])
        assert collect(probe).series == {}
    finally:
        proc.wait()


def _respawn_at(pid: int, argv: list) -> subprocess.Popen:
    """Start argv with PID `pid` by setting the namespace's last PID; other forks can race, so retry."""
    for _ in range(20):
        try:
            with open("/proc/sys/kernel/ns_last_pid", "w") as f:
                f.write(str(pid - 1))
        except OSError as exc:
            pytest.skip(f"cannot choose the next PID: {exc}")
        proc = subprocess.Popen(argv)
        if proc.pid == pid:
            return proc
        proc.kill()
        proc.wait()
    pytest.skip(f"another process kept taking PID {pid}")


def exec_done(pid: int) -> None:
    assert comm(pid) == "sleep"


@contextlib.contextmanager
def a_reused_pid(probe: ProcessProbe, read_start):
    """A `sleep` the probe reads once (`read_start` gives the start times read), killed, and
    another `sleep` started with its PID: yields (the PID, the first one's start time)."""
    first = subprocess.Popen(["sleep", "60"])
    pid = first.pid
    probe.set_pids([pid])
    # Popen returns once the child has let go of our memory, a moment before exec names it "sleep".
    eventually(lambda: exec_done(pid))
    first_start = read_start()[(str(pid), "sleep")]
    time.sleep(0.05)  # start times have clock-tick resolution: the two must not share a tick
    first.kill()
    first.wait()
    second = _respawn_at(pid, ["sleep", "61"])
    try:
        eventually(lambda: exec_done(pid))
        yield pid, first_start
    finally:
        second.kill()
        second.wait()


def test_reused_pid_is_not_read_as_the_dead_process(probe):
    with a_reused_pid(probe, lambda: collect(probe).values(START_TIME)) as (pid, first_start):
        snaps = [collect(probe), collect(probe)]
        assert all(first_start not in snap.values(START_TIME).values() for snap in snaps)
        assert snaps[-1].values(START_TIME) == {(str(pid), "sleep"): pytest.approx(start_time(pid), abs=0.01)}


def test_a_cached_process_is_read_again_once_the_kernel_says_its_pid_changed():
    """Values are cached for the interval; a PID the sched probe marks (it exited and came back,
    or exec'd) is read anew, even when another refresh (a job's collect) came in between."""
    table = ProcessTable()
    # A process first read is given a phase in the interval (reads spread over it), so the next
    # read of some PIDs is due at once with 60 s: with this interval it never is in the test.
    probe = ProcessProbe(table, interval=1e9)
    probe.start()

    def collect_told(renamed: set) -> dict:
        table.refresh(renamed)
        snap = Snapshot()
        probe.collect(snap)
        return snap.values(START_TIME)

    with a_reused_pid(probe, lambda: collect_told(set())) as (pid, first_start):
        assert collect_told(set()) == {(str(pid), "sleep"): first_start}  # not told: the cache stands
        table.refresh({pid})  # the exit, as a job's collect sees it
        assert collect_told(set()) == {(str(pid), "sleep"): pytest.approx(start_time(pid), abs=0.01)}
        assert start_time(pid) != pytest.approx(first_start, abs=0.001)


# Grows by the bytes named on each line of its stdin (touching every page), then sleeps in read().
GROWER = ("import sys\nheld = []\nprint('ready', flush=True)\nfor line in sys.stdin:\n"
          "    held.append(bytearray(b'\\1') * int(line))\n    print('grown', flush=True)\n")


def collect_with_sched(sched_probe, probe: ProcessProbe) -> Snapshot:
    """A collect as the agent makes one: the table told by the sched probe, which reads first."""
    probe.proctable.refresh(sched_probe.renamed())
    snap = Snapshot()
    sched_probe.collect(snap)
    probe.collect(snap)
    return snap


def test_a_process_that_has_not_run_is_not_read_again_and_one_that_has_is(sched_probe, proctable):
    """With the sched probe telling the process table which processes ran, a sleeping process is
    read once, not at every interval (here every collect); once it wakes and grows, the next
    collect reads it, and gives the memory the kernel gives."""
    probe = ProcessProbe(proctable, interval=0, idle_interval=1e9)
    probe.start()
    reads = collections.Counter()
    read = probe._read
    probe._read = lambda pid, *rest: (reads.update([pid]), read(pid, *rest))[1]  # the real read, counted
    child = subprocess.Popen([sys.executable, "-c", GROWER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)
    try:
        assert child.stdout.readline() == "ready\n"
        pid = child.pid
        probe.set_pids([pid])

        def collect_rss() -> int:
            return collect_with_sched(sched_probe, probe).values(RESIDENT_MEMORY)[(str(pid), comm(pid))]

        def sleeping() -> None:
            assert state(pid) == "S"

        eventually(sleeping, timeout=10)
        collect_rss(), collect_rss()  # the first read, and one more if it ran after the sched probe looked
        before, asleep = reads[pid], collect_rss()
        for _ in range(5):
            assert collect_rss() == asleep
        assert reads[pid] == before  # not read again: it has not run
        child.stdin.write(f"{64 * MIB}\n")
        child.stdin.flush()
        assert child.stdout.readline() == "grown\n"
        eventually(sleeping, timeout=10)
        grown = collect_rss()
        assert reads[pid] == before + 1
        assert grown == psutil.Process(pid).memory_info().rss >= asleep + 64 * MIB
    finally:
        child.stdin.close()
        child.wait(10)


def test_an_idle_process_is_read_again_once_its_wait_runs_out(sched_probe, proctable):
    """A collect looks only at the processes that may be due (came, renamed, ran): one that sleeps
    is looked at again when its wait runs out (here 0.3 to 0.6 s, by its PID), and read then,
    though nothing about it changed."""
    probe = ProcessProbe(proctable, interval=0.5, idle_interval=0.6)
    probe.start()
    reads = collections.Counter()
    read = probe._read
    probe._read = lambda pid, *rest: (reads.update([pid]), read(pid, *rest))[1]  # the real read, counted
    with subprocess.Popen(["sleep", "60"]) as sleeper:
        try:
            def asleep_and_still() -> None:  # done starting: it runs no more, so nothing but time makes it due
                before = psutil.Process(sleeper.pid).cpu_times()
                time.sleep(0.1)
                assert state(sleeper.pid) == "S" and psutil.Process(sleeper.pid).cpu_times() == before
            eventually(asleep_and_still, timeout=10)
            probe.set_pids([sleeper.pid])
            end = time.monotonic() + 2.5
            while time.monotonic() < end:
                snap = collect_with_sched(sched_probe, probe)
                assert (str(sleeper.pid), "sleep") in snap.values(RESIDENT_MEMORY)
                time.sleep(0.05)
            # Read first at once, then at the first collect after each wait ran out: at least twice
            # more in 2.5 s (with collects up to 0.3 s apart on a loaded host), at most every 0.3 s;
            # once alone if only a change could make it due.
            assert 3 <= reads[sleeper.pid] <= 9
        finally:
            sleeper.kill()


# Names itself (prctl PR_SET_NAME) as each line of input says, and answers "named".
RENAMER = r"""
import ctypes, sys
print("ready", flush=True)
for line in sys.stdin:
    ctypes.CDLL(None).prctl(15, line.strip().encode(), 0, 0, 0)
    print("named", flush=True)
"""


def test_the_rows_told_as_changes_are_the_rows_given(sched_probe, proctable):
    """Each collect tells its rows as what changed since the one before (the budget applies them
    instead of comparing every row): applied to the rows of the collect before, they give this
    one's, through a rename, a process that grows, one that exits and one that is chosen anew."""
    probe = ProcessProbe(proctable, interval=0.2, idle_interval=1e9)
    probe.start()
    sleepers = [subprocess.Popen(["sleep", "60"]) for _ in range(2)]
    grower, renamer = (subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True) for code in (GROWER, RENAMER))
    try:
        assert grower.stdout.readline() == renamer.stdout.readline() == "ready\n"
        for sleeper in sleepers:
            eventually(lambda: exec_done(sleeper.pid))
        chosen = [grower.pid, renamer.pid, sleepers[0].pid]
        probe.set_pids(chosen)
        mark, held = None, {}

        def check() -> Snapshot:
            nonlocal mark
            snap = collect_with_sched(sched_probe, probe)
            for metric in probe.metrics:
                told = snap.changes[(metric,)]
                assert mark is None or told.since == mark
                rows = held.get(metric, {})
                for labels in told.gone:
                    rows.pop(labels, None)
                rows.update(told.rows)
                held[metric] = rows
                assert rows == dict(snap.series.get(metric, ())), metric.name
            mark = told.mark
            return snap

        def shown(pid: int, name: str, metric=START_TIME):
            values = check().values(metric)
            assert (str(pid), name) in values
            return values[(str(pid), name)]

        shown(grower.pid, comm(grower.pid))
        renamer.stdin.write("dozer\n")  # renamed
        renamer.stdin.flush()
        assert renamer.stdout.readline() == "named\n"
        eventually(lambda: shown(renamer.pid, "dozer"))
        grower.stdin.write(f"{32 * MIB}\n")  # grows, and is read again within the interval
        grower.stdin.flush()
        assert grower.stdout.readline() == "grown\n"
        grown = psutil.Process(grower.pid).memory_info().rss

        def grown_shown():
            assert shown(grower.pid, comm(grower.pid), RESIDENT_MEMORY) == grown
        eventually(grown_shown)
        sleepers[0].kill()  # exits
        sleepers[0].wait()

        def gone():
            assert (str(sleepers[0].pid), "sleep") not in check().values(START_TIME)
        eventually(gone)
        probe.set_pids(chosen + [sleepers[1].pid])  # chosen anew
        assert (str(sleepers[1].pid), "sleep") in check().values(START_TIME)
        for _ in range(3):
            check()
    finally:
        for child in (grower, renamer):
            child.stdin.close()
            child.wait(10)
        for sleeper in sleepers:
            sleeper.kill()
            sleeper.wait()


def test_the_table_lists_proc_only_when_the_sched_probe_says_a_process_came_or_went(sched_probe):
    """The sched probe marks every process forked, exec'd, renamed or ended: told so, a refresh
    whose notices are empty lists nothing, and one that follows a fork or an exit has the process
    in or out. Other tests' processes come and go on the host, so only quiet refreshes are checked
    for having listed nothing."""
    table = ProcessTable()
    listings = []
    listing = table.listing
    table.listing = lambda: (listings.append(1), listing())[1]  # the real listing, counted
    sched_probe.renamed()  # what came before this test
    table.refresh(None)
    child = subprocess.Popen(["sleep", "60"])
    try:
        def named() -> None:  # Popen returns as exec closes its files, before exec names the process
            table.refresh(sched_probe.renamed(), complete=True)
            assert table.name(child.pid) == "sleep"
        eventually(named)
        quiet = 0
        for _ in range(40):
            notices, before = sched_probe.renamed(), len(listings)
            table.refresh(notices, complete=True)
            if notices == set():
                quiet += 1
                assert len(listings) == before
            time.sleep(0.01)
        assert quiet >= 10 and table.alive(child.pid)
    finally:
        child.kill()
        child.wait()
    table.refresh(sched_probe.renamed(), complete=True)
    assert not table.alive(child.pid)


# Grows its touched memory by the bytes each line of input says, and answers "grown".
GROWER = r"""
import sys
kept = [bytearray(48 << 20)]
kept[0][::4096] = b"\1" * (len(kept[0]) // 4096)
print("ready", flush=True)
for line in sys.stdin:
    kept.append(b"\1" * int(line))
    print("grown", flush=True)
"""


def test_uss_is_read_again_once_rss_moved_by_a_32nd_and_a_kernel_thread_s_never(probe, monkeypatch):
    full_reads = collections.Counter()
    real = psutil.Process.memory_full_info
    monkeypatch.setattr(psutil.Process, "memory_full_info", lambda p: full_reads.update([p.pid]) or real(p))
    kthread = next(int(pid) for pid in os.listdir("/proc") if pid.isdigit()
                   and int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[6]) & 0x200000)  # PF_KTHREAD
    with subprocess.Popen([sys.executable, "-c", GROWER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                          text=True) as grower:
        assert grower.stdout.readline() == "ready\n"
        probe.set_pids([grower.pid, kthread])

        def grow_and_read(size: int) -> tuple[int, int]:
            grower.stdin.write(f"{size}\n")
            grower.stdin.flush()
            assert grower.stdout.readline() == "grown\n"
            probe.proctable.refresh(set())  # told, as by the sched probe: no process renamed or new
            snap = Snapshot()
            probe.collect(snap)
            labels = (str(grower.pid), comm(grower.pid))
            return snap.values(RESIDENT_MEMORY)[labels], snap.values(UNIQUE_MEMORY)[labels]
        rss, uss = grow_and_read(0)
        assert full_reads[grower.pid] == 1 and 48 * MIB <= uss <= rss
        # 1 MiB more is less than a 32nd of its RSS: the USS of the first read is given again.
        rss2, uss2 = grow_and_read(MIB)
        assert (full_reads[grower.pid], uss2) == (1, uss) and rss + MIB - 64 * 1024 <= rss2 <= rss + MIB + 256 * 1024
        # 8 MiB more is: read anew, with the 9 MiB grown since.
        rss3, uss3 = grow_and_read(8 * MIB)
        assert full_reads[grower.pid] == 2 and uss + 9 * MIB - 64 * 1024 <= uss3 <= uss + 9 * MIB + 256 * 1024
        grower.stdin.close()
    snap = collect(probe)
    kernel = (str(kthread), comm(kthread))
    assert (snap.values(RESIDENT_MEMORY)[kernel], snap.values(UNIQUE_MEMORY)[kernel]) == (0, 0)
    assert full_reads[kthread] == 0


# Run as root to import, then as nobody (no CAP_SYS_PTRACE): reads the PID it is given twice, as two
# scrapes would, and prints the rows of each and how many times the process was read.
AS_NOBODY = r"""
import json, os, sys
from drums.metrics import Snapshot
from drums.probes.process import ProcessProbe
from drums.proctable import ProcessTable
table = ProcessTable()
probe = ProcessProbe(table, interval=1e9)  # due again only when the kernel says it changed
probe.start()
probe.set_pids([int(sys.argv[1])])
reads, read = [], probe._read
probe._read = lambda *args: reads.append(args[0]) or read(*args)
os.setgid(65534)
os.setuid(65534)
out = []
for _ in range(2):
    table.refresh(set())  # as the sched probe tells it: no process renamed
    snap = Snapshot()
    probe.collect(snap)
    out.append({m.name: v for m, rows in snap.series.items() for _, v in rows})
print(json.dumps({"rows": out, "reads": len(reads)}))
"""


def test_a_process_whose_memory_and_io_the_kernel_denies_keeps_its_other_rows_and_its_cadence():
    """The agent run without CAP_SYS_PTRACE, or a process of another user namespace: smaps_rollup
    and io are denied, statm, status and the fd directory are not. The process keeps the rows it
    can give, and is read again when due, not at every scrape."""
    with subprocess.Popen(["sleep", "60"]) as sleeper:
        eventually(lambda: exec_done(sleeper.pid))
        done = subprocess.run([sys.executable, "-c", AS_NOBODY, str(sleeper.pid)], capture_output=True, text=True,
                              timeout=30)
        with open(f"/proc/{sleeper.pid}/statm") as f:
            resident = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        fds = len(os.listdir(f"/proc/{sleeper.pid}/fd"))
        started = start_time(sleeper.pid)
        sleeper.kill()
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout)
    assert got["reads"] == 1
    first, second = got["rows"]
    assert first == second
    assert first == {RESIDENT_MEMORY.name: resident, THREADS.name: 1, OPEN_FDS.name: fds,
                     START_TIME.name: pytest.approx(started, abs=0.01)}
