// Messages published and taken per ROS 2 publisher and subscription, counted by uprobes on
// librcl's rcl_publish* and rcl_take* functions, and the time between two publishes of each
// publisher. On one host Fast DDS moves samples over shared
// memory, where no socket sees them; every ROS 2 client library still goes through rcl.
//
// The agent attaches these programs to each librcl.so it finds in processes' memory maps, and
// names each handle (an rcl_publisher_t or rcl_subscription_t address) by reading its topic name
// from the process's memory.
#include <uapi/linux/ptrace.h>
#include "drums.h"

#define PUBLISHED 0
#define TAKEN 1

struct handle_key_t {
    u32 tgid;
    u32 op;       // PUBLISHED or TAKEN
    u64 handle;   // the rcl_publisher_t * or rcl_subscription_t * passed as first argument
};

BPF_HASH(handles, struct handle_key_t, u64, 16384);

// Time between two publishes of one publisher, in log-linear slots: 2^PERIOD_SUB_LOG2 slots per
// power of two of microseconds (each under 1.6% wide) from 2^PERIOD_MIN_LOG2 us (128 us) to
// 2^24 us (16.8 s), one slot under and one over. The agent exports the edges of the slots that
// hold counts as Prometheus buckets: a quantile within 1% of the truth at any rate, where a fixed
// set of buckets would be off by up to a whole bucket.
#define PERIOD_SUB_LOG2 6
#define PERIOD_MIN_LOG2 7
#define PERIOD_OCTAVES 17
#define PERIOD_SLOTS ((PERIOD_OCTAVES << PERIOD_SUB_LOG2) + 2)
struct period_t {
    u64 last_ns;  // when the publisher last published
    u64 sum_ns;
    u64 missed;   // deadlines that passed between two messages, for a publisher in `deadlines`
    u32 slots[PERIOD_SLOTS];
};
// Allocated as publishers first publish (4.4 KB each), not for all of them up front.
BPF_F_TABLE("hash", struct handle_key_t, struct period_t, periods, 4096, BPF_F_NO_PREALLOC);
BPF_PERCPU_ARRAY(period_zero, struct period_t, 1);  // never written: what a new entry starts as
// The Deadline QoS of publishers that offer one, in ns, written by the agent from the graph: a
// period of n deadlines or more counts n missed, as the kernel saw the messages (not as the
// application's QoS events say).
BPF_HASH(deadlines, struct handle_key_t, u64, 4096);
// The subscription a thread passed to rcl_take, kept until it returns. Task-local storage, not a
// hash keyed by thread: a hash update costs about 0.5 us here, where this is a pointer lookup.
BPF_TASK_STORAGE(takes, u64);
BPF_ARRAY(dropped, u64, 3);

static __always_inline void count_drop(int which)
{
    u64 *d = dropped.lookup(&which);
    if (d)
        __sync_fetch_and_add(d, 1);
}

static __always_inline void count(struct handle_key_t *key)
{
    u64 zero = 0;
    u64 *n = handles.lookup_or_try_init(key, &zero);
    if (n)
        __sync_fetch_and_add(n, 1);
    else
        count_drop(1);
}

static __always_inline u64 period_slot(u64 ns)
{
    u64 us = ns / 1000;
    if (us < (1ULL << PERIOD_MIN_LOG2))
        return 0;
    u64 octave = bpf_log2l(us) - 1;  // 2^octave <= us < 2^(octave + 1)
    if (octave >= PERIOD_MIN_LOG2 + PERIOD_OCTAVES)
        return PERIOD_SLOTS - 1;
    u64 sub = (us >> (octave - PERIOD_SUB_LOG2)) & ((1 << PERIOD_SUB_LOG2) - 1);
    return 1 + ((octave - PERIOD_MIN_LOG2) << PERIOD_SUB_LOG2) + sub;
}

static __always_inline void period(struct handle_key_t *key, u64 now)
{
    struct period_t *p = periods.lookup(key);
    if (!p) {
        int zero = 0;
        struct period_t *fresh = period_zero.lookup(&zero);
        if (!fresh)
            return;
        periods.insert(key, fresh);  // fails only if full, or if another thread made it first
        p = periods.lookup(key);
        if (!p) {
            count_drop(2);
            return;
        }
    }
    // Threads publishing at once on one publisher may both measure from the same last publish:
    // rare, and no count is lost.
    u64 last = p->last_ns;
    p->last_ns = now;
    if (!last || now <= last)
        return;
    __sync_fetch_and_add(&p->sum_ns, now - last);
    u64 *deadline = deadlines.lookup(key);
    if (deadline && *deadline)
        __sync_fetch_and_add(&p->missed, (now - last) / *deadline);
    u64 slot = period_slot(now - last);  // 64 bits: the verifier follows the bound to the access
    if (slot < PERIOD_SLOTS)
        __sync_fetch_and_add(&p->slots[slot], 1);
}

int on_publish(struct pt_regs *ctx)
{
    u64 now = bpf_ktime_get_ns();
    struct handle_key_t key = {.tgid = bpf_get_current_pid_tgid() >> 32, .op = PUBLISHED,
                               .handle = PT_REGS_PARM1(ctx)};
    count(&key);
    period(&key, now);
    return 0;
}

// rcl_take returns RCL_RET_OK (0) only when it took a message: that needs the return probe too.
int on_take(struct pt_regs *ctx)
{
    u64 *handle = takes.task_storage_get(bpf_get_current_task_btf(), 0, BPF_LOCAL_STORAGE_GET_F_CREATE);
    if (handle)
        *handle = PT_REGS_PARM1(ctx);
    else
        count_drop(0);
    return 0;
}

int on_take_return(struct pt_regs *ctx)
{
    u64 *handle = takes.task_storage_get(bpf_get_current_task_btf(), 0, 0);
    if (!handle || !*handle)
        return 0;
    u64 h = *handle;
    *handle = 0;
    if (PT_REGS_RC(ctx) == 0) {
        struct handle_key_t key = {.tgid = bpf_get_current_pid_tgid() >> 32, .op = TAKEN, .handle = h};
        count(&key);
    }
    return 0;
}
