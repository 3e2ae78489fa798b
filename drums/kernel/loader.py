"""Compiles a probe's BPF C with bcc, attaches it and pins its maps and links in bpffs.

bcc keeps LLVM in the process that compiles (about 100 MB), so the agent runs this module as a
short-lived child (`python -m drums.kernel.loader`: a JSON request on stdin; exit status 0, or 1
and one error line on stdout) and afterwards only reads the pins. Attachments that the kernel cannot pin (kprobes made
through perf events) are loaded in the agent itself instead; see drums.probes.bpf.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass

from drums.errors import DrumsError, ProbeError
from drums.kernel import bpffs

BPF_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "bpf")
PINNABLE = {"tp_btf", "raw_tracepoint", "fentry", "tracepoint", "uprobe"}
# Calls a return probe can follow at once: each thread inside a probed function (a receive that
# blocks, a send preempted) holds one, and a return past them goes uncounted. The kernel's default,
# max(10, 2 x CPUs), lost calls of seven threads sending on one socket under a SCHED_FIFO thread on
# 5.10 with two CPUs. 4096 is the kernel's most.
KRETPROBE_MAXACTIVE = 4096
# Attachment kinds that load a program for the agent, pinned as prog_<function>: to attach to
# uprobes, to run itself, or to attach to a tracepoint and hold (Linux < 5.15: drums.kernel.perflink).
PROGRAMS = {"program", "run", "held_tracepoint"}


@dataclass
class LoadRequest:
    source: str  # file name under bpf/
    cflags: list[str]
    attachments: list[tuple[str, str, str]]  # (kind, target, function)
    maps: list[str]
    pin_dir: str
    headers: str | None = None


def program_text(source: str) -> str:
    """A program's text with bpf/drums.h written in where it is included: bcc rewrites map calls
    (`dropped.lookup(...)`) only in the text it is given, and drums.h has the maps all programs share.
    #line directives keep compile errors pointing at the files' own lines."""
    def read(name: str) -> str:
        try:
            with open(os.path.join(BPF_DIR, name)) as f:
                return f.read()
        except OSError as e:
            raise ProbeError(f"BPF source {name} not found in {BPF_DIR}: {e.strerror}") from None
    lines = read(source).splitlines(keepends=True)
    for i, line in enumerate(lines):
        if line.strip() == '#include "drums.h"':
            lines[i] = f'#line 1 "drums.h"\n{read("drums.h")}#line {i + 2} "{source}"\n'
    return "".join(lines)


def _compile(req: LoadRequest):
    if req.headers:
        os.environ["BCC_KERNEL_SOURCE"] = req.headers
    try:
        from bcc import BPF
    except ImportError:
        raise ProbeError("bcc is not installed (Debian/Ubuntu: apt-get install python3-bpfcc)") from None
    try:
        return BPF(text=program_text(req.source).encode(), cflags=req.cflags + [f"-I{BPF_DIR}"])
    except Exception as e:  # bcc raises bare Exception for compile and verifier errors
        raise ProbeError(f"{req.source}: {str(e).splitlines()[0] if str(e) else 'failed to load'}") from None


