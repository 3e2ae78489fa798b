"""What each socket and scheduler probe costs per kernel event, beside the floor: an empty BPF
program on the same tracepoint, attached as the probe's are (tp_btf where the kernel offers it),
which pays the same dispatch and does nothing.

Two measures, both printed:
- the program's own run time per event, from the kernel's BPF statistics
  (kernel.bpf_stats_enabled: run_time_ns / run_cnt of each program);
- the time added to a fixed workload per operation, with the statistics off (they cost time
  themselves), against the same workload with no program attached.
Workloads run in a child process pinned to one CPU: 1-byte send()+recv() on a unix datagram
socketpair and on a loopback TCP connection (two sock_send_length/sock_recv_length events per
operation), and a pipe ping-pong between two processes on one CPU (per round trip two
sched_switch and two sched_wakeup events). Goal: the probes cost at most 1.3x the floor.

    .venv/bin/python bench/event_cost.py [--rounds 15] [--ops 50000] [--pingpongs 25000]
"""
from __future__ import annotations

import argparse
import glob
import json
import logging
import os
import shutil
import subprocess
import sys
import textwrap

from common import (BenchError, ForeignWatch, bpftool_json, fmt, main_wrapper, median, percentile,
                    print_table, progress, ratio, require_root, require_tool)
from floor import Floor

PIN_ROOT = "/sys/fs/bpf/drums_bench"
# The sockets probe as `drums agent --splice-tracepoints` loads it, measured too where that differs
# (a kernel without kprobes: the syscall tracepoints then slow every system call).
SPLICE_TRACEPOINTS = "drums --splice-tracepoints"
STATS_SYSCTL = "/proc/sys/kernel/bpf_stats_enabled"

# probe -> its workloads, and the (tracepoint, Drums program) pairs those workloads exercise.
PROBES = {
    "sockets": (("unix", "tcp"), (("sock_send_length", "on_send"), ("sock_recv_length", "on_recv"))),
    "sched": (("pingpong",), (("sched_switch", "on_switch"), ("sched_wakeup", "on_wakeup"))),
}
WORKLOAD_LABEL = {
    "unix": "send+recv 1 B, unix dgram socketpair",
    "tcp": "send+recv 1 B, loopback TCP",
    "pingpong": "pipe ping-pong round trip, 2 processes on 1 CPU",
}
# The workload, run as `python -c WORKLOAD kind ops batches cpu`; prints ns per op of each batch
# and the probed events per op, counted from the workload's own view (not from BPF, which would
# also count every other process on the host): a send and a receive call per socket operation;
# for the ping-pong, each context switch of the two processes (sched_switch) and each voluntary
# one, which a wakeup ends (sched_wakeup).
WORKLOAD = textwrap.dedent("""
    import gc, json, os, resource, socket, sys, time
    kind, ops, batches, cpu = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    os.sched_setaffinity(0, {cpu})
    n = max(1, ops // batches)
    out = []
    if kind == "pingpong":
        a_r, a_w = os.pipe(); b_r, b_w = os.pipe()
        child = os.fork()
        if child == 0:
            read, write = os.read, os.write
            for _ in range(n * batches):
                read(a_r, 1); write(b_w, b"x")
            os._exit(0)
        read, write = os.read, os.write
        gc.disable()
        before = resource.getrusage(resource.RUSAGE_SELF)
        for _ in range(batches):
            t = time.perf_counter_ns()
            for _ in range(n):
                write(a_w, b"x"); read(b_r, 1)
            out.append((time.perf_counter_ns() - t) / n)
        after = resource.getrusage(resource.RUSAGE_SELF)
        os.waitpid(child, 0)
        kid = resource.getrusage(resource.RUSAGE_CHILDREN)
        voluntary = after.ru_nvcsw - before.ru_nvcsw + kid.ru_nvcsw
        switches = voluntary + after.ru_nivcsw - before.ru_nivcsw + kid.ru_nivcsw
        events = {"sched_switch": switches / (n * batches), "sched_wakeup": voluntary / (n * batches)}
    else:
        if kind == "unix":
            a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        else:
            srv = socket.socket(); srv.bind(("127.0.0.1", 0)); srv.listen(1)
            a = socket.create_connection(srv.getsockname()); b, _ = srv.accept()
            a.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        send, recv = a.send, b.recv
        for _ in range(1000):
            send(b"x"); recv(1)
        gc.disable()
        for _ in range(batches):
            t = time.perf_counter_ns()
            for _ in range(n):
                send(b"x"); recv(1)
            out.append((time.perf_counter_ns() - t) / n)
        events = {"sock_send_length": 1.0, "sock_recv_length": 1.0}
    print(json.dumps({"ns_per_op": out, "events_per_op": events}))
""")


