"""Empty BPF programs where the probes attach theirs: the floor that any program there pays (the
kernel's dispatch to it), with nothing of its own. bench/event_cost.py sets each probe's programs
beside them, path by path; bench/workload_overhead.py runs a workload with them alone.
"""
from __future__ import annotations

import os

from common import BenchError

from drums.kernel import tracing  # after common, which puts the project on sys.path

FLOOR_SOURCE = """
int floor_tp(struct bpf_raw_tracepoint_args *ctx) { return 0; }
int floor_regs(struct pt_regs *ctx) { return 0; }
"""


class Floor:
    """The empty programs, compiled once with bcc and attached only while measured. `fexit`: the
    kernel functions a trampoline path attaches to (compiled only where the kernel takes them)."""

    def __init__(self, headers: str | None, fexit: tuple[str, ...] = ()):
        if headers:
            os.environ["BCC_KERNEL_SOURCE"] = headers
        try:
            from bcc import BPF
        except ImportError:
            raise BenchError("bcc is not installed (apt-get install python3-bpfcc)") from None
        self.bpf = BPF(text=FLOOR_SOURCE + "".join(f"KRETFUNC_PROBE({fn}) {{ return 0; }}\n" for fn in fexit))
        self.fexit = list(self.bpf.kfunc_exit_fds)  # bcc attached them as it loaded them
        for name in self.fexit:
            self.bpf.detach_kretfunc(name)
        self.attached: dict[str, tuple[int, int]] = {}  # tp_btf tracepoint -> (program fd, link fd)
        self.undo: list = []  # how to detach the others

    def attach(self, tracepoints) -> None:
        """On tracepoints as the probes attach theirs where the kernel offers it: as tp_btf programs."""
        self.attach_path([("tp_btf", tp, "") for tp in tracepoints])

    def attach_path(self, attachments) -> None:
        """Where a probe's path attaches (BpfProbe.attachments): the same kinds at the same places."""
        b = self.bpf
        for kind, target, _ in attachments:
            if kind == "tp_btf":
                self.attached[target] = tracing.attach(b.module, "floor_tp", target)
            elif kind == "raw_tracepoint":
                b.attach_raw_tracepoint(tp=target, fn_name="floor_tp")
                self.undo.append(lambda t=target: b.detach_raw_tracepoint(tp=t))
            elif kind in ("kprobe", "kprobe_link"):
                b.attach_kprobe(event=target, fn_name="floor_regs")
                self.undo.append(lambda t=target: b.detach_kprobe(event=t, fn_name="floor_regs"))
            elif kind in ("kretprobe", "kretprobe_link"):
                b.attach_kretprobe(event=target, fn_name="floor_regs")
                self.undo.append(lambda t=target: b.detach_kretprobe(event=t, fn_name="floor_regs"))
            elif kind == "fentry":
                for name in self.fexit:
                    b.attach_kretfunc(name)
                    self.undo.append(lambda n=name: b.detach_kretfunc(n))
            elif kind != "run":  # "run": a program the agent runs itself, never the kernel
                raise BenchError(f"no empty program for a {kind} attachment")

    def detach(self) -> None:
        for prog, link in self.attached.values():
            os.close(link)
            os.close(prog)
        self.attached = {}
        while self.undo:
            self.undo.pop()()

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
