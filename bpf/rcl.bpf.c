// Messages published and taken per ROS 2 publisher and subscription, counted by uprobes on
// librcl's rcl_publish* and rcl_take* functions; the time between two publishes of each publisher;
// each message's delivery, from the stamps the RMW gives rcl_take; and each node's reaction time:
// from a thread's take of a message to its publishes until it takes another, runs a timer
// (rcl_timer_call) or takes a service request or response, per input and output. Not at rcl_wait:
// an executor waits as often as it takes, and a uprobe there would cost every message a trap. On
// one host Fast DDS moves samples over shared memory, where no socket sees them; every ROS 2 client
// library still goes through rcl.
//
// The agent attaches these programs to each librcl.so it finds in processes' memory maps, and
// names each handle (an rcl_publisher_t or rcl_subscription_t address) by reading its topic name
// from the process's memory.
#include <uapi/linux/ptrace.h>
#define DROPS 5
#include "drums.h"

#define PUBLISHED 0
#define TAKEN 1

struct handle_key_t {
    u32 tgid;
    u32 op;       // PUBLISHED or TAKEN
    u64 handle;   // the rcl_publisher_t * or rcl_subscription_t * passed as first argument
};

BPF_HASH(handles, struct handle_key_t, u64, 16384);

// Times in log-linear slots: 2^SUB_LOG2 slots per power of two of nanoseconds (each under 1.6%
// wide) over OCTAVES powers of two from 2^min_log2 ns, one slot under and one over. The agent
// exports the edges of the slots that hold counts as Prometheus buckets: a quantile within 1% of
// the truth at any rate, where a fixed set of buckets would be off by up to a whole bucket.
#define SUB_LOG2 6
#define OCTAVES 17
#define SLOTS ((OCTAVES << SUB_LOG2) + 2)
#define PERIOD_MIN_LOG2 17    // periods: 131 us to 17.2 s
#define REACTION_MIN_LOG2 14  // reactions: 16 us to 2.1 s
#define DELIVERY_MIN_LOG2 12  // deliveries: 4 us to 537 ms
struct timing_t {
    u64 last_ns;  // when the publisher last published, or the subscription last took (periods)
    u64 sum_ns;
    u64 missed;   // deadlines that passed between two messages, for an endpoint in `deadlines`
    u64 messages; // a publisher's messages: counted here rather than in `handles`, one lookup fewer
    u32 slots[SLOTS];
};
// Allocated as publishers first publish (4.4 KB each), not for all of them up front; for a
// subscription that requests a deadline, as it takes (its deadlines missed, its slots unread).
BPF_F_TABLE("hash", struct handle_key_t, struct timing_t, periods, 4096, BPF_F_NO_PREALLOC);
// A node's reaction: the subscription a thread took from and the publisher it then published on.
struct reaction_key_t {
    u32 tgid;
    u32 pad;
    u64 input;
    u64 output;
};
BPF_F_TABLE("hash", struct reaction_key_t, struct timing_t, reactions, 4096, BPF_F_NO_PREALLOC);
BPF_PERCPU_ARRAY(timing_zero, struct timing_t, 1);  // never written: what a new entry starts as

// rmw_message_info_t (rmw/types.h, Humble and later): source_timestamp and received_timestamp
// (ns of the realtime clock), two sequence numbers, then publisher_gid: its identifier pointer and
// the GUID's 16 bytes.
#define MESSAGE_INFO_GID_OFF 40
struct message_info_t {
    s64 source_ns;
    s64 received_ns;
    u8 between[MESSAGE_INFO_GID_OFF - 16];
    u8 publisher[16];
};
// Deliveries to a subscription from one publisher: the transport (received less source stamp) and
// the message's age when the subscriber took it (take less source stamp). Every message counted
// here (timed, or skewed) is a take not counted in `handles`: one lookup fewer.
struct delivery_key_t {
    u32 tgid;
    u32 pad;
    u64 subscription;
    u8 publisher[16];
};
struct delivery_t {
    u64 transport_sum_ns;
    u64 age_sum_ns;
    u64 skewed;  // messages stamped after they were received or taken: clocks apart (two hosts)
    u32 transport[SLOTS];
    u32 age[SLOTS];
};
BPF_F_TABLE("hash", struct delivery_key_t, struct delivery_t, deliveries, 4096, BPF_F_NO_PREALLOC);
BPF_PERCPU_ARRAY(delivery_zero, struct delivery_t, 1);
// CLOCK_REALTIME less CLOCK_MONOTONIC (ns), written by the agent as it starts and at each collect.
BPF_ARRAY(realtime_offset, s64, 1);
// The Deadline QoS of publishers that offer one and subscriptions that request one, in ns, written
// by the agent from the graph: a period of n deadlines or more between two messages published, or
// taken, counts n missed, as the kernel saw the messages (not as the application's QoS events say).
BPF_HASH(deadlines, struct handle_key_t, u64, 4096);
// How many entries `deadlines` has, as the agent wrote it: an array is read for nearly nothing, and
// saves hashing every message's key where no endpoint has a deadline.
BPF_ARRAY(deadlines_known, u32, 1);

