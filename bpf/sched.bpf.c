// On-CPU time, run-queue latency and context switches of every thread, from the scheduler's own
// tracepoints. On-CPU time is the kernel's own account (se.sum_exec_runtime, what /proc and top
// show), which leaves out time a hypervisor stole: a clock read at each switch would count it too
// (seen: 30% more than /proc on a busy VM). A thread's time is its runtime at its last switch-out
// less its runtime when its entry was made, so no switch is needed to pair with another. One hash
// entry per thread holds its counts, with no atomics: a thread's counters are only written by the
// CPU that switches it in or out (the waker's CPU writes enqueued_at alone). A context switch looks
// up one entry (the thread switched out) where the programs see typed tasks (tp_btf), two on raw
// tracepoints.
//
// Task offsets (TASK_*_OFF) come from BTF.
#include "drums.h"

// Run-queue latency histogram: slot i counts waits of [2^i, 2^(i+1)) microseconds (slot 0 also
// takes waits under 1 us); the last slot takes everything longer.
#define RUNQ_SLOTS 24
#define TASK_DEAD 0x80  // include/linux/sched.h, unchanged since 4.14

#define DROP_THREAD 0
#define DROP_PROCESS 1
#define DROP_RENAMED 2

struct sched_t {
    u64 oncpu_ns;
    u64 runq_ns;
    u64 runq_waits;
    u64 voluntary;
    u64 involuntary;
    u32 runq_hist[RUNQ_SLOTS];
};

struct thread_sched_t {
    u32 tgid;
    u32 pad;
    u64 enqueued_at;  // raw tracepoints: when the thread became runnable; 0 while running or sleeping
    u64 process_start;
    u64 runtime_base;  // the thread's runtime when this entry was made: s.oncpu_ns counts from it
    char comm[16];
    struct sched_t s;
};

// Exited threads of one process. The PID of a process that was just reaped can go to a new process
// before sched_process_free frees this entry: process_start tells the two apart.
struct exited_sched_t {
    u64 process_start;
    struct sched_t s;
};

// pid_max is 32768 on small systems and 4M on large ones; 65536 live threads covers a robot.
BPF_HASH(thread_sched, u32, struct thread_sched_t, 65536);
// Threads that exited, folded per process until the process is reaped.
BPF_HASH(exited_sched, u32, struct exited_sched_t, 16384);
// The current task of each CPU and its runtime when it was switched in: the agent reads the runtime
// of a thread that keeps its CPU (it may not switch out for seconds) from /proc, and a thread's last
// slice after it exited is charged to its process from this.
struct oncpu_t {
    u64 runtime;
    u32 tid;
    u32 pad;
    u64 waited;  // tp_btf: how long that task waited to be switched in here; counted at its switch-out
};
BPF_PERCPU_ARRAY(oncpu, struct oncpu_t, 1);

// Processes that were forked, or whose leader was renamed, exec'd or exited, since the agent last
// looked, each with when that last happened: the agent reads their names and command lines again
// (and a PID that came back is a new process), instead of every process's on every scrape; and
// while none came or went, it does not list /proc at all.
BPF_HASH(renamed, u32, u64, 16384);

// Events lost to a full map, by reason; exported per probe. (bcc rewrites map calls only in the
// main file, so each program declares this map and its helper itself.)
BPF_ARRAY(dropped, u64, 3);

static __always_inline void count_drop(int which)
{
    u64 *d = dropped.lookup(&which);
    if (d)
        __sync_fetch_and_add(d, 1);
}

static __always_inline void mark_renamed(u32 tgid)
{
    u64 now = bpf_ktime_get_ns();
    if (renamed.update(&tgid, &now) != 0)
        count_drop(DROP_RENAMED);  // the agent then reads every name again
}

// `runtime_base`: the thread's runtime when it started to be counted.
static __always_inline struct thread_sched_t *thread_entry(u32 tid, u64 task, u64 runtime_base)
{
    struct thread_sched_t *t = thread_sched.lookup(&tid);
    if (t)
        return t;
    struct thread_sched_t fresh = {};
    KREAD(fresh.tgid, task + TASK_TGID_OFF);
    bpf_probe_read_kernel(fresh.comm, sizeof(fresh.comm), (void *)(task + TASK_COMM_OFF));
    fresh.process_start = process_start(task);
    fresh.runtime_base = runtime_base;
    if (thread_sched.insert(&tid, &fresh) != 0) {
        count_drop(DROP_THREAD);
        return 0;
    }
    return thread_sched.lookup(&tid);
}

// Atomic: threads of one process can exit on several CPUs at once (a slow path: once per thread).
static __always_inline void fold(struct sched_t *into, struct sched_t *from)
{
    __sync_fetch_and_add(&into->oncpu_ns, from->oncpu_ns);
    __sync_fetch_and_add(&into->runq_ns, from->runq_ns);
    __sync_fetch_and_add(&into->runq_waits, from->runq_waits);
    __sync_fetch_and_add(&into->voluntary, from->voluntary);
    __sync_fetch_and_add(&into->involuntary, from->involuntary);
#pragma unroll
    for (int i = 0; i < RUNQ_SLOTS; i++)
        __sync_fetch_and_add(&into->runq_hist[i], from->runq_hist[i]);
}

