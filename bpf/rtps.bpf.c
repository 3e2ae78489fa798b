// Samples and bytes per DDS writer, read from the RTPS messages that watched processes send and
// receive over UDP. All topics of a DDS participant share its sockets, so the socket counters
// cannot split them; the RTPS header can: a 12-byte GUID prefix names the participant, and each
// DATA or DATA_FRAG submessage names its writer (entity id) and the sample's sequence number.
//
// Only processes in `watched` (filled by the agent: those with a DDS library loaded) are parsed.
// The syscall tracepoints are attached as perf-event links so they can be pinned like the rest
// (Linux >= 5.15; before, the agent holds their perf events).
// A datagram is read where it lies in user memory after the call returned; a field split between
// two pieces of a gathered send is not read (Fast DDS puts all headers in the first piece).
#include <uapi/linux/ptrace.h>
#define DROPS 2
#include "drums.h"

#define MAX_IOV 4            // Fast DDS sends header, payload, padding, trailer: 4 pieces
#define MAX_SUBMESSAGES 24   // discovery batches about 20 (INFO_TS, DATA) pairs in one datagram
#define RTPS_HEADER 20       // "RTPS", version, vendor, GUID prefix
#define SUB_INFO_SRC 0x0c
#define SUB_DATA 0x15
#define SUB_DATA_FRAG 0x16
#define FLAG_LITTLE 0x01
#define FLAG_DATA 0x04       // DATA carries a serialized sample
#define FLAG_KEY 0x08        // ... or a serialized key
#define SENT 0
#define RECEIVED 1

struct writer_key_t {
    u32 tgid;       // the process that sent or received
    u32 direction;  // SENT or RECEIVED
    u8 prefix[12];  // the writer's GUID: participant prefix ...
    u8 entity[4];   // ... and entity id
};

struct writer_counts_t {
    u64 samples;       // sequence numbers seen for the first time: repairs and resends are not samples
    u64 sample_bytes;  // the serialized size of each of those samples
    u64 wire_bytes;    // serialized payload in every datagram: each destination, each repair
    s64 last_sn;       // the highest sequence number seen
    u64 seen;          // bit i: last_sn - i was seen. A repair of a lost sample comes after later
                       // ones; it is a sample if it is one of the SEEN_WINDOW before the highest
};
#define SEEN_WINDOW 64

struct segment_t {
    u64 base;
    u64 len;
};

// The first HEAD bytes of a datagram, read in one go: every header of a user sample lies there
// (Fast DDS's first piece holds the RTPS header, INFO_DST, INFO_TS and the DATA header). One
// read instead of one per field: each bpf_probe_read_user costs about 100 ns here.
#define HEAD 256
struct head_t {
    u8 b[HEAD + 32];  // slack: the verifier sees a field of up to 32 bytes at any offset below HEAD
};

struct datagram_t {
    struct segment_t seg[MAX_IOV];
    u32 nseg;
    u32 cached;  // bytes of seg[0] in head
    u8 *head;
};

BPF_HASH(watched, u32, u8, 4096);  // processes with a DDS library, set by the agent
BPF_TABLE("lru_hash", struct writer_key_t, struct writer_counts_t, writers, 16384);
#ifdef PREEMPT_RT
// Under PREEMPT_RT a program runs with migration, not preemption, disabled: another thread's call
// on this CPU can come in the middle of a parse and overwrite a per-CPU head, so each thread has
// its own (of those that send or receive in watched processes; LRU, so ended threads' go).
BPF_TABLE("lru_hash", u32, struct head_t, heads, 4096);
BPF_PERCPU_ARRAY(head_zero, struct head_t, 1);  // never written: what a thread's head starts as
#else
BPF_PERCPU_ARRAY(heads, struct head_t, 1);
#endif

// Reads n bytes (a constant, at most 32) at a logical offset of the datagram: from the head read
// already where it lies there, else from user memory; a field split across two pieces is not read.
static __always_inline int read_at(struct datagram_t *dg, u64 off, void *dst, u32 n)
{
    if (off + n <= dg->cached) {
        __builtin_memcpy(dst, dg->head + (off & (HEAD - 1)), n);
        return 0;
    }
    for (int i = 0; i < MAX_IOV; i++) {
        if (i >= dg->nseg)
            return -1;
        if (off < dg->seg[i].len) {
            if (off + n > dg->seg[i].len)
                return -1;
            return bpf_probe_read_user(dst, n, (void *)(dg->seg[i].base + off));
        }
        off -= dg->seg[i].len;
    }
    return -1;
}

