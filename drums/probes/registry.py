"""Every probe by name, in the order the agent starts them."""
from __future__ import annotations

from drums.errors import UsageError
from drums.kernel.features import Features
from drums.probes.base import Probe
from drums.proctable import MappedLibraries, ProcessTable

# In the order they collect: sched before process, to which it tells the processes that ran.
PROBES = ("sockets", "sched", "tcp", "host", "process", "rtps", "rcl", "loads", "latency")
# Run by default only with the ros2 graph: they count per DDS writer and topic (loads tells them
# at once when a process loads ROS 2 or DDS).
ROS2_PROBES = ("rtps", "rcl", "loads")


def build(features: Features, proctable: ProcessTable, names=PROBES, pin_root: str = "",
          ros_timing: bool = True, attach: dict[str, str] | None = None,
          splice_tracepoints: bool = False) -> list[Probe]:
    """The probes called `names`; BPF probes pin under `pin_root` (default /sys/fs/bpf/drums);
    `ros_timing`: rcl times messages as well as counting them; `attach`: probe -> the one attach
    path it may take, or "fallback" for its fallback alone; `splice_tracepoints`: see
    drums.probes.sockets.splice_reads."""
    from drums.probes.host import HostProbe
    from drums.probes.latency import LatencyProbe
    from drums.probes.loads import LINKERS, LoadsProbe
    from drums.probes.process import ProcessProbe
    from drums.probes.procsched import ProcSchedProbe
    from drums.probes.rcl import RclProbe
    from drums.probes.rtps import DDS_LIBRARIES, RtpsProbe
    from drums.probes.sched import SchedProbe
    from drums.probes.sockdiag_sockets import SockDiagSocketsProbe
    from drums.probes.sockets import SocketsProbe
    from drums.probes.tcp import SockDiagTcpProbe, TcpProbe

    from drums.kernel.bpffs import PIN_ROOT

    pin_root = pin_root or PIN_ROOT
    dds = MappedLibraries(proctable, DDS_LIBRARIES + LINKERS)  # each process's map read once for all three
    makers = {
        "sockets": lambda: SocketsProbe(features, proctable, pin_root=pin_root, splice_tracepoints=splice_tracepoints),
        "sched": lambda: SchedProbe(features, proctable, pin_root=pin_root),
        "tcp": lambda: TcpProbe(features, pin_root=pin_root),
        "host": HostProbe,
        "process": lambda: ProcessProbe(proctable),
        "rtps": lambda: RtpsProbe(features, proctable, dds, pin_root=pin_root),
        "rcl": lambda: RclProbe(features, proctable, dds, timing=ros_timing, pin_root=pin_root),
        "loads": lambda: LoadsProbe(features, dds, pin_root=pin_root),
        "latency": LatencyProbe,  # probes only the targets of latency jobs
    }
    # What runs where eBPF cannot (not root, no bcc, old kernel): the kernel's own counters.
    fallbacks = {
        "sockets": lambda: SockDiagSocketsProbe(proctable),
        "sched": lambda: ProcSchedProbe(proctable),
        "tcp": SockDiagTcpProbe,
    }
    attach = attach or {}
    unknown = sorted(set(attach) - set(names))
    if unknown:
        raise UsageError(f"--attach {unknown[0]}=...: no such probe runs (probes: {', '.join(names)})")
    probes = []
    for name in PROBES:
        if name in names:
            probe = makers[name]()
            probe.fallback = fallbacks.get(name)
            if name in attach:
                probe = held_to(probe, attach[name])
            probes.append(probe)
    return probes


def held_to(probe: Probe, path: str) -> Probe:
    """The probe with only the attach path `path` left to it (its fallback itself for "fallback")."""
    paths = [p.name for p in probe.paths]
    if path == "fallback" and probe.fallback is not None:
        return probe.fallback()
    if path not in paths:
        offered = paths + (["fallback"] if probe.fallback is not None else [])
        raise UsageError(f"--attach {probe.name}={path}: probe {probe.name} has no such path "
                         f"({', '.join(offered) if offered else 'it has no attach paths'})")
    probe.paths = tuple(p for p in probe.paths if p.name == path)
    return probe