// Fold a thread that is gone into its process and free its entry. `create` is false after the
// thread has left its thread group: its process may have been reaped already, and an entry made
// then would never be freed.
static __always_inline void thread_died(u32 tid, struct thread_sched_t *t, bool create)
{
    u32 tgid = t->tgid;
    struct exited_sched_t *p = exited_sched.lookup(&tgid);
    if (p && p->process_start != t->process_start) {
        exited_sched.delete(&tgid);  // left by the process that had this PID before
        p = 0;
    }
    if (!p && create) {
        struct exited_sched_t fresh = {.process_start = t->process_start};
        exited_sched.insert(&tgid, &fresh);
        p = exited_sched.lookup(&tgid);
        if (!p)
            count_drop(DROP_PROCESS);
    }
    if (p)
        fold(&p->s, &t->s);
    thread_sched.delete(&tid);
}

static __always_inline void count_wait(struct thread_sched_t *t, u64 waited)
{
    t->s.runq_ns += waited;
    t->s.runq_waits++;
    u32 slot = bpf_log2l(waited / 1000) - 1;  // [2^slot, 2^(slot+1)) us; slot 0 is [0, 2)
    if (slot >= RUNQ_SLOTS)
        slot = RUNQ_SLOTS - 1;
    t->s.runq_hist[slot]++;
}

#if DRUMS_ATTACH == ATTACH_TP_BTF
// Where programs see typed tasks, when a thread became runnable is kept in the task itself
// (task-local storage: a few loads, against a hash lookup that costs as much as the rest of the
// program), so that wakeup and switch-in never look up the thread's entry. The wait ends at
// switch-in, is held by the CPU (oncpu.waited) and added to the entry at the thread's switch-out
// (or exit), when the entry is looked up anyway: a thread's waits show once it has left the CPU,
// as its CPU time does.
struct waiting_t {
    u64 enqueued_at;  // 0 while running or sleeping
};
BPF_TASK_STORAGE(waiting, struct waiting_t);

// The wait of the task this CPU switched in, if that is the thread `tid`, into its entry.
static __always_inline void take_wait(struct oncpu_t *current, u32 tid, struct thread_sched_t *t)
{
    if (current->tid == tid && current->waited) {
        count_wait(t, current->waited);
        current->waited = 0;
    }
}
#endif

static __always_inline void enqueued(u32 tid, u64 task, u64 now)
{
#if DRUMS_ATTACH == ATTACH_TP_BTF
    struct waiting_t *w = waiting.task_storage_get((void *)task, 0, BPF_LOCAL_STORAGE_GET_F_CREATE);
    if (w)
        w->enqueued_at = now;
#else
    u64 runtime = 0;  // a thread that waits does not run: this is its runtime until it does
    KREAD(runtime, task + TASK_RUNTIME_OFF);
    struct thread_sched_t *t = thread_entry(tid, task, runtime);
    if (t)
        t->enqueued_at = now;
#endif
}

// sched:sched_switch (preempt, prev, next[, prev_state])
int on_switch(struct bpf_raw_tracepoint_args *ctx)
{
    u64 now = bpf_ktime_get_ns();
    int zero = 0;
    struct oncpu_t *current = oncpu.lookup(&zero);
    if (!current)
        return 0;
    u64 prev = ctx->args[1], next = ctx->args[2];
    u32 prev_tid = 0, next_tid = 0;
    KREAD(prev_tid, prev + TASK_PID_OFF);
    KREAD(next_tid, next + TASK_PID_OFF);
    // The kernel has charged prev's slice to its runtime before this tracepoint (update_curr, as it
    // was dequeued or put back).
    u64 prev_runtime = 0, next_runtime = 0;
    KREAD(prev_runtime, prev + TASK_RUNTIME_OFF);
    KREAD(next_runtime, next + TASK_RUNTIME_OFF);
#ifdef SWITCH_HAS_PREV_STATE
    unsigned int state = (unsigned int)ctx->args[3];  // kernel >= 5.18
#else
    unsigned int state = 0;
    KREAD(state, prev + TASK_STATE_OFF);
#endif
    bool preempt = ctx->args[0] & 1;
    // Prev's runtime when it was switched in here, if this CPU saw that (the probe may have been
    // loaded since).
    u64 prev_runtime_in = current->tid == prev_tid ? current->runtime : prev_runtime;

    if (prev_tid) {  // tid 0 is the idle task
        // A dead thread's last switch: its entry is only looked up, never made (see thread_died).
        struct thread_sched_t *t = (state & TASK_DEAD) ? thread_sched.lookup(&prev_tid)
                                                       : thread_entry(prev_tid, prev, prev_runtime_in);
#if DRUMS_ATTACH == ATTACH_TP_BTF
        if (t)
            take_wait(current, prev_tid, t);
        if (state == 0) {  // still runnable: it waits on the run queue from now
            struct waiting_t *w = waiting.task_storage_get((void *)prev, 0, BPF_LOCAL_STORAGE_GET_F_CREATE);
            if (w)
                w->enqueued_at = now;
        }
#endif
        if (t) {
            if (prev_runtime > t->runtime_base)
                t->s.oncpu_ns = prev_runtime - t->runtime_base;
            // The kernel's own rule for nvcsw/nivcsw (kernel/sched/core.c, __schedule).
            if (!preempt && state)
                t->s.voluntary++;
            else
                t->s.involuntary++;
#if DRUMS_ATTACH != ATTACH_TP_BTF
            if (state == 0)
                t->enqueued_at = now;  // still runnable: it waits on the run queue from now
#endif
            if (state & TASK_DEAD)
                thread_died(prev_tid, t, false);
        } else if (state & TASK_DEAD) {
            // Folded at exit: the slice it ran since then joins its process's totals.
            u32 tgid = 0;
            KREAD(tgid, prev + TASK_TGID_OFF);
            struct exited_sched_t *p = exited_sched.lookup(&tgid);
            if (p) {
                if (prev_runtime > prev_runtime_in)
                    __sync_fetch_and_add(&p->s.oncpu_ns, prev_runtime - prev_runtime_in);
                __sync_fetch_and_add(preempt ? &p->s.involuntary : &p->s.voluntary, 1);
            }
        }
    }
    if (next_tid) {
#if DRUMS_ATTACH == ATTACH_TP_BTF
        struct waiting_t *w = waiting.task_storage_get((void *)next, 0, 0);
        current->waited = w && w->enqueued_at ? now - w->enqueued_at : 0;
        if (w)
            w->enqueued_at = 0;
#else
        struct thread_sched_t *t = thread_sched.lookup(&next_tid);
        if (t && t->enqueued_at) {
            count_wait(t, now - t->enqueued_at);
            t->enqueued_at = 0;
        }
#endif
    }
    current->runtime = next_runtime;
    current->tid = next_tid;
    return 0;
}