static __always_inline u16 field16(u8 *p, u8 flags)
{
    return flags & FLAG_LITTLE ? p[0] | p[1] << 8 : p[0] << 8 | p[1];
}

static __always_inline u32 field32(u8 *p, u8 flags)
{
    return flags & FLAG_LITTLE ? p[0] | p[1] << 8 | p[2] << 16 | (u32)p[3] << 24
                               : (u32)p[0] << 24 | p[1] << 16 | p[2] << 8 | p[3];
}

static __always_inline void count_sample(struct writer_key_t *key, s64 sn, u64 size, u64 bytes)
{
    struct writer_counts_t fresh = {.last_sn = -1};
    struct writer_counts_t *c = writers.lookup_or_try_init(key, &fresh);
    if (!c) {
        count_drop(1);
        return;
    }
    __sync_fetch_and_add(&c->wire_bytes, bytes);
    if (!size)
        return;
    if (sn > c->last_sn) {
        u64 ahead = sn - c->last_sn;
        c->seen = ahead < SEEN_WINDOW ? c->seen << ahead | 1 : 1;
        c->last_sn = sn;
    } else {
        u64 behind = c->last_sn - sn;
        if (behind >= SEEN_WINDOW || c->seen & 1ULL << behind)
            return;  // a resend, or a sequence number too old to tell
        c->seen |= 1ULL << behind;
    }
    __sync_fetch_and_add(&c->samples, 1);
    __sync_fetch_and_add(&c->sample_bytes, size);
}

static __always_inline void parse(struct datagram_t *dg, u64 total, u32 direction)
{
    struct writer_key_t key = {.tgid = bpf_get_current_pid_tgid() >> 32, .direction = direction};
    u8 head[RTPS_HEADER];
    if (total < RTPS_HEADER || read_at(dg, 0, head, RTPS_HEADER) != 0)
        return;
    if (head[0] != 'R' || head[1] != 'T' || head[2] != 'P' || head[3] != 'S')
        return;
    __builtin_memcpy(key.prefix, head + 8, 12);
    u64 off = RTPS_HEADER;
    for (int i = 0; i < MAX_SUBMESSAGES; i++) {
        u8 sub[4];
        if (off + 4 > total || read_at(dg, off, sub, 4) != 0)
            return;
        u8 flags = sub[1];
        u64 len = field16(sub + 2, flags);
        u64 body = off + 4;
        u64 size = len ? len : total - body;  // a last submessage may say 0: "to the end"
        if (sub[0] == SUB_INFO_SRC) {
            if (read_at(dg, body + 8, key.prefix, 12) != 0)
                return;
        } else if (sub[0] == SUB_DATA || sub[0] == SUB_DATA_FRAG) {
            // extraFlags, octetsToInlineQos, readerId, writerId, writerSN (high, low); DATA_FRAG
            // goes on: fragmentStartingNum, fragmentsInSubmessage, fragmentSize, sampleSize
            u8 d[32];
            if (read_at(dg, body, d, 20) == 0 && (d[11] == 0x02 || d[11] == 0x03)) {
                // entity kinds 0x02/0x03: user-defined writers; built-in discovery is skipped
                __builtin_memcpy(key.entity, d + 8, 4);
                s64 sn = (s64)field32(d + 12, flags) << 32 | field32(d + 16, flags);
                u64 header = 4 + field16(d + 2, flags);  // up to the payload (or inline QoS)
                u64 bytes = size > header ? size - header : 0;
                u64 sample = 0;
                if (sub[0] == SUB_DATA_FRAG) {
                    if (read_at(dg, body + 28, d + 28, 4) == 0)
                        sample = field32(d + 28, flags);
                } else if (flags & (FLAG_DATA | FLAG_KEY)) {
                    sample = bytes;
                }
                count_sample(&key, sn, sample, bytes);
            }
        }
        if (!len)
            return;
        off = body + len;
    }
}

// Where the head of a datagram is read to.
static __always_inline struct head_t *scratch(void)
{
    int zero = 0;
#ifdef PREEMPT_RT
    u32 tid = (u32)bpf_get_current_pid_tgid();
    struct head_t *h = heads.lookup(&tid), *fresh = h ? 0 : head_zero.lookup(&zero);
    return fresh ? heads.lookup_or_try_init(&tid, fresh) : h;
#else
    return heads.lookup(&zero);
#endif
}

