// On-CPU time, run-queue latency and context switches of every thread, from the scheduler's own
// tracepoints. On-CPU time is the kernel's own account (se.sum_exec_runtime, what /proc and top
// show), which leaves out time a hypervisor stole: a clock read at each switch would count it too
// (seen: 30% more than /proc on a busy VM). A thread's time is its runtime at its last switch-out
// less its runtime when its entry was made, so no switch is needed to pair with another; where the
// programs see typed tasks (tp_btf), run-queue waits are the kernel's own account likewise (see
// count_waits). One entry per thread holds its counts, with no atomics: a thread's counters are
// only written by the CPU that switches it in or out (the waker's CPU writes enqueued_at alone).
// The entry is in the thread's slot of an array (by thread ID) when that is free, else in a hash:
// an array lookup is a few instructions, a hash lookup a function call (half the cost of a switch).
// With tp_btf a context switch looks up one entry (the thread switched out) and the generation of
// the marks (an array's: a few instructions), and reads no clock, and only new tasks' wakeups have
// a program; raw tracepoint programs time the waits themselves.
//
// Task offsets (TASK_*_OFF) come from BTF.
#define DROPS 3
#define MARKED_KEY u32
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
    u32 tid;  // with tgid, the owner of a slot (see thread_slots); 0 in a free one
    u64 enqueued_at;  // raw tracepoints: when the thread became runnable; 0 while running or sleeping
    u64 process_start;
    // The thread's runtime when this entry was made: s.oncpu_ns counts from it; with tp_btf, its
    // run-queue time and runs likewise (see count_waits).
    u64 runtime_base;
    u64 delay_base;
    u64 runs_base;
    u64 marked;  // the generation in which the entry was last marked changed (see mark_changed)
    // What a switch touches comes first (the first two cache lines, as a rule: the histogram's low
    // slots take the short waits); the name, which only the agent reads, last.
    struct sched_t s;
    char comm[16];
};

// Exited threads of one process, kept after it ended until the agent has read its final totals
// (and deleted the entry): process_start tells it from a later process that got its PID.
struct exited_sched_t {
    u64 process_start;
    struct sched_t s;
    char comm[16];  // the leader's name when it exited: the agent may never have seen the process
};

// Threads whose slot (below) another live thread holds, or all of them before Linux 5.12. 16,384
// entries here and 8,192 slots hold 24,576 live threads (pid_max is 32768 on small systems), in
// 4.5 MB of kernel memory: 65,536 entries, as there were before the slots, took 17.8 MB.
BPF_HASH(thread_sched, u32, struct thread_sched_t, 16384);
// Slot tid % THREAD_SLOTS holds the entry of the first live thread with that remainder (the others'
// are in thread_sched). Taken with a compare-and-swap of its first word (Linux >= 5.12; elsewhere
// THREAD_SLOTS is 1 and no slot is used); memory-mapped, so the agent reads it in place.
BPF_F_TABLE("array", u32, struct thread_sched_t, thread_slots, THREAD_SLOTS, BPF_F_MMAPABLE);
// Threads that exited, folded per process until the agent read the ended process's totals.
BPF_HASH(exited_sched, u32, struct exited_sched_t, 16384);
// The current task of each CPU and its runtime when it was switched in: the agent reads the runtime
// of a thread that keeps its CPU (it may not switch out for seconds) from /proc, and a thread's last
// slice after it exited is charged to its process from this. Also what a thread's entry counts
// from, if it is made at the thread's switch-out here.
struct oncpu_t {
    u64 runtime;
    u32 tid;
    u32 pad;
    u64 run_delay;  // tp_btf: the task's sched_info when it was switched in, before its wait was added
    u64 runs;
};
BPF_PERCPU_ARRAY(oncpu, struct oncpu_t, 1);

// Processes that were forked, or whose leader was renamed, exec'd or exited, since the agent last
// looked, each with when that last happened: the agent reads their names and command lines again
// (and a PID that came back is a new process), instead of every process's on every scrape; and
// while none came or went, it does not list /proc at all.
BPF_HASH(renamed, u32, u64, 16384);

static __always_inline void mark_renamed(u32 tgid)
{
    u64 now = bpf_ktime_get_ns();
    if (renamed.update(&tgid, &now) != 0)
        count_drop(DROP_RENAMED);  // the agent then reads every name again
}