static __always_inline u64 deadline_of(struct handle_key_t *key)
{
    int zero = 0;
    u32 *known = deadlines_known.lookup(&zero);
    u64 *deadline = known && *known ? deadlines.lookup(key) : 0;
    return deadline ? *deadline : 0;
}
// Per thread: the subscription it passed to rcl_take, kept until it returns, and the last one it
// took a message from and when, until it takes another or runs a timer or service. Task-local
// storage where tracing programs have it (TASK_STORAGE: Linux >= 5.12, "bpf: Enable task local
// storage for tracing programs"), not a hash keyed by thread: a hash update costs about 0.5 us
// here, where this is a pointer lookup. Before, that hash, LRU so that ended threads' entries go.
struct took_t {
    u64 pending;
    u64 info;  // the rmw_message_info_t the pending take fills
    u64 input;
    u64 at;
};
#ifdef TASK_STORAGE
BPF_TASK_STORAGE(takes, struct took_t);
#else
BPF_TABLE("lru_hash", u32, struct took_t, takes, 16384);  // threads between takes at once
#endif

// The calling thread's, made if `create` and it has none.
static __always_inline struct took_t *took_of_thread(int create)
{
#ifdef TASK_STORAGE
    return takes.task_storage_get(bpf_get_current_task_btf(), 0, create ? BPF_LOCAL_STORAGE_GET_F_CREATE : 0);
#else
    u32 tid = (u32)bpf_get_current_pid_tgid();
    struct took_t *t = takes.lookup(&tid);
    if (t || !create)
        return t;
    struct took_t fresh = {};
    takes.update(&tid, &fresh);
    return takes.lookup(&tid);
#endif
}
// Processes that took a message (a byte per PID modulo TAKERS): a thread of one that never did
// reacts to nothing, and its publishes skip the task-storage lookup (a helper call) for an array's
// read. A PID that shares a slot only costs its publishes that lookup.
#define TAKERS 4096
BPF_ARRAY(takers, u8, TAKERS);

static __always_inline void count(struct handle_key_t *key)
{
    u64 zero = 0;
    u64 *n = handles.lookup_or_try_init(key, &zero);
    if (n)
        __sync_fetch_and_add(n, 1);
    else
        count_drop(1);
}

static __always_inline u64 log_slot(u64 ns, u64 min_log2)
{
    if (ns < (1ULL << min_log2))
        return 0;
    u64 octave = bpf_log2l(ns) - 1;  // 2^octave <= ns < 2^(octave + 1)
    if (octave >= min_log2 + OCTAVES)
        return SLOTS - 1;
    u64 sub = (ns >> (octave - SUB_LOG2)) & ((1 << SUB_LOG2) - 1);
    return 1 + ((octave - min_log2) << SUB_LOG2) + sub;
}

// 64 bits: the verifier follows the bound to the access.
static __always_inline void count_slot(struct timing_t *t, u64 slot)
{
    if (slot < SLOTS)
        __sync_fetch_and_add(&t->slots[slot], 1);
}

// What a new entry of `periods` or `reactions` starts as.
static __always_inline struct timing_t *zero_timing(void)
{
    int zero = 0;
    return timing_zero.lookup(&zero);
}

// The endpoint's period entry, with the time since its last message counted; 0 if no entry
// could be had.
static __always_inline struct timing_t *period(struct handle_key_t *key, u64 now, u64 deadline)
{
    struct timing_t *p = periods.lookup(key), *fresh = p ? 0 : zero_timing();
    if (fresh)  // the template is looked up only for an endpoint's first message
        p = periods.lookup_or_try_init(key, fresh);
    if (!p) {
        count_drop(2);
        return 0;
    }
    // Threads publishing at once on one publisher may both measure from the same last publish:
    // rare, and no count is lost.
    u64 last = p->last_ns;
    p->last_ns = now;
    if (last && now > last) {
        __sync_fetch_and_add(&p->sum_ns, now - last);
        if (deadline)
            __sync_fetch_and_add(&p->missed, (now - last) / deadline);
        count_slot(p, log_slot(now - last, PERIOD_MIN_LOG2));
    }
    return p;
}