// sched:sched_wakeup and sched:sched_wakeup_new (task): the task is now on a run queue.
int on_wakeup(struct bpf_raw_tracepoint_args *ctx)
{
    u64 task = ctx->args[0];
    u32 tid = 0;
    KREAD(tid, task + TASK_PID_OFF);
    if (tid)
        enqueued(tid, task, bpf_ktime_get_ns());
    return 0;
}

// sched:sched_process_exit (task, group_dead) runs in the exiting thread while it still belongs to
// its process: fold it now. What it does until its last switch-out joins the fold while the
// process entry lasts.
int on_exit(struct bpf_raw_tracepoint_args *ctx)
{
    u64 id = bpf_get_current_pid_tgid();
    u32 tid = (u32)id;
    if (tid == (u32)(id >> 32))
        mark_renamed(tid);  // its PID may come back as another process
    struct thread_sched_t *t = thread_sched.lookup(&tid);
    if (!t)
        return 0;
#if DRUMS_ATTACH == ATTACH_TP_BTF
    int zero = 0;
    struct oncpu_t *current = oncpu.lookup(&zero);
    if (current)
        take_wait(current, tid, t);
#endif
    thread_died(tid, t, true);
    return 0;
}

// sched:sched_process_exec (task, old_pid, bprm): a thread other than the leader that calls exec
// takes over the leader's PID, so its old thread ID is gone without a final switch-out.
int on_exec(struct bpf_raw_tracepoint_args *ctx)
{
    u32 old_tid = (u32)ctx->args[1];
    u32 tid = (u32)bpf_get_current_pid_tgid();
    mark_renamed(tid);  // a new command line, whether or not its name changed
    if (old_tid == tid)
        return 0;
    struct thread_sched_t *t = thread_sched.lookup(&old_tid);
    if (t)
        thread_died(old_tid, t, true);
    return 0;
}

// task:task_rename (task, comm): exec and prctl(PR_SET_NAME) rename threads after they started.
int on_rename(struct bpf_raw_tracepoint_args *ctx)
{
    u64 task = ctx->args[0];
    u32 tid = 0, tgid = 0;
    KREAD(tid, task + TASK_PID_OFF);
    KREAD(tgid, task + TASK_TGID_OFF);
    if (tid == tgid)
        mark_renamed(tgid);  // the process's name is its leader's
    struct thread_sched_t *t = thread_sched.lookup(&tid);
    if (t)
        bpf_probe_read_kernel_str(t->comm, sizeof(t->comm), (void *)ctx->args[1]);
    return 0;
}

// sched:sched_process_fork (parent, child): a new process (not a new thread) is marked.
int on_fork(struct bpf_raw_tracepoint_args *ctx)
{
    u32 tgid = leader_tgid(ctx->args[1]);
    if (tgid)
        mark_renamed(tgid);
    return 0;
}

// sched:sched_process_free (task): a reaped process leader takes its folded totals with it.
int on_task_free(struct bpf_raw_tracepoint_args *ctx)
{
    u32 tgid = leader_tgid(ctx->args[0]);
    if (tgid)
        exited_sched.delete(&tgid);
    return 0;
}
