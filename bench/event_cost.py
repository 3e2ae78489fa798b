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

With --paths all, each probe on every attach path this kernel offers, beside empty programs on that
path (on kprobes, on fexit); with --kernel 6.1, then so in a VM of Debian 12's kernel, which offers
the fentry and kprobe paths that this machine's does not (`make bench` does both).

    .venv/bin/python bench/event_cost.py [--rounds 15] [--ops 50000] [--pingpongs 25000] [--paths all] [--kernel 6.1]
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
import tempfile
import textwrap
from typing import NamedTuple

from common import (BenchError, ForeignWatch, bpftool_json, fmt, main_wrapper, median, percentile,
                    print_table, progress, ratio, require_root, require_tool)
from floor import Floor

PIN_ROOT = "/sys/fs/bpf/drums_bench"
# The sockets probe as `drums agent --splice-tracepoints` loads it, measured too where that differs
# (a kernel without kprobes: the syscall tracepoints then slow every system call).
SPLICE_TRACEPOINTS = "--splice-tracepoints"
STATS_SYSCTL = "/proc/sys/kernel/bpf_stats_enabled"
VM_TIMEOUT = 45 * 60  # seconds for --kernel's VM to boot and measure under emulation

class Condition(NamedTuple):
    """What a workload runs beside: nothing, empty programs or Drums's, on an attach path."""
    kind: str  # none, floor or drums
    path: str = ""
    splice: bool = False  # the sockets probe as `drums agent --splice-tracepoints` loads it

    def __str__(self) -> str:
        return " ".join([self.kind, self.path] + [SPLICE_TRACEPOINTS] * self.splice).strip()


NONE = Condition("none")

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


def probe_class(name: str):
    from drums.probes.sched import SchedProbe
    from drums.probes.sockets import SocketsProbe
    return SchedProbe if name == "sched" else SocketsProbe


def make_probe(name: str, path: str, splice_tracepoints: bool = False):
    """The probe held to the attach path `path`, as `drums agent --attach NAME=PATH` holds it."""
    from drums.kernel.features import Features
    from drums.probes.registry import held_to
    from drums.proctable import ProcessTable

    extra = {"splice_tracepoints": splice_tracepoints} if name == "sockets" else {}
    return held_to(probe_class(name)(Features(), ProcessTable(), pin_root=PIN_ROOT, **extra), path)


def measured_paths(every: bool) -> dict[str, list[str]]:
    """probe -> the attach paths measured: every one this kernel offers, or the agent's alone."""
    from drums.kernel.features import Features
    from drums.probes.bpf import usable_paths

    features = Features()
    out = {}
    for name in PROBES:
        offered = [p.name for p in usable_paths(probe_class(name).paths, features)]
        if not offered:
            raise BenchError(f"this kernel offers probe {name} no attach path")
        out[name] = offered if every else offered[:1]
    return out


def floor_attachments(name: str, path: str) -> list[tuple[str, str, str]]:
    """Where the probe's path attaches on this kernel, for the empty programs to attach alike."""
    probe = make_probe(name, path)
    return probe.attachments(probe.paths[0])


