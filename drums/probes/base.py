"""What every probe is: a named source of metric series with a visible attach status."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from drums.metrics import Metric, Snapshot


@dataclass
class ProbeStatus:
    attached: bool = False
    attach_type: str = "none"  # raw_tracepoint, kprobe, fentry, psutil, proc, sock_diag, none
    reason: str = ""  # why it is not attached, or what a fallback lacks
    map_fill: dict[str, float] = field(default_factory=dict)  # map name -> used fraction
    dropped: int = 0  # events lost because a map was full
    missed: int | None = None  # runs of its programs the kernel skipped (one already running on that CPU), if counted
    map_memory: int = 0  # bytes of kernel memory its BPF maps hold


class Probe:
    """Subclasses set `name` and `metrics`, and implement start/collect/stop."""

    name = ""
    metrics: tuple[Metric, ...] = ()
    fallback: Callable[[], "Probe"] | None = None  # what to run instead when start() fails
    paths: tuple = ()  # the attach paths a BPF probe may take, best first (drums.probes.bpf.AttachPath)

    def __init__(self):
        self.status = ProbeStatus()

    def start(self) -> None:
        raise NotImplementedError

    def collect(self, snap: Snapshot) -> None:
        raise NotImplementedError

    def read_map_memory(self) -> None:
        """Bring status.map_memory up to date (a probe without BPF maps has none)."""

    def stop(self) -> None:
        pass

    def unload(self) -> None:
        """Stop and leave nothing loaded in the kernel (a BPF probe removes its pins)."""
        self.stop()

    # What the agent tells a probe, or asks of it, at each collect; a probe that has no use for it
    # keeps these.

    def set_pids(self, pids) -> None:
        """The processes of the chosen ones that the probe reads (those it reads one by one)."""

    def want_rtt(self, connections: set[tuple[str, str]]) -> None:
        """The (local, remote) connections whose round-trip time is wanted."""

    def want_deadlines(self, deadlines: dict[str, int]) -> None:
        """The Deadline QoS, ns, of the graph's endpoints by GID."""

    def renamed(self) -> set[int] | None:
        """The processes that came or may have been renamed since the last collect; None where the
        probe cannot tell."""
        return None

    def ended(self) -> dict[int, str]:
        """The processes that ended since the last collect, with their names, where the probe's
        kernel maps keep them until then; read before any probe collects."""
        return {}

    def transitions(self) -> int | None:
        """The host's TCP state changes so far; None where the probe does not count them."""
        return None
