"""A full map of exited threads, in the real kernel: a thread that exits then cannot hand its CPU
time to its process, and that loss is counted, shown as a full map, and said in the log."""
import glob
import struct
import subprocess
import sys

from drums.kernel.bpffs import PinnedMap
from tests.agentproc import assert_monotonic, running_agent, samples, scrape

# Threads that start, run a little and end: each exit folds its time into the process's entry.
THREADS = ("import sys, threading\nfor _ in range(20):\n    t = threading.Thread(target=sum, args=(range(10000),)); "
           "t.start(); t.join()\nprint('done', flush=True)\nsys.stdin.read()")
FAKE_TGID = 1 << 30  # above any pid_max: the agent deletes such entries at its next collect


def sched(text: str, name: str, **labels) -> float:
    return samples(text, name)[tuple(sorted({"probe": "sched", **labels}.items()))]


def test_a_full_exited_thread_map_is_counted_shown_and_said():
    logs: list[str] = []
    with running_agent("--probe", "sched", "--graph", "auto", logs=logs) as url:
        port = url.rsplit(":", 1)[1].split("/")[0]
        before = scrape(url)
        (pins,) = glob.glob(f"/sys/fs/bpf/drums_agent_{port}/sched-*")
        exited = PinnedMap(f"{pins}/exited_sched")
        try:  # fill it to the brim with processes that do not exist
            zero = bytes(exited.value_size)
            for i in range(exited.max_entries):
                try:
                    exited.update(struct.pack("<I", FAKE_TGID + i), zero)
                except Exception:  # noqa: BLE001 - full: the map holds real processes too
                    break
        finally:
            exited.close()
        # The kernel keeps a spare element or two per CPU that a program's insert may still take: of
        # ten live processes, the first find room, the others do not.
        procs = [subprocess.Popen([sys.executable, "-c", THREADS], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
                 for _ in range(10)]
        for p in procs:
            p.stdout.readline()
        full = scrape(url)
        for p in procs:
            p.kill()
            p.wait()
        after = scrape(url)  # the fake processes are gone from the map by now
    assert sched(full, "drums_probe_map_fill_ratio", map="exited_sched") == 1.0
    assert sched(after, "drums_probe_map_fill_ratio", map="exited_sched") < 0.5
    lost = sched(full, "drums_probe_dropped_events_total") - sched(before, "drums_probe_dropped_events_total")
    assert lost >= 20  # a process's 20 thread exits at least (others on this machine may have lost theirs too)
    assert_monotonic([before, full, after])
    said = [line for line in logs[0].splitlines() if line.startswith("drums: probe sched:")]
    assert len(said) == 1 and "events lost to full BPF maps" in said[0] and "map exited_sched 100% full" in said[0], said