def fexit_targets(paths: dict[str, list[str]]) -> tuple[str, ...]:
    """The kernel functions the sockets probe's fentry path exits from: those its kprobe path
    returns from (each family's sendmsg and recvmsg, and what splice and sendfile call)."""
    if "fentry" not in paths["sockets"]:
        return ()
    return tuple(t for kind, t, _ in floor_attachments("sockets", "kprobe") if kind == "kretprobe")


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
    paths = measured_paths(args.paths == "all")
    floor = Floor(Features().kernel_headers, fexit_targets(paths))
    added: dict[tuple[str, Condition], list[float]] = {}  # (workload, condition) -> ns/op per round
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
        if condition == NONE:
            for tp, count in events.items():
                events_per_op.setdefault((workload, tp), []).append(count)

    logging.getLogger("drums").setLevel(logging.ERROR)  # the probe's caveat, said once below instead
    splice_differs = not Features().kprobes
    # probe -> its conditions (what runs, on which path, with --splice-tracepoints): none, then the
    # empty programs and Drums on each path measured.
    orders = {name: [NONE] + [Condition(kind, path) for path in ps for kind in ("floor", "drums")]
              + ([Condition("drums", ps[0], True)] if splice_differs and name == "sockets" else [])
              for name, ps in paths.items()}
    try:
        # Pass 1, statistics off: time per operation, conditions rotated round by round.
        for rnd in range(args.rounds):
            for probe_name, (workloads, _) in PROBES.items():
                order = orders[probe_name]
                for condition in order[rnd % len(order):] + order[:rnd % len(order)]:
                    progress(f"round {rnd + 1}/{args.rounds}: {probe_name} workloads, {condition}")
                    if condition == NONE:
                        watch.look()
                    elif condition.kind == "floor":
                        floor.attach_path(floor_attachments(probe_name, condition.path))
                    else:
                        probe = make_probe(probe_name, condition.path, condition.splice)
                        probe.start()
                    try:
                        for w in workloads:
                            measure(w, condition)
                    finally:
                        floor.detach()
                        if probe is not None:
                            probe.unload()
                            probe = None

        # Pass 2, statistics on: each program's own time per run, on the agent's path (a
        # tracepoint's: the programs of the other paths are not one per tracepoint).
        set_stats(1)
        for probe_name, (workloads, pairs) in PROBES.items() if args.paths == "agent" else ():
            tps = [tp for tp, _ in pairs]
            for condition in ("floor", "drums"):
                progress(f"bpf_stats: {probe_name} workloads, {condition}")
                if condition == "floor":
                    floor.attach(tps)
                    ids = floor.prog_ids(tps)
                else:
                    probe = make_probe(probe_name, paths[probe_name][0])
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

    kernel = f"Linux {os.uname().release}"
    if self_ns:
        rows = []
        for probe_name, (_, pairs) in PROBES.items():
            for tp, fn in pairs:
                f, d = self_ns.get((tp, "floor"), float("nan")), self_ns.get((tp, "drums"), float("nan"))
                program = fn if found_by_name.get(fn) != "not attached" else "no program on this path"
                rows.append([f"{tp} ({probe_name}: {program})", paths[probe_name][0], fmt(f, 1), fmt(d, 1),
                             ratio(d, f)])
        print_table(f"Per-event cost: the program's own run time (kernel bpf_stats), {kernel}",
                    ["event (probe: program)", "path", "empty program ns/run", "Drums ns/run", "Drums / empty"],
                    rows,
                    ["run_time_ns / run_cnt over the workloads below; the statistics themselves add a clock "
                     "read per run to both columns.",
                     "Drums programs found by name with `bpftool prog show -j`: "
                     + ", ".join(f"{fn} {found}" for fn, found in found_by_name.items())])

    rows = []
    for probe_name, (workloads, pairs) in PROBES.items():
        for w in workloads:
            none = median(added[w, NONE])
            events = sum(median(events_per_op.get((w, tp), [0])) for tp, _ in pairs)
            for condition in (c for c in orders[probe_name] if c.kind == "drums"):
                # Paired by round: a slow drift of the host (another session's programs coming and
                # going, a busy neighbour) cancels out within a round.
                fl = median(f - n for f, n in zip(added[w, Condition("floor", condition.path)], added[w, NONE]))
                dr = median(d - n for d, n in zip(added[w, condition], added[w, NONE]))
                per_event = (f"{fmt(fl / events, 1)} / {fmt(dr / events, 1)}" if events else "n/a")
                also = f", {SPLICE_TRACEPOINTS}" if condition.splice else ""
                rows.append([f"{WORKLOAD_LABEL[w]} ({probe_name}{also})", condition.path,
                             fmt(none, 0), fmt(fl, 1), fmt(dr, 1), ratio(dr, fl), fmt(events, 2), per_event])
    notes = watch.notes() + [
        f"ns per operation: the fastest of {args.batches} batches of a run (other work on the host only "
        f"ever adds time); added ns: median over {args.rounds} rounds of the difference to the same round's "
        "run without programs; "
        f"{args.ops:,} socket operations or {args.pingpongs:,} round trips per run, on CPU {args.cpu}; "
        "added = with programs attached minus with none; the empty programs attach where Drums's do on "
        "that path (kprobes: on entry and return of each family's sendmsg and recvmsg; fentry: fexit on "
        "them). Goal: Drums at most 1.3x the floor.",
        "spread of the added ns/op over the rounds (25th to 75th percentile): " + "; ".join(
            f"{w} {c} {_spread(added[w, c], added[w, NONE])}"
            for w in WORKLOAD_LABEL for c in sorted({c for ww, c in added if ww == w} - {NONE})),
    ] + ([f"this kernel has no kprobes: {SPLICE_UNCOUNTED_WHY} (the --splice-tracepoints rows: two per "
          "socket operation, each taking the kernel's syscall tracing path)"] if splice_differs else [])
    print_table(f"Per-event cost: time added to a workload, {kernel}",
                ["workload (probe)", "path", "no program ns/op", "empty added ns/op", "Drums added ns/op",
                 "Drums / empty", "events/op", "added ns/event empty / Drums"], rows, notes)


