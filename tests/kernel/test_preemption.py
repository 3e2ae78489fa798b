"""Why every read-modify-write in Drums' programs is atomic, even of per-CPU data: on a PREEMPT_RT
kernel a BPF trampoline (fentry) runs its program with migration, not preemption, disabled, so the
program of one task can be preempted between its load and its store by the same program run for
another task on that CPU. (Tracepoint and kprobe programs run with preemption disabled there too.)
Here a per-CPU counter is added to on a syscall, plainly and atomically, while processes on one CPU
make the call and a SCHED_FIFO process preempts them: the atomic add loses nothing anywhere, and the
plain one loses updates on an RT kernel's fentry path."""
import ctypes
import os
import subprocess
import sys
import time

import pytest

from tests.conftest import TIME_SCALE

# A plain add whose load and store are held apart by a loop (about a microsecond here), so that a
# preemption has somewhere to land; and an atomic add beside it.
PROGRAM = r"""
BPF_HASH(callers, u32, u8, 8);
BPF_PERCPU_ARRAY(plain, u64, 1);
BPF_PERCPU_ARRAY(atomic, u64, 1);

static __always_inline void count(void)
{
    u32 tgid = bpf_get_current_pid_tgid() >> 32;
    if (!callers.lookup(&tgid))
        return;
    int zero = 0;
    u64 *p = plain.lookup(&zero), *a = atomic.lookup(&zero);
    if (!p || !a)
        return;
    u64 seen = *p;
    for (int i = 0; i < 64; i++)
        bpf_get_prandom_u32();
    *p = seen + 1;
    __sync_fetch_and_add(a, 1);
}
#ifdef FENTRY
// What getppid(2) calls to name the parent (task_tgid_vnr inlines to it): a function in every
// kernel's BTF, where the syscall's own wrapper need not be (Debian's 6.1 has no __x64_sys_getppid).
KFUNC_PROBE(__task_pid_nr_ns) { count(); return 0; }
#else
TRACEPOINT_PROBE(syscalls, sys_enter_getppid) { count(); return 0; }
#endif
"""

# Pinned to CPU 1, it calls getppid until told to stop (argv[1] "fifo": as a SCHED_FIFO process
# that sleeps half a millisecond between calls), then says how many calls it made.
CALLER = r"""
import os, select, sys, time
os.sched_setaffinity(0, {1})
fifo = sys.argv[1] == "fifo"
if fifo:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
print(flush=True)
sys.stdin.readline()
n = 0
while not select.select([sys.stdin], [], [], 0)[0]:
    for _ in range(1 if fifo else 1000):
        os.getppid()
        n += 1
    if fifo:
        time.sleep(0.0005)
print(n, flush=True)
"""


@pytest.mark.kernel
@pytest.mark.skipif(1 not in os.sched_getaffinity(0), reason="needs CPU 1")
def test_a_plain_add_loses_updates_where_programs_are_preempted_and_an_atomic_one_none(features):
    os.environ["BCC_KERNEL_SOURCE"] = features.kernel_headers
    from bcc import BPF

    callers = [subprocess.Popen([sys.executable, "-c", CALLER, kind], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True) for kind in ("plain",) * 4 + ("fifo",)]
    cflags = ["-DFENTRY"] if features.fentry else []
    b = BPF(text=PROGRAM.encode(), cflags=cflags)
    try:
        for c in callers:
            b[b"callers"][ctypes.c_uint32(c.pid)] = ctypes.c_uint8(1)
            c.stdout.readline()
        for c in callers:
            c.stdin.write("go\n")
            c.stdin.flush()
        time.sleep(TIME_SCALE)
        for c in callers:
            c.stdin.write("stop\n")
            c.stdin.flush()
        calls = sum(int(c.stdout.readline()) for c in callers)
        plain, atomic = sum(b[b"plain"][0]), sum(b[b"atomic"][0])
    finally:
        for c in callers:
            c.kill()
            c.wait()
        b.cleanup()
    # Every call ran the program; on fentry so may a rare other use of the function by these
    # processes (seen: 1 in 967,442 calls on 5.10). Both adds saw the same runs.
    assert calls <= atomic <= calls + 8 if features.fentry else atomic == calls, (atomic, calls)
    if features.fentry and features.preempt_rt:
        assert plain < atomic, (plain, atomic)  # seen: ...
    else:  # no preemption amid a program: a tracepoint's, or anything on a kernel that is not fully preemptible
        assert plain == atomic, (plain, atomic)
