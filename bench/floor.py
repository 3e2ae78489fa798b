"""Empty BPF programs on the tracepoints the probes use: the floor that any program there pays
(the kernel's dispatch to it), with nothing of its own. bench/event_cost.py sets each probe's
programs beside them; bench/workload_overhead.py runs a workload with them alone.
"""
from __future__ import annotations

import os

from common import BenchError

from drums.kernel import tracing  # after common, which puts the project on sys.path

FLOOR_SOURCE = b"""
int floor_send(struct bpf_raw_tracepoint_args *ctx) { return 0; }
int floor_recv(struct bpf_raw_tracepoint_args *ctx) { return 0; }
int floor_switch(struct bpf_raw_tracepoint_args *ctx) { return 0; }
int floor_wakeup(struct bpf_raw_tracepoint_args *ctx) { return 0; }
"""
FLOOR_FN = {"sock_send_length": b"floor_send", "sock_recv_length": b"floor_recv",
            "sched_switch": b"floor_switch", "sched_wakeup": b"floor_wakeup"}


class Floor:
    """The empty programs, compiled once with bcc and attached only while measured."""

    def __init__(self, headers: str | None):
        if headers:
            os.environ["BCC_KERNEL_SOURCE"] = headers
        try:
            from bcc import BPF
        except ImportError:
            raise BenchError("bcc is not installed (apt-get install python3-bpfcc)") from None
        self.bpf = BPF(text=FLOOR_SOURCE)
        self.attached: dict[str, tuple[int, int]] = {}  # tracepoint -> (program fd, link fd)

    def attach(self, tracepoints) -> None:
        """As the probes attach theirs where the kernel offers it: as tp_btf programs (the same
        dispatch as a raw tracepoint's)."""
        for tp in tracepoints:
            self.attached[tp] = tracing.attach(self.bpf.module, FLOOR_FN[tp].decode(), tp)

    def detach(self) -> None:
        for prog, link in self.attached.values():
            os.close(link)
            os.close(prog)
        self.attached = {}

    def prog_ids(self, tracepoints) -> dict[str, int]:
        out = {}
        for tp in tracepoints:
            with open(f"/proc/self/fdinfo/{self.attached[tp][0]}") as f:
                info = dict(line.split(":", 1) for line in f if ":" in line)
            out[tp] = int(info["prog_id"])
        return out

    def close(self) -> None:
        self.detach()
        self.bpf.cleanup()