def in_vm(name: str, args) -> None:
    """The paths of another kernel of tests/kernels/matrix.py, measured in a VM of it, as
    `make test-kernels` boots one (under KVM where it works, else emulation: there the ns are
    emulated time, ten to fifty times this host's, and only the ratios carry over)."""
    from tests.kernels import run as kernels
    from tests.kernels.matrix import MATRIX

    k = next((k for k in MATRIX if k.name == name and not k.arch), None)
    if k is None:
        raise BenchError(f"--kernel {name}: no such kernel of this machine's architecture in tests/kernels/matrix.py")
    try:
        vmlinuz, headers = kernels.unpack(k)
        kvm, why = kernels.kvm_works(vmlinuz)
    except (RuntimeError, OSError, subprocess.CalledProcessError) as e:
        raise BenchError(f"--kernel {name}: {e}") from None
    mode = "KVM" if kvm else "software emulation"
    sizes = ["--rounds", str(max(1, args.rounds // 3)), "--ops", str(args.ops), "--pingpongs", str(args.pingpongs),
             "--batches", str(args.batches), "--cpu", str(args.cpu)]
    progress(f"Linux {k.release}: booting under {mode}{'' if kvm else f' ({why})'}; every path, {sizes[1]} rounds")
    with tempfile.TemporaryDirectory(prefix="drums-bench-") as out:
        command = (f"{kernels.VENV_BIN}/python -m tests.kernels.guest bench {out} {headers} "
                   f"bench/event_cost.py --paths all {' '.join(sizes)} >{out}/log 2>&1")
        status, console = kernels.vng(vmlinuz, bool(kvm), command, out, VM_TIMEOUT)
        try:
            with open(os.path.join(out, "tables.jsonl")) as f:
                tables = [json.loads(line) for line in f]
        except OSError:
            tables = []
        if not tables:  # (virtme-ng's own exit status says nothing of the guest's)
            log = kernels.tail(os.path.join(out, "log")) or console
            raise BenchError(f"--kernel {name}: " + (f"the VM did not finish in {VM_TIMEOUT // 60} min" if status is None
                                                     else f"no tables (exit status {status}): {log[-400:]!r}"))
    for t in tables:
        print_table(f"{t['title']} ({k.robots.split(';')[0]}, in a VM under {mode})", t["headers"], t["rows"],
                    t["notes"] + ([] if kvm else ["under emulation the ns are emulated time; compare the ratios"]))


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
    parser.add_argument("--kernel", metavar="NAME", default="",
                        help="then every path of this kernel of tests/kernels/matrix.py (6.1: fentry and kprobes), "
                             "in a VM of it, a third of the rounds (make bench: 6.1)")
    parser.add_argument("--paths", choices=("agent", "all"), default="agent",
                        help="each probe on the path the agent takes (default), or on every path this kernel "
                             "offers, each beside empty programs on that path (no per-program statistics)")
    args = parser.parse_args()
    def both() -> None:
        run(args)
        if args.kernel:
            in_vm(args.kernel, args)
    main_wrapper(both)


if __name__ == "__main__":
    main()