static __always_inline void reaction(u32 tgid, u64 output, u64 now)
{
    struct took_t *took = took_of_thread(0);
    if (!took || !took->input || now < took->at)
        return;
    struct reaction_key_t key = {.tgid = tgid, .input = took->input, .output = output};
    struct timing_t *r = reactions.lookup(&key), *fresh = r ? 0 : zero_timing();
    if (fresh)
        r = reactions.lookup_or_try_init(&key, fresh);
    if (!r) {
        count_drop(3);
        return;
    }
    __sync_fetch_and_add(&r->sum_ns, now - took->at);
    count_slot(r, log_slot(now - took->at, REACTION_MIN_LOG2));
}

// DRUMS_COUNT_ONLY (drums agent --no-ros-timing): messages are counted, not timed.
int on_publish(struct pt_regs *ctx)
{
    struct handle_key_t key = {.tgid = bpf_get_current_pid_tgid() >> 32, .op = PUBLISHED,
                               .handle = PT_REGS_PARM1(ctx)};
#ifdef DRUMS_COUNT_ONLY
    count(&key);
#else
    u64 now = bpf_ktime_get_ns();
    struct timing_t *p = period(&key, now, deadline_of(&key));
    if (p)
        __sync_fetch_and_add(&p->messages, 1);
    else
        count(&key);  // no period entry to be had: counted as without timing
    u32 slot = key.tgid & (TAKERS - 1);
    u8 *taker = takers.lookup(&slot);
    if (taker && *taker)
        reaction(key.tgid, key.handle, now);
#endif
    return 0;
}

// Whether the take was counted here (timed, or skewed).
static __always_inline int delivery(u32 tgid, u64 subscription, u64 info, u64 now)
{
    struct message_info_t m;  // one read of user memory: its stamps and the GID
    if (bpf_probe_read_user(&m, sizeof(m), (void *)info) != 0)
        return 0;
    int zero = 0;
    s64 *offset = realtime_offset.lookup(&zero);
    if (m.source_ns <= 0 || m.received_ns <= 0 || !offset || !*offset)
        return 0;  // the RMW stamps nothing, or the agent has not said the clock yet
    struct delivery_key_t key = {.tgid = tgid, .subscription = subscription};
    __builtin_memcpy(key.publisher, m.publisher, sizeof(key.publisher));
    struct delivery_t *d = deliveries.lookup(&key), *fresh = d ? 0 : delivery_zero.lookup(&zero);
    if (fresh)
        d = deliveries.lookup_or_try_init(&key, fresh);
    if (!d) {
        count_drop(4);
        return 0;
    }
    s64 transport = m.received_ns - m.source_ns, age = (s64)now + *offset - m.source_ns;
    if (transport < 0 || age < 0) {
        __sync_fetch_and_add(&d->skewed, 1);
        return 1;
    }
    __sync_fetch_and_add(&d->transport_sum_ns, transport);
    __sync_fetch_and_add(&d->age_sum_ns, age);
    u64 slot = log_slot(transport, DELIVERY_MIN_LOG2);
    if (slot < SLOTS)
        __sync_fetch_and_add(&d->transport[slot], 1);
    slot = log_slot(age, DELIVERY_MIN_LOG2);
    if (slot < SLOTS)
        __sync_fetch_and_add(&d->age[slot], 1);
    return 1;
}

// rcl_take(subscription, message, message_info, allocation) returns RCL_RET_OK (0) only when it
// took a message: that needs the return probe too.
int on_take(struct pt_regs *ctx)
{
    struct took_t *took = took_of_thread(1);
    if (took) {
        took->pending = PT_REGS_PARM1(ctx);
        took->info = PT_REGS_PARM3(ctx);
    } else {
        count_drop(0);
    }
    return 0;
}

int on_take_return(struct pt_regs *ctx)
{
    struct took_t *took = took_of_thread(0);
    if (!took || !took->pending)
        return 0;
    u64 h = took->pending;
    took->pending = 0;
    if (PT_REGS_RC(ctx) == 0) {
        struct handle_key_t key = {.tgid = bpf_get_current_pid_tgid() >> 32, .op = TAKEN, .handle = h};
#ifdef DRUMS_COUNT_ONLY
        count(&key);
#else
        u64 now = bpf_ktime_get_ns();
        u64 deadline = deadline_of(&key);
        if (deadline)
            period(&key, now, deadline);
        took->input = h;
        took->at = now;
        u32 slot = key.tgid & (TAKERS - 1);
        u8 *taker = takers.lookup(&slot);
        if (taker && !*taker)
            *taker = 1;
        if (!took->info || !delivery(key.tgid, h, took->info, now))
            count(&key);  // not counted with its delivery
#endif
    }
    return 0;
}

// rcl_timer_call, rcl_take_request and rcl_take_response: what the thread publishes next reacts to
// a timer or a service, not to the message it took last.
int on_idle(struct pt_regs *ctx)
{
    struct took_t *took = took_of_thread(0);
    if (took)
        took->input = 0;
    return 0;
}