def run_workload(kind: str, ops: int, batches: int, cpu: int) -> tuple[float, dict[str, float]]:
    """ns per operation of the fastest batch (the one least disturbed by the rest of the host),
    and the probed events per operation, by tracepoint."""
    proc = subprocess.run([sys.executable, "-c", WORKLOAD, kind, str(ops), str(batches), str(cpu)],
                          capture_output=True, text=True, timeout=300, check=False)
    if proc.returncode != 0:
        raise BenchError(f"workload {kind} failed: {proc.stderr.strip()[-300:]}")
    data = json.loads(proc.stdout)
    return min(data["ns_per_op"]), data["events_per_op"]


def make_probe(name: str, condition: str = "drums"):
    from drums.kernel.features import Features
    from drums.probes.sched import SchedProbe
    from drums.probes.sockets import SocketsProbe
    from drums.proctable import ProcessTable

    if name == "sched":
        return SchedProbe(Features(), ProcessTable(), pin_root=PIN_ROOT)
    return SocketsProbe(Features(), ProcessTable(), pin_root=PIN_ROOT,
                        splice_tracepoints=condition == SPLICE_TRACEPOINTS)


def drums_prog_ids(probe_name: str) -> dict[str, int]:
    """tracepoint -> id of the program Drums attached there, found through the probe's link pins."""
    out = {}
    for pin in glob.glob(os.path.join(PIN_ROOT, f"{probe_name}-*", "link*")):
        link = bpftool_json("link", "show", "pinned", pin)
        if link and link.get("tp_name"):
            out[link["tp_name"]] = link["prog_id"]
    return out


def prog_stats(prog_id: int) -> tuple[int, int]:
    """(run_time_ns, run_cnt) of a program; zero while kernel.bpf_stats_enabled is 0."""
    p = bpftool_json("prog", "show", "id", str(prog_id)) or {}
    return p.get("run_time_ns", 0), p.get("run_cnt", 0)


def set_stats(value: int) -> int:
    with open(STATS_SYSCTL) as f:
        old = int(f.read())
    with open(STATS_SYSCTL, "w") as f:
        f.write(str(value))
    return old