#ifdef SYSCALL_ENTRIES
// Before Linux 5.15 (no bpf_task_pt_regs) the entry is traced too, for the argument: kept per
// thread until the call returns, for every process, since a node's receiving thread blocks in its
// call before the agent knows the process speaks DDS. So only a call that was under way when the
// probe loaded goes unparsed. LRU, sized for the threads in such calls at once: an entry whose exit
// went untraced is replaced by its thread's next call.
BPF_TABLE("lru_hash", u32, u64, arguments, 16384);

static __always_inline int enter(struct syscall_enter_t *ctx)
{
    u32 tid = (u32)bpf_get_current_pid_tgid();
    u64 ptr = ctx->args[1];
    arguments.update(&tid, &ptr);
    return 0;
}

int enter_sendto(void *ctx) { return enter(ctx); }
int enter_sendmsg(void *ctx) { return enter(ctx); }
int enter_recvfrom(void *ctx) { return enter(ctx); }
int enter_recvmsg(void *ctx) { return enter(ctx); }
#endif

// Where the kernel has bpf_task_pt_regs (Linux >= 5.15), only the exit is traced: the buffer (or
// struct msghdr) argument is still in the registers the task saved on entering the kernel. Tracing
// the entry too costs a second event per call, and misses the first datagram of a thread that was
// already waiting when it became watched.
static __always_inline int leave(void *ctx, u32 msghdr, u32 direction)
{
    s64 ret = ((struct syscall_exit_t *)ctx)->ret;
    u64 ptr = 0;
#ifdef SYSCALL_ENTRIES
    u64 id = bpf_get_current_pid_tgid();
    u32 tgid = id >> 32, tid = (u32)id;
    u64 *arg = arguments.lookup(&tid);
    if (!arg)
        return 0;
    ptr = *arg;
    arguments.delete(&tid);
    if (ret <= 0 || !ptr || !watched.lookup(&tgid))
        return 0;
#else
    u32 tgid = bpf_get_current_pid_tgid() >> 32;
    if (ret <= 0 || !watched.lookup(&tgid))
        return 0;
    struct pt_regs *regs = (struct pt_regs *)bpf_task_pt_regs(bpf_get_current_task_btf());
    if (bpf_probe_read_kernel(&ptr, sizeof(ptr), &PT_REGS_PARM2(regs)) != 0 || !ptr)
        return 0;
#endif
    struct head_t *head = scratch();
    if (!head)
        return 0;
    struct datagram_t dg = {.nseg = 1, .head = head->b};
    if (msghdr) {
        // struct user_msghdr: msg_iov at 16, msg_iovlen at 24 (LP64 user-space ABI)
        u64 iov[2] = {};
        if (bpf_probe_read_user(iov, sizeof(iov), (void *)(ptr + 16)) != 0 || !iov[1])
            return 0;
        dg.nseg = iov[1] < MAX_IOV ? iov[1] : MAX_IOV;
        if (bpf_probe_read_user(dg.seg, dg.nseg * sizeof(dg.seg[0]), (void *)iov[0]) != 0)
            return 0;
    } else {
        // One piece, copied in as a msghdr's pieces are: the verifier then knows nothing of its
        // length, as of theirs, and does not follow every bound the parser compares it with (a
        // plain store took the verifier 940,000 of its 1,000,000 instructions; this, 105,000).
        struct segment_t one = {.base = ptr, .len = ret};
        bpf_probe_read_kernel(dg.seg, sizeof(one), &one);
    }
    u64 cached = dg.seg[0].len < (u64)ret ? dg.seg[0].len : ret;  // a receive fills only what arrived
    OPAQUE(cached);
    if (cached > HEAD)
        cached = HEAD;
    if (bpf_probe_read_user(dg.head, cached, (void *)dg.seg[0].base) == 0)
        dg.cached = cached;
    parse(&dg, ret, direction);
    return 0;
}

int on_sendto(void *ctx) { return leave(ctx, 0, SENT); }
int on_sendmsg(void *ctx) { return leave(ctx, 1, SENT); }
int on_recvfrom(void *ctx) { return leave(ctx, 0, RECEIVED); }
int on_recvmsg(void *ctx) { return leave(ctx, 1, RECEIVED); }