#if THREAD_SLOTS > 1
// The slot a thread's entry goes in, whoever holds it.
static __always_inline struct thread_sched_t *slot_of(u32 tid)
{
    u32 slot = tid & (THREAD_SLOTS - 1);
    return thread_slots.lookup(&slot);
}
#endif

// The thread's entry, if it has one.
static __always_inline struct thread_sched_t *thread_of(u32 tid)
{
#if THREAD_SLOTS > 1
    struct thread_sched_t *t = slot_of(tid);
    if (t && t->tid == tid)
        return t;
#endif
    return thread_sched.lookup(&tid);
}

// `base`: the thread's runtime (and sched_info) when it started to be counted.
static __always_inline struct thread_sched_t *thread_entry(u32 tid, u64 task, struct oncpu_t *base)
{
    struct thread_sched_t *t = thread_of(tid);
    if (t)
        return t;
    struct thread_sched_t fresh = {.tid = tid};
    KREAD(fresh.tgid, task + TASK_TGID_OFF);
    bpf_probe_read_kernel(fresh.comm, sizeof(fresh.comm), (void *)(task + TASK_COMM_OFF));
    fresh.process_start = process_start(task);
    fresh.runtime_base = base->runtime;
    fresh.delay_base = base->run_delay;
    fresh.runs_base = base->runs;
#if THREAD_SLOTS > 1
    t = slot_of(tid);
    if (t) {
        // Of two CPUs that make entries for two threads of one free slot at once, one takes it. Of
        // two that make this thread's at once (a new task's wakeup on its parent's CPU and its
        // first switch-in on another), the second finds it taken by this very thread: a second
        // entry in thread_sched would be one that no event updates, counted beside the slot's.
        u64 was = __sync_val_compare_and_swap((u64 *)t, 0, *(u64 *)&fresh);
        if (was == 0) {
            *t = fresh;
            mark_changed(tid, &t->marked);
            return t;
        }
        if (was == *(u64 *)&fresh)
            return t;
    }
#endif
    if (thread_sched.insert(&tid, &fresh) != 0) {
        t = thread_sched.lookup(&tid);  // made by another CPU at this moment, or the map is full
        if (!t)
            count_drop(DROP_THREAD);
        return t;
    }
    t = thread_sched.lookup(&tid);
    if (t)
        mark_changed(tid, &t->marked);
    return t;
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
// thread has left its thread group: its process may have ended and been read by the agent already.
static __always_inline void thread_died(u32 tid, struct thread_sched_t *t, bool create)
{
    u32 tgid = t->tgid;
    struct exited_sched_t *p = exited_sched.lookup(&tgid);
    if (p && p->process_start != t->process_start) {
        // Left by the process that had this PID before, which ended since the agent's last read:
        // what it did then is lost.
        exited_sched.delete(&tgid);
        count_drop(DROP_PROCESS);
        p = 0;
    }
    if (!p && create) {
        struct exited_sched_t fresh = {.process_start = t->process_start};
        exited_sched.insert(&tgid, &fresh);
        p = exited_sched.lookup(&tgid);
        if (!p)
            count_drop(DROP_PROCESS);
    }
    if (p) {
        fold(&p->s, &t->s);
        if (tid == tgid)
            __builtin_memcpy(p->comm, t->comm, sizeof(p->comm));
    }
#if THREAD_SLOTS > 1
    struct thread_sched_t *own = slot_of(tid);
    if (own && own->tid == tid) {
        // Emptied, then given up (its first word last), before another thread can take it.
        u64 owner = *(u64 *)own;
        __builtin_memset((u8 *)own + 8, 0, sizeof(*own) - 8);
        __sync_val_compare_and_swap((u64 *)own, owner, 0);
        mark_changed(tid, 0);  // marked once it is gone: a look at the mark finds it gone
        return;
    }
#endif
    thread_sched.delete(&tid);
    mark_changed(tid, 0);
}

// The histogram slot of a wait: [2^slot, 2^(slot+1)) us; slot 0 is [0, 2). Microseconds without
// a division (a BPF division is the CPU's, tens of cycles, on every switch): the multiply-shift is
// at most one over below 2^33 ns (8.6 s, already the last slot's), which the check takes back.
static __always_inline u64 runq_slot(u64 ns)
{
    if (ns >= (1ULL << 33))
        return RUNQ_SLOTS - 1;
    u64 us = ns * 1099511628ULL >> 40;  // 2^40 / 1000, rounded up
    if (us * 1000 > ns)
        us--;
    u64 slot = bpf_log2l(us) - 1;
    return slot >= RUNQ_SLOTS ? RUNQ_SLOTS - 1 : slot;
}

// n waits into the histogram slot of a wait of `ns`.
static __always_inline void add_waits(u32 *hist, u64 ns, u32 n)
{
    u64 slot = runq_slot(ns);
    OPAQUE(slot);
    if (slot < RUNQ_SLOTS)
        hist[slot] += n;
}

#if DRUMS_ATTACH == ATTACH_TP_BTF
// Where programs see typed tasks, run-queue waits are the kernel's own account of them (the task's
// sched_info, which /proc/<pid>/schedstat shows): its total wait and its runs, each run after a
// wait. A thread's totals are set at its switch-out, as its CPU time is, so wakeups need no program
// and a switch no clock read. The runs since the last switch-out (one, unless the entry is new)
// go to the histogram at their mean wait.
#ifndef TASK_RUN_DELAY_OFF
#error "the kernel has no sched_info (CONFIG_SCHED_INFO): run-queue waits need the raw tracepoint path"
#endif
static __always_inline void count_waits(struct thread_sched_t *t, u64 run_delay, u64 runs)
{
    if (run_delay < t->delay_base || runs < t->runs_base + t->s.runq_waits + 1)
        return;
    u64 waited = run_delay - t->delay_base, n = runs - t->runs_base;
    u64 mean = waited > t->s.runq_ns ? waited - t->s.runq_ns : 0;
    if (n - t->s.runq_waits > 1)  // as a rule one run since the last switch-out: no division
        mean /= n - t->s.runq_waits;
    add_waits(t->s.runq_hist, mean, n - t->s.runq_waits);
    t->s.runq_ns = waited;
    t->s.runq_waits = n;
}
#else
static __always_inline void count_wait(struct thread_sched_t *t, u64 waited)
{
    t->s.runq_ns += waited;
    t->s.runq_waits++;
    add_waits(t->s.runq_hist, waited, 1);
}
#endif

// sched:sched_switch (preempt, prev, next[, prev_state])
int on_switch(struct bpf_raw_tracepoint_args *ctx)
{
    int zero = 0;
    struct oncpu_t *current = oncpu.lookup(&zero);
    if (!current)
        return 0;
    u64 prev = ctx->args[1], next = ctx->args[2];
    // What prev's counts start from if its entry is made now: its runtime (and sched_info) when it
    // was switched in here, if this CPU saw that (the probe may have been loaded since), else now.
    struct oncpu_t in = {}, out = {};
    KREAD(in.tid, prev + TASK_PID_OFF);
    KREAD(out.tid, next + TASK_PID_OFF);
    u32 prev_tid = in.tid, next_tid = out.tid;
    // The kernel has charged prev's slice to its runtime before this tracepoint (update_curr, as it
    // was dequeued or put back). Prev's sched_info holds the wait before the run now ending; next's
    // wait is added to its own as it arrives, after this tracepoint.
    u64 prev_runtime = 0;
    KREAD(prev_runtime, prev + TASK_RUNTIME_OFF);
    KREAD(out.runtime, next + TASK_RUNTIME_OFF);
#if DRUMS_ATTACH == ATTACH_TP_BTF
    u64 prev_delay = 0, prev_runs = 0;
    KREAD(prev_delay, prev + TASK_RUN_DELAY_OFF);
    KREAD(prev_runs, prev + TASK_PCOUNT_OFF);
    KREAD(out.run_delay, next + TASK_RUN_DELAY_OFF);
    KREAD(out.runs, next + TASK_PCOUNT_OFF);
#else
    u64 now = bpf_ktime_get_ns();
#endif
#ifdef SWITCH_HAS_PREV_STATE
    unsigned int state = (unsigned int)ctx->args[3];  // kernel >= 5.18
#else
    unsigned int state = 0;
    KREAD(state, prev + TASK_STATE_OFF);
#endif
    bool preempt = ctx->args[0] & 1;
    if (current->tid == prev_tid) {
        in = *current;
    } else {
        in.runtime = prev_runtime;
#if DRUMS_ATTACH == ATTACH_TP_BTF
        in.run_delay = prev_delay;
        in.runs = prev_runs;
#endif
    }

    if (prev_tid) {  // tid 0 is the idle task
        // A dead thread's last switch: its entry is only looked up, never made (see thread_died).
        struct thread_sched_t *t = (state & TASK_DEAD) ? thread_of(prev_tid) : thread_entry(prev_tid, prev, &in);
        if (t) {
            if (prev_runtime > t->runtime_base)
                t->s.oncpu_ns = prev_runtime - t->runtime_base;
            // The kernel's own rule for nvcsw/nivcsw (kernel/sched/core.c, __schedule).
            if (!preempt && state)
                t->s.voluntary++;
            else
                t->s.involuntary++;
#if DRUMS_ATTACH == ATTACH_TP_BTF
            count_waits(t, prev_delay, prev_runs);
#else
            if (preempt || state == 0)
                t->enqueued_at = now;  // still on its run queue (__schedule dequeues neither): it waits from now
#endif
            if (state & TASK_DEAD)
                thread_died(prev_tid, t, false);
            else
                mark_changed(prev_tid, &t->marked);  // after its counts: a look at the mark sees them
        } else if (state & TASK_DEAD) {
            // Folded at exit: the slice it ran since then joins its process's totals.
            u32 tgid = 0;
            KREAD(tgid, prev + TASK_TGID_OFF);
            struct exited_sched_t *p = exited_sched.lookup(&tgid);
            if (p) {
                if (prev_runtime > in.runtime)
                    __sync_fetch_and_add(&p->s.oncpu_ns, prev_runtime - in.runtime);
                __sync_fetch_and_add(preempt ? &p->s.involuntary : &p->s.voluntary, 1);
            }
        }
    }
#if DRUMS_ATTACH != ATTACH_TP_BTF
    if (next_tid) {
        struct thread_sched_t *t = thread_of(next_tid);
        if (t && t->enqueued_at) {
            count_wait(t, now - t->enqueued_at);
            t->enqueued_at = 0;
            mark_changed(next_tid, &t->marked);
        }
    }
#endif
    *current = out;
    return 0;
}

// sched:sched_wakeup and sched:sched_wakeup_new (task): the task is now on a run queue. Raw
// tracepoint programs time its wait from here. With tp_btf only new tasks come here (a program on
// every wakeup would cost more than the switches save): their entries are made before they first
// run, so that a new process has its rows from its start, not from its first switch-out.
int on_wakeup(struct bpf_raw_tracepoint_args *ctx)
{
    u64 task = ctx->args[0];
    struct oncpu_t base = {};  // a thread that waits does not run: this is its runtime until it does
    KREAD(base.tid, task + TASK_PID_OFF);
    KREAD(base.runtime, task + TASK_RUNTIME_OFF);
#if DRUMS_ATTACH == ATTACH_TP_BTF
    KREAD(base.run_delay, task + TASK_RUN_DELAY_OFF);
    KREAD(base.runs, task + TASK_PCOUNT_OFF);
#endif
    struct thread_sched_t *t = base.tid ? thread_entry(base.tid, task, &base) : 0;
#if DRUMS_ATTACH != ATTACH_TP_BTF
    if (t)
        t->enqueued_at = bpf_ktime_get_ns();
#endif
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
    struct thread_sched_t *t = thread_of(tid);
    if (!t)
        return 0;
#if DRUMS_ATTACH == ATTACH_TP_BTF
    // The exiting task is the tracepoint's first argument (typed here): bpf_get_current_task_btf
    // came in Linux 5.11.
    u64 task = ctx->args[0], run_delay = 0, runs = 0;  // the wait before its run now
    KREAD(run_delay, task + TASK_RUN_DELAY_OFF);
    KREAD(runs, task + TASK_PCOUNT_OFF);
    count_waits(t, run_delay, runs);
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
    struct thread_sched_t *t = thread_of(old_tid);
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
    struct thread_sched_t *t = thread_of(tid);
    if (t) {
        bpf_probe_read_kernel_str(t->comm, sizeof(t->comm), (void *)ctx->args[1]);
        mark_changed(tid, &t->marked);
    }
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