def attach(req: LoadRequest):
    """Compile and attach in this process; returns the bcc object and the fds to pin by name:
    links, and programs loaded for later attachment ("program", e.g. uprobes) or for the agent to
    run ("run")."""
    from drums.kernel import perflink, tracing

    b = _compile(req)
    fds, programs = [], {}
    try:
        for kind, target, fn in req.attachments:
            if kind == "tracepoint":
                fds.append(perflink.tracepoint(b.load_func(fn.encode(), b.TRACEPOINT).fd, target))
            elif kind == "program":
                programs[f"prog_{fn}"] = b.load_func(fn.encode(), b.KPROBE).fd  # uprobes are kprobe programs
            elif kind == "held_tracepoint":
                programs[f"prog_{fn}"] = b.load_func(fn.encode(), b.TRACEPOINT).fd
            elif kind == "run":  # a raw tracepoint program the agent runs itself (bpffs.run_program)
                programs[f"prog_{fn}"] = b.load_func(fn.encode(), b.RAW_TRACEPOINT).fd
            elif kind == "tp_btf":
                fds.append(tracing.attach(b.module, fn, target)[1])
            elif kind == "raw_tracepoint":
                b.attach_raw_tracepoint(tp=target.encode(), fn_name=fn.encode())
                fds.append(b.raw_tracepoint_fds[target.encode()])
            elif kind in ("kprobe_link", "kretprobe_link"):  # pinnable, unlike bcc's kprobes (see perflink)
                fds.append(perflink.kprobe(b.load_func(fn.encode(), b.KPROBE).fd, target, kind == "kretprobe_link"))
            elif kind == "kprobe":
                b.attach_kprobe(event=target.encode(), fn_name=fn.encode())
            elif kind == "kretprobe":
                b.attach_kretprobe(event=target.encode(), fn_name=fn.encode(), maxactive=KRETPROBE_MAXACTIVE)
            elif kind == "fentry":
                pass  # bcc attached KFUNC_PROBE/KRETFUNC_PROBE functions when it loaded them
            else:
                raise ProbeError(f"unknown attach kind {kind}")
    except Exception as e:
        b.cleanup()  # detach what did attach
        if isinstance(e, ProbeError):
            raise
        raise ProbeError(f"attach {kind} {target}: {e}") from None
    if any(kind == "fentry" for kind, _, _ in req.attachments):
        fds.extend(list(b.kfunc_entry_fds.values()) + list(b.kfunc_exit_fds.values()))
    return b, {f"link{i}": fd for i, fd in enumerate(fds)} | programs


def load_and_pin(req: LoadRequest) -> None:
    """Attach, then pin every map, link and program under req.pin_dir, replacing what was there."""
    b, pins = attach(req)
    tmp = req.pin_dir + "-partial"  # bpffs refuses names with dots
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(tmp)
    for name in req.maps:
        bpffs.pin(b[name.encode()].map_fd, os.path.join(tmp, name))
    for name, fd in pins.items():
        bpffs.pin(fd, os.path.join(tmp, name))
    shutil.rmtree(req.pin_dir, ignore_errors=True)
    os.rename(tmp, req.pin_dir)


# Seconds a probe may take to compile and load before it is given up: half a second on a PC, tens
# of seconds on a small board or under emulation (the sockets probe took over 60 s there beside
# another VM).
COMPILE_TIMEOUT = 600


def load_in_child(req: LoadRequest, timeout: float = COMPILE_TIMEOUT) -> None:
    """Run load_and_pin in a child process so that LLVM never enters the agent."""
    try:
        proc = subprocess.run([sys.executable, "-m", "drums.kernel.loader"], input=json.dumps(asdict(req)),
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise ProbeError(f"{req.source}: compiling took over {timeout:.0f} s") from None
    if proc.returncode != 0:
        # The loader prints its one-line error on stdout; stderr holds bcc's verifier log.
        lines = [line for line in proc.stdout.splitlines() if line.strip()]
        errors = [line for line in proc.stderr.splitlines() if "error:" in line]
        raise ProbeError(" ".join((lines[-1:] or [f"loader exited with {proc.returncode}"]) + errors[:1]))


def can_load_fentry(headers: str | None) -> bool:
    """Whether the kernel accepts a BPF trampoline (some refuse them with EPERM)."""
    if headers:
        os.environ["BCC_KERNEL_SOURCE"] = headers
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)  # libbcc prints the kernel's refusal itself; the answer is all we need
    try:
        from bcc import BPF
        b = BPF(text=b"KFUNC_PROBE(do_nanosleep) { return 0; }")
        b.cleanup()
        return True
    except Exception:
        return False
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def main() -> int:
    try:
        data = json.load(sys.stdin)
        req = LoadRequest(**data)
        req.attachments = [tuple(a) for a in req.attachments]
        load_and_pin(req)
    except (DrumsError, OSError) as e:
        print(e)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