def run(args) -> None:
    require_root()
    require_tool("bpftool")
    from drums.kernel.features import Features
    from drums.kernel.bpffs import PIN_ROOT as AGENT_PIN_ROOT
    from drums.probes.sockets import SPLICE_UNCOUNTED_WHY

    if os.path.realpath(PIN_ROOT) == os.path.realpath(AGENT_PIN_ROOT):
        raise BenchError("the benchmark's pin root must differ from the agent's")
    tracepoints = [tp for _, pairs in PROBES.values() for tp, _ in pairs]
    watch = ForeignWatch(tracepoints)
    floor = Floor(Features().kernel_headers)
    added: dict[tuple[str, str], list[float]] = {}  # (workload, condition) -> ns/op per round
    events_per_op: dict[tuple[str, str], list[float]] = {}  # (workload, tracepoint) -> per run
    self_ns: dict[tuple[str, str], float] = {}  # (tracepoint, floor|drums) -> ns per program run
    found_by_name: dict[str, bool] = {}
    old_stats = set_stats(0)
    probe = None

    def ops_of(workload):
        return args.pingpongs if workload == "pingpong" else args.ops

    def measure(workload, condition):
        ns, events = run_workload(workload, ops_of(workload), args.batches, args.cpu)
        added.setdefault((workload, condition), []).append(ns)
        if condition == "none":
            for tp, count in events.items():
                events_per_op.setdefault((workload, tp), []).append(count)

    logging.getLogger("drums").setLevel(logging.ERROR)  # the probe's caveat, said once below instead
    splice_differs = not Features().kprobes
    try:
        # Pass 1, statistics off: time per operation, conditions rotated round by round.
        order = ["none", "floor", "drums"] + ([SPLICE_TRACEPOINTS] if splice_differs else [])
        for rnd in range(args.rounds):
            for probe_name, (workloads, pairs) in PROBES.items():
                tps = [tp for tp, _ in pairs]
                for condition in order:
                    if condition == SPLICE_TRACEPOINTS and probe_name != "sockets":
                        continue
                    progress(f"round {rnd + 1}/{args.rounds}: {probe_name} workloads, {condition}")
                    if condition == "none":
                        watch.look()
                    if condition == "floor":
                        floor.attach(tps)
                    elif condition != "none":
                        probe = make_probe(probe_name, condition)
                        probe.start()
                    try:
                        for w in workloads:
                            measure(w, condition)
                    finally:
                        floor.detach()
                        if probe is not None:
                            probe.unload()
                            probe = None
            order = order[1:] + order[:1]

        # Pass 2, statistics on: each program's own time per run, and events per operation.
        set_stats(1)
        for probe_name, (workloads, pairs) in PROBES.items():
            tps = [tp for tp, _ in pairs]
            for condition in ("floor", "drums"):
                progress(f"bpf_stats: {probe_name} workloads, {condition}")
                if condition == "floor":
                    floor.attach(tps)
                    ids = floor.prog_ids(tps)
                else:
                    probe = make_probe(probe_name)
                    probe.start()
                    ids = drums_prog_ids(probe_name)
                    listed = {(p.get("name"), p["id"]) for p in bpftool_json("prog", "show") or []}
                    for tp, fn in pairs:
                        found = (fn, ids.get(tp)) in listed
                        found_by_name[fn] = "not attached" if tp not in ids else "yes" if found else "no"
                try:
                    before = {tp: prog_stats(ids[tp]) for tp in tps if tp in ids}
                    for w in workloads:
                        run_workload(w, ops_of(w), args.batches, args.cpu)
                    after = {tp: prog_stats(ids[tp]) for tp in tps if tp in ids}
                finally:
                    floor.detach()
                    if probe is not None:
                        probe.unload()
                        probe = None
                for tp in tps:
                    if tp not in ids:
                        self_ns[tp, condition] = 0.0  # the probe's path needs no program there
                        continue
                    d_ns, d_cnt = (after[tp][0] - before[tp][0]), (after[tp][1] - before[tp][1])
                    self_ns[tp, condition] = d_ns / d_cnt if d_cnt else float("nan")
    finally:
        set_stats(old_stats)
        if probe is not None:
            probe.unload()
        floor.close()
        shutil.rmtree(PIN_ROOT, ignore_errors=True)  # the probes remove their own dirs, not the root

    rows = []
    for probe_name, (_, pairs) in PROBES.items():
        for tp, fn in pairs:
            f, d = self_ns.get((tp, "floor"), float("nan")), self_ns.get((tp, "drums"), float("nan"))
            program = fn if found_by_name.get(fn) != "not attached" else "no program on this path"
            rows.append([f"{tp} ({probe_name}: {program})", fmt(f, 1), fmt(d, 1), ratio(d, f)])
    print_table("Per-event cost: the program's own run time (kernel bpf_stats)",
                ["event (probe: program)", "empty program ns/run", "Drums ns/run", "Drums / empty"], rows,
                ["run_time_ns / run_cnt over the workloads below; the statistics themselves add a clock "
                 "read per run to both columns.",
                 "Drums programs found by name with `bpftool prog show -j`: "
                 + ", ".join(f"{fn} {found}" for fn, found in found_by_name.items())])

    rows = []
    for probe_name, (workloads, pairs) in PROBES.items():
        for w in workloads:
            none = median(added[w, "none"])
            # Paired by round: a slow drift of the host (another session's programs coming and
            # going, a busy neighbour) cancels out within a round.
            fl = median(f - n for f, n in zip(added[w, "floor"], added[w, "none"]))
            events = sum(median(events_per_op.get((w, tp), [0])) for tp, _ in pairs)
            for condition, also in (("drums", ""), (SPLICE_TRACEPOINTS, ", --splice-tracepoints")):
                if (w, condition) not in added:
                    continue
                dr = median(d - n for d, n in zip(added[w, condition], added[w, "none"]))
                per_event = (f"{fmt(fl / events, 1)} / {fmt(dr / events, 1)}" if events else "n/a")
                rows.append([f"{WORKLOAD_LABEL[w]} ({probe_name}{also})", fmt(none, 0), fmt(fl, 1), fmt(dr, 1),
                             ratio(dr, fl), fmt(events, 2), per_event])
    notes = watch.notes() + [
        f"ns per operation: the fastest of {args.batches} batches of a run (other work on the host only "
        f"ever adds time); added ns: median over {args.rounds} rounds of the difference to the same round's "
        "run without programs; "
        f"{args.ops:,} socket operations or {args.pingpongs:,} round trips per run, on CPU {args.cpu}; "
        "added = with programs attached minus with none. Goal: Drums at most 1.3x the floor.",
        "spread of the added ns/op over the rounds (25th to 75th percentile): " + "; ".join(
            f"{w} {c} {_spread(added[w, c], added[w, 'none'])}"
            for w in WORKLOAD_LABEL for c in ("floor", "drums", SPLICE_TRACEPOINTS) if (w, c) in added),
    ] + ([f"this kernel has no kprobes: {SPLICE_UNCOUNTED_WHY} (the --splice-tracepoints rows: two per "
          "socket operation, each taking the kernel's syscall tracing path)"] if splice_differs else [])
    print_table("Per-event cost: time added to a workload",
                ["workload (probe)", "no program ns/op", "empty added ns/op", "Drums added ns/op",
                 "Drums / empty", "events/op", "added ns/event empty / Drums"], rows, notes)


def _spread(with_programs: list[float], without: list[float]) -> str:
    diffs = [a - b for a, b in zip(with_programs, without)]
    return f"{fmt(percentile(diffs, 25), 0)}..{fmt(percentile(diffs, 75), 0)}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=15, help="rounds of none/floor/drums (default 15)")
    parser.add_argument("--ops", type=int, default=50_000, help="socket operations per run (default 50000)")
    parser.add_argument("--pingpongs", type=int, default=25_000, help="round trips per run (default 25000)")
    parser.add_argument("--batches", type=int, default=5, help="timed batches per run (default 5)")
    parser.add_argument("--cpu", type=int, default=1, help="CPU the workload runs on (default 1)")
    args = parser.parse_args()
    main_wrapper(lambda: run(args))


if __name__ == "__main__":
    main()
