// Bytes, calls and errors of every TCP, UDP and unix socket, per socket and per process.
//
// A socket's counts go to the process that first used it (its owner): a call looks up the
// socket's entry and nothing else, which is what one call costs (a second lookup, per thread, cost
// as much again). The entry is in the socket's slot of an array (by a hash of its id) when
// that is free, else in a hash: an array lookup is a few instructions, a hash lookup a function
// call (half of what a call's program cost before the slots). When an entry goes, its counts are
// folded into its owner's closed_traffic, so that the owner's totals (its sockets' entries plus
// that) never go backwards.
//
// Kernel struct offsets arrive as -D flags read from the running kernel's BTF (drums/kernel/btf.py),
// never from the installed headers, which may belong to another kernel. DRUMS_ATTACH picks the
// attach path chosen by drums/probes/sockets.py: 6 (tp_btf) or 1 (raw) = the sock_send/recv_length
// tracepoints (kernel >= 6.6), 2 = fexit, 3 = kprobes on the families' sendmsg and recvmsg.
#define DROPS 2
#define MARKED_KEY u64
#include "drums.h"

#define CLASS_TCP 0
#define CLASS_UDP 1
#define CLASS_UNIX 2
#define CLASS_OTHER 3
#define NCLASSES 4  // a power of two (fold masks with it)

#define DROP_SOCKET 0
#define DROP_PROCESS 1

struct traffic_t {
    u64 sent_bytes;
    u64 sent_calls;
    u64 recv_bytes;
    u64 recv_calls;
    u64 send_errors;
    u64 recv_errors;
};

// One per socket (keyed by its id: see socket_id); identity is read once, at first use.
struct socket_traffic_t {
    u64 ino;          // socket inode: tells a reused struct sock from the socket that held it before
    u32 tgid;         // process that first used the socket: its owner
    u32 netns;
    u16 family;
    u16 protocol;
    u16 unused;
    u16 lport;        // host byte order
    u16 rport;        // host byte order
    u16 klass;
    u32 pad;
    u8 laddr[16];     // IPv4 addresses use the first 4 bytes
    u8 raddr[16];
    struct traffic_t t;
    u64 marked;       // the generation in which the socket was last marked changed (see below)
    u64 process_start;  // of the owner: with tgid, what tells it from a later process with its PID
    u64 id;           // in a slot, the socket that owns it; 0 in a free slot and in socket_traffic
};

// What a process's sockets counted that their entries no longer hold, kept after it ended until the
// agent has read its final totals (and deleted the entry): process_start tells it from a later
// process that got its PID.
struct process_traffic_t {
    u64 process_start;
    struct traffic_t by_class[NCLASSES];
    char comm[16];  // its name when it last closed a socket: the agent may never have seen the process
};

// Sockets whose slot (below) another socket holds, or all of them before Linux 5.12. With the
// slots, room for 40,960 open sockets (the benchmark's 10,000 with room for churn; 10,000 sockets
// leave about a quarter here); a full map is counted.
BPF_HASH(socket_traffic, u64, struct socket_traffic_t, 24576);
// Slot slot_of(id) holds the entry of the first live socket with that slot: taken with a
// compare-and-swap of its `id` (Linux >= 5.12; elsewhere SOCKET_SLOTS is 1 and no slot is used);
// all zero while free. Memory-mapped, so the agent reads it in place.
BPF_F_TABLE("array", u32, struct socket_traffic_t, socket_slots, SOCKET_SLOTS, BPF_F_MMAPABLE);
// Counts of closed sockets (and of calls on sockets without an entry), per owner, until the agent has
// read them after it ended.
BPF_HASH(closed_traffic, u32, struct process_traffic_t, 16384);

static __always_inline u16 classify(u16 family, u16 protocol)
{
    if (family == AF_UNIX)
        return CLASS_UNIX;
    if (family == AF_INET || family == AF_INET6) {
        if (protocol == IPPROTO_TCP)
            return CLASS_TCP;
        if (protocol == IPPROTO_UDP || protocol == IPPROTO_UDPLITE)
            return CLASS_UDP;
    }
    return CLASS_OTHER;
}

static __always_inline void add_traffic(struct traffic_t *into, struct traffic_t *from)
{
    // Atomic: the sockets of a process close on several CPUs at once.
    __sync_fetch_and_add(&into->sent_bytes, from->sent_bytes);
    __sync_fetch_and_add(&into->sent_calls, from->sent_calls);
    __sync_fetch_and_add(&into->recv_bytes, from->recv_bytes);
    __sync_fetch_and_add(&into->recv_calls, from->recv_calls);
    __sync_fetch_and_add(&into->send_errors, from->send_errors);
    __sync_fetch_and_add(&into->recv_errors, from->recv_errors);
}

// Counts that no socket entry holds, added to the process's closed_traffic.
static __always_inline void fold(u32 tgid, u64 start, u16 klass, struct traffic_t *t)
{
    if (klass >= NCLASSES)
        return;
    struct process_traffic_t *p = closed_traffic.lookup(&tgid);
    if (p && p->process_start != start) {
        // Left by the process that had this PID before, which ended since the agent's last read:
        // what it did then is lost.
        closed_traffic.delete(&tgid);
        count_drop(DROP_PROCESS);
        p = 0;
    }
    if (!p) {
        struct process_traffic_t fresh = {.process_start = start};
        closed_traffic.insert(&tgid, &fresh);
        p = closed_traffic.lookup(&tgid);
    }
    OPAQUE(klass);
    if (!p) {
        count_drop(DROP_PROCESS);
        return;
    }
    add_traffic(&p->by_class[klass & (NCLASSES - 1)], t);
    if (bpf_get_current_pid_tgid() >> 32 == tgid)
        bpf_get_current_comm(p->comm, sizeof(p->comm));
}

// What names a socket in the maps: its struct sock's address, as a number. A typed program (tp_btf)
// holds that as a pointer, which the verifier lets it subtract from another pointer but not
// hash: there, it is the address less that of a map's value (which stays put while the map lives).
// 0: none.
static __always_inline u64 socket_id(u64 sk)
{
#if DRUMS_ATTACH == ATTACH_TP_BTF
    int zero = 0;
    u64 *base = dropped.lookup(&zero);
    return base ? sk - (u64)base : 0;
#else
    return sk;
#endif
}

// socket_id() of a socket that a program without typed pointers meets as a number: the map
// value's address becomes a number too, copied out by the helper (as root may).
static __always_inline u64 socket_id_untyped(u64 sk)
{
#if DRUMS_ATTACH == ATTACH_TP_BTF
    int zero = 0;
    u64 *base = dropped.lookup(&zero);
    if (!base)
        return 0;
    u64 where = (u64)base, at = 0;
    bpf_probe_read_kernel(&at, sizeof(at), &where);
    return sk - at;
#else
    return sk;
#endif
}

#if SOCKET_SLOTS > 1
// The slot a socket's entry goes in, whoever holds it. Fibonacci hashing: the product's upper
// bits mix all of the id's, whose lowest are the same for every socket of a slab.
static __always_inline struct socket_traffic_t *slot_of(u64 id)
{
    u32 slot = (u32)((id * 0x9E3779B97F4A7C15ULL) >> 32) & (SOCKET_SLOTS - 1);
    return socket_slots.lookup(&slot);
}
#endif

// The socket's entry, if it has one.
static __always_inline struct socket_traffic_t *socket_of(u64 id)
{
#if SOCKET_SLOTS > 1
    struct socket_traffic_t *s = slot_of(id);
    if (s && s->id == id)
        return s;
#endif
    return socket_traffic.lookup(&id);
}

// A socket's entry goes, and its counts to its owner: once, whichever of several CPUs find it over
// (1: this one).
static __always_inline int forget(u64 id, struct socket_traffic_t *s)
{
    struct socket_traffic_t gone = *s;  // a copy: a freed entry can be given to another socket at once
#if SOCKET_SLOTS > 1
    if (s->id) {
        // Claimed by zeroing its start (the agent waits for a slot that shows none: half made or
        // half given up), emptied, then given up (its owner last).
        u64 start = gone.process_start;
        if (!start || __sync_val_compare_and_swap(&s->process_start, start, 0) != start)
            return 0;
        gone = *s;  // with what was counted until the claim
        gone.process_start = start;
        __builtin_memset(s, 0, __builtin_offsetof(struct socket_traffic_t, id));
        __sync_val_compare_and_swap(&s->id, id, 0);
    } else
#endif
    if (socket_traffic.delete(&id) != 0)
        return 0;
    fold(gone.tgid, gone.process_start, gone.klass, &gone.t);
    mark_changed(id, 0);
    return 1;
}

// Whether the entry still holds the socket the agent named (see forget_gone); any, if it named none.
static __always_inline bool holds(struct socket_traffic_t *s, struct bpf_raw_tracepoint_args *named)
{
    return !named || (s->ino == named->args[1] && s->tgid == (u32)named->args[2]
                      && s->process_start == named->args[3]);
}

// Every entry of the socket goes (that `named` names, if any): two CPUs that made its first entry
// at once, as its slot was given up, may have made one in the slot and one in socket_traffic.
// 1 if this call folded counts into the owner's closed_traffic.
static __always_inline int forget_socket(u64 id, struct bpf_raw_tracepoint_args *named)
{
    int n = 0;
#if SOCKET_SLOTS > 1
    struct socket_traffic_t *s = slot_of(id);
    if (s && s->id == id && holds(s, named))
        n |= forget(id, s);
#endif
    struct socket_traffic_t *h = socket_traffic.lookup(&id);
    if (h && holds(h, named))
        n |= forget(id, h);
    return n;
}

static __always_inline u64 socket_ino(const int typed, u64 sk)
{
    u64 sock = 0, ino = 0;
    KREAD_AS(typed, sock, sk + SK_SOCKET_OFF);
    if (!sock)
        return 0;
    if (typed) {
        // The verifier checks each load against its struct, and the inode lies past struct socket
        // (in struct socket_alloc): it is reached through the socket's file instead.
        u64 file = 0, inode = 0;
        KREAD_AS(typed, file, sock + SOCKET_FILE_OFF);
        if (file)
            KREAD_AS(typed, inode, file + FILE_INODE_OFF);
        if (inode)
            KREAD_AS(typed, ino, inode + INODE_INO_OFF);
    } else {
        bpf_probe_read_kernel(&ino, sizeof(ino), (void *)(sock + SOCKET_INO_OFF));
    }
    return ino;
}

static __always_inline void read_identity(struct socket_traffic_t *s, u64 sk)
{
    read_endpoints(sk, &s->family, &s->netns, &s->lport, &s->rport, s->laddr, s->raddr);
    bpf_probe_read_kernel(&s->protocol, 2, (void *)(sk + SK_PROTOCOL_OFF));
    s->klass = classify(s->family, s->protocol);
}

// One call's counts, in a zeroed traffic_t.
static __always_inline void one_call(struct traffic_t *t, int ret, int is_send)
{
    if (ret < 0) {
        *(is_send ? &t->send_errors : &t->recv_errors) = 1;
    } else if (is_send) {
        t->sent_bytes = ret;
        t->sent_calls = 1;
    } else {
        t->recv_bytes = ret;
        t->recv_calls = 1;
    }
}

// A new entry for the socket, in its slot if that is free, else in socket_traffic; 0 if the map is full.
static __always_inline struct socket_traffic_t *make_entry(u64 id, struct socket_traffic_t *fresh)
{
#if SOCKET_SLOTS > 1
    struct socket_traffic_t *s = slot_of(id);
    if (s) {
        // Of two CPUs that make entries for two sockets of one free slot at once, one takes it.
        // Its counts are zero already: a CPU that makes this socket's entry at the same moment
        // finds the slot taken by this very socket and counts into it, which no write here undoes.
        u64 was = __sync_val_compare_and_swap(&s->id, 0, id);
        if (was == 0) {
            __builtin_memcpy(s, fresh, __builtin_offsetof(struct socket_traffic_t, t));
            // Made, for the agent, when its start shows (an atomic: after the rest).
            __sync_val_compare_and_swap(&s->process_start, 0, fresh->process_start);
            return s;
        }
        if (was == id)
            return s;
    }
#endif
    if (socket_traffic.insert(&id, fresh) == 0)
        return socket_traffic.lookup(&id);
    count_drop(DROP_SOCKET);
    return 0;
}

// The socket's entry, created at first use. A call on a socket that gets none (see below) is
// folded into the calling process's closed_traffic here.
static __always_inline struct socket_traffic_t *socket_entry(const int typed, u64 sk, u64 id, int ret, int is_send)
{
    struct socket_traffic_t *s = socket_of(id);
    if (s) {
        // TCP entries are deleted when the connection closes, and any at the address of a socket
        // that connects, listens or is accepted (on_tcp_state); other sockets are freed without a
        // tracepoint, so a recycled struct sock is recognised by its new inode.
        if (s->klass == CLASS_TCP)
            return s;
        u64 ino = socket_ino(typed, sk);
        if (ino == s->ino)
            return s;
        forget_socket(id, 0);  // whether or not a fresh entry takes its place
    }
    struct socket_traffic_t fresh = {};
    fresh.tgid = bpf_get_current_pid_tgid() >> 32;
    fresh.process_start = process_start_as(typed, CURRENT_TASK_AS(typed));
    fresh.ino = socket_ino(typed, sk);
    read_identity(&fresh, sk);
    // A TCP socket in CLOSE (never connected, or reset) would never pass CLOSE again to free its
    // entry, and its struct sock would pass the entry to the next socket: it gets none.
    u8 state = 0;
    if (fresh.klass == CLASS_TCP)
        KREAD_AS(typed, state, sk + SK_STATE_OFF);
    if (state != TCP_CLOSE) {
        s = make_entry(id, &fresh);
        if (s) {
            if (fresh.klass == CLASS_TCP)
                KREAD_AS(typed, state, sk + SK_STATE_OFF);
            if (state != TCP_CLOSE)
                return s;
            // A CLOSE that came on another CPU after the state was read found no entry to forget:
            // this one goes now, as it would have then, and the call's counts with it. (The
            // tracepoint comes just before the state is stored: an entry made in between stays,
            // and the agent forgets it once idle, finding its socket gone.)
            forget_socket(id, 0);
        }
    }
    one_call(&fresh.t, ret, is_send);
    fold(fresh.tgid, fresh.process_start, fresh.klass, &fresh.t);
    return 0;
}

// One call on the socket `sk` (whose id is `id`): `typed` where the program sees typed pointers.
static __always_inline void count_as(const int typed, u64 sk, u64 id, int ret, int flags, int is_send)
{
    if (ret == -EAGAIN || ret == -EINTR || (ret <= -ERESTARTSYS && ret >= -ERESTART_RESTARTBLOCK))
        return;  // non-blocking polls and interrupted or restarted calls are not failures of the socket
    if (!is_send && ret >= 0 && (flags & MSG_PEEK))
        return;  // the bytes will be counted when they are really read
    struct socket_traffic_t *s = id ? socket_entry(typed, sk, id, ret, is_send) : 0;
    if (!s)
        return;
    // Atomic: the threads of a process, and processes that share a socket, call at once.
    if (ret < 0) {
        __sync_fetch_and_add(is_send ? &s->t.send_errors : &s->t.recv_errors, 1);
    } else if (is_send) {
        __sync_fetch_and_add(&s->t.sent_bytes, ret);
        __sync_fetch_and_add(&s->t.sent_calls, 1);
    } else {
        __sync_fetch_and_add(&s->t.recv_bytes, ret);
        __sync_fetch_and_add(&s->t.recv_calls, 1);
    }
    // Marked after its counts: the agent may take the mark and look the entry up at any moment, and
    // a count made after that look would wait for the socket's next call to be marked again.
    mark_changed(id, &s->marked);
}

static __always_inline void count(u64 sk, int ret, int flags, int is_send)
{
    count_as(TYPED, sk, socket_id(sk), ret, flags, is_send);
}

// A struct socket's sock.
static __always_inline u64 sock_of(u64 sock)
{
    u64 sk = 0;
    if (sock)
        bpf_probe_read_kernel(&sk, sizeof(sk), (void *)(sock + SOCKET_SK_OFF));
    return sk;
}

#if DRUMS_ATTACH == ATTACH_RAW_TRACEPOINT || DRUMS_ATTACH == ATTACH_TP_BTF
// sock:sock_send_length / sock_recv_length (sk, ret, flags), kernel >= 6.6.
int on_send(struct bpf_raw_tracepoint_args *ctx)
{
    count(ctx->args[0], (int)ctx->args[1], (int)ctx->args[2], 1);
    return 0;
}

int on_recv(struct bpf_raw_tracepoint_args *ctx)
{
    count(ctx->args[0], (int)ctx->args[1], (int)ctx->args[2], 0);
    return 0;
}
#endif

// splice(2) from a TCP or unix stream socket hands its bytes to the pipe without sock_recvmsg, so
// without sock_recv_length: on the tracepoint paths SPLICE_READS says what counts them, a call per
// splice. A socket of another kind is read through sock_recvmsg, and a splice or sendfile into a
// socket sends through sock_sendmsg (Linux >= 6.5): those the tracepoints count. io_uring's splice
// is no syscall.
#define SPLICE_BY_KPROBES 1   // kprobes on tcp_splice_read and unix_stream_splice_read
#define SPLICE_BY_SYSCALLS 2  // the syscall's tracepoints, which slow every system call on the host
#ifndef SPLICE_READS
#define SPLICE_READS 0  // not counted
#endif
#define ON_TRACEPOINTS (DRUMS_ATTACH == ATTACH_RAW_TRACEPOINT || DRUMS_ATTACH == ATTACH_TP_BTF)

#if ON_TRACEPOINTS && SPLICE_READS == SPLICE_BY_SYSCALLS
BPF_HASH(splicing, u32, u64, 4096);  // thread -> the socket it splices from, while it does

// The sock of the running task's file descriptor `fd` if it is a TCP or unix stream socket, else 0.
static __always_inline u64 spliced_socket(u64 fd)
{
    u64 task = bpf_get_current_task(), files = 0, fdt = 0, fds = 0, file = 0, inode = 0;
    u32 max = 0;
    u16 mode = 0, family = 0, protocol = 0, type = 0;
    bpf_probe_read_kernel(&files, sizeof(files), (void *)(task + TASK_FILES_OFF));
    if (files)
        bpf_probe_read_kernel(&fdt, sizeof(fdt), (void *)(files + FILES_FDT_OFF));
    if (!fdt)
        return 0;
    bpf_probe_read_kernel(&max, sizeof(max), (void *)(fdt + FDTABLE_MAX_FDS_OFF));
    bpf_probe_read_kernel(&fds, sizeof(fds), (void *)(fdt + FDTABLE_FD_OFF));
    if (fd >= max || !fds)
        return 0;
    bpf_probe_read_kernel(&file, sizeof(file), (void *)(fds + fd * 8));
    if (file)
        bpf_probe_read_kernel(&inode, sizeof(inode), (void *)(file + FILE_INODE_OFF));
    if (inode)
        bpf_probe_read_kernel(&mode, sizeof(mode), (void *)(inode + INODE_MODE_OFF));
    if ((mode & 0170000) != 0140000)  // S_IFSOCK
        return 0;
    u64 sock = 0;
    bpf_probe_read_kernel(&sock, sizeof(sock), (void *)(file + FILE_PRIVATE_OFF));
    u64 sk = sock_of(sock);
    if (!sk)
        return 0;
    bpf_probe_read_kernel(&family, sizeof(family), (void *)(sk + SK_FAMILY_OFF));
    bpf_probe_read_kernel(&protocol, sizeof(protocol), (void *)(sk + SK_PROTOCOL_OFF));
    bpf_probe_read_kernel(&type, sizeof(type), (void *)(sk + SK_TYPE_OFF));
    if (family == AF_UNIX ? type == SOCK_STREAM : classify(family, protocol) == CLASS_TCP)
        return sk;
    return 0;
}

// syscalls:sys_enter_splice (fd_in, off_in, fd_out, off_out, len, flags) and its exit.
int on_splice_enter(struct syscall_enter_t *ctx)
{
    u64 sk = spliced_socket(ctx->args[0]);
    if (sk) {
        u32 tid = (u32)bpf_get_current_pid_tgid();
        splicing.update(&tid, &sk);
    }
    return 0;
}

int on_splice_exit(struct syscall_exit_t *ctx)
{
    u32 tid = (u32)bpf_get_current_pid_tgid();
    u64 *from = splicing.lookup(&tid);
    if (!from)
        return 0;
    u64 sk = *from;
    splicing.delete(&tid);
    count_as(0, sk, socket_id_untyped(sk), (int)ctx->ret, 0, 0);
    return 0;
}
#endif

#if DRUMS_ATTACH == ATTACH_FENTRY || DRUMS_ATTACH == ATTACH_KPROBE
// Before Linux 6.6 the programs take what sock_sendmsg and sock_recvmsg hand each family's
// sendmsg and recvmsg (inet, inet6 and the unix ones), where the tracepoints later came: the same
// calls, the same results, every socket family the agent names. Besides: what splice(2) takes
// from a TCP or unix stream socket (their splice_read), and before Linux 6.5 what sendfile and
// splice hand a socket (its sendpage, a call per page).
#endif

#if DRUMS_ATTACH == ATTACH_FENTRY
// fexit sees arguments and return value together: no per-call state to keep. (bcc cannot take
// programs made by a macro of ours: each is written out. The seqpacket calls go through the
// datagram ones, so are not hooked twice.)
KRETFUNC_PROBE(inet_sendmsg, struct socket *sock, struct msghdr *msg, size_t size, int ret)
{
    count(sock_of((u64)sock), ret, 0, 1);
    return 0;
}

KRETFUNC_PROBE(inet6_sendmsg, struct socket *sock, struct msghdr *msg, size_t size, int ret)
{
    count(sock_of((u64)sock), ret, 0, 1);
    return 0;
}

KRETFUNC_PROBE(unix_stream_sendmsg, struct socket *sock, struct msghdr *msg, size_t size, int ret)
{
    count(sock_of((u64)sock), ret, 0, 1);
    return 0;
}

KRETFUNC_PROBE(unix_dgram_sendmsg, struct socket *sock, struct msghdr *msg, size_t size, int ret)
{
    count(sock_of((u64)sock), ret, 0, 1);
    return 0;
}

KRETFUNC_PROBE(inet_recvmsg, struct socket *sock, struct msghdr *msg, size_t size, int flags, int ret)
{
    count(sock_of((u64)sock), ret, flags, 0);
    return 0;
}

KRETFUNC_PROBE(inet6_recvmsg, struct socket *sock, struct msghdr *msg, size_t size, int flags, int ret)
{
    count(sock_of((u64)sock), ret, flags, 0);
    return 0;
}

KRETFUNC_PROBE(unix_stream_recvmsg, struct socket *sock, struct msghdr *msg, size_t size, int flags, int ret)
{
    count(sock_of((u64)sock), ret, flags, 0);
    return 0;
}

KRETFUNC_PROBE(unix_dgram_recvmsg, struct socket *sock, struct msghdr *msg, size_t size, int flags, int ret)
{
    count(sock_of((u64)sock), ret, flags, 0);
    return 0;
}

KRETFUNC_PROBE(tcp_splice_read, struct socket *sock, loff_t *ppos, struct pipe_inode_info *pipe, size_t len,
               unsigned int flags, ssize_t ret)
{
    count(sock_of((u64)sock), (int)ret, 0, 0);
    return 0;
}

KRETFUNC_PROBE(unix_stream_splice_read, struct socket *sock, loff_t *ppos, struct pipe_inode_info *pipe, size_t len,
               unsigned int flags, ssize_t ret)
{
    count(sock_of((u64)sock), (int)ret, 0, 0);
    return 0;
}

#ifdef HAS_SENDPAGE  // Linux < 6.5
KRETFUNC_PROBE(inet_sendpage, struct socket *sock, struct page *page, int offset, size_t size, int flags,
               ssize_t ret)
{
    count(sock_of((u64)sock), (int)ret, 0, 1);
    return 0;
}
KRETFUNC_PROBE(unix_stream_sendpage, struct socket *sock, struct page *page, int offset, size_t size, int flags,
               ssize_t ret)
{
    count(sock_of((u64)sock), (int)ret, 0, 1);
    return 0;
}
#endif

#endif

#if DRUMS_ATTACH == ATTACH_KPROBE || (ON_TRACEPOINTS && SPLICE_READS == SPLICE_BY_KPROBES)
#include <uapi/linux/ptrace.h>  // struct pt_regs for PT_REGS_RC

// A kprobe sees the arguments, its kretprobe the result: the socket waits here in between. One
// call per thread at a time: a socket call does not nest another on the same thread.
struct call_t {
    u64 sk;
    int flags;
};
BPF_HASH(calls, u32, struct call_t, 4096);

static __always_inline void remember(u64 sock, int flags)
{
    u32 tid = (u32)bpf_get_current_pid_tgid();
    struct call_t c = {.sk = sock_of(sock), .flags = flags};
    calls.update(&tid, &c);
}

static __always_inline void finish(struct pt_regs *ctx, int is_send)
{
    u32 tid = (u32)bpf_get_current_pid_tgid();
    struct call_t *c = calls.lookup(&tid);
    if (!c)
        return;
    struct call_t got = *c;
    calls.delete(&tid);
    count_as(0, got.sk, socket_id_untyped(got.sk), (int)PT_REGS_RC(ctx), got.flags, is_send);
}

int enter_tcp_splice_read(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_tcp_splice_read(struct pt_regs *ctx)
{
    finish(ctx, 0);
    return 0;
}

int enter_unix_stream_splice_read(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_unix_stream_splice_read(struct pt_regs *ctx)
{
    finish(ctx, 0);
    return 0;
}

#endif

#if DRUMS_ATTACH == ATTACH_KPROBE

int enter_inet_sendmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_inet_sendmsg(struct pt_regs *ctx)
{
    finish(ctx, 1);
    return 0;
}

int enter_inet6_sendmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_inet6_sendmsg(struct pt_regs *ctx)
{
    finish(ctx, 1);
    return 0;
}

int enter_unix_stream_sendmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_unix_stream_sendmsg(struct pt_regs *ctx)
{
    finish(ctx, 1);
    return 0;
}

int enter_unix_dgram_sendmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_unix_dgram_sendmsg(struct pt_regs *ctx)
{
    finish(ctx, 1);
    return 0;
}

int enter_inet_recvmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), (int)PT_REGS_PARM4(ctx));
    return 0;
}

int exit_inet_recvmsg(struct pt_regs *ctx)
{
    finish(ctx, 0);
    return 0;
}

int enter_inet6_recvmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), (int)PT_REGS_PARM4(ctx));
    return 0;
}

int exit_inet6_recvmsg(struct pt_regs *ctx)
{
    finish(ctx, 0);
    return 0;
}

int enter_unix_stream_recvmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), (int)PT_REGS_PARM4(ctx));
    return 0;
}

int exit_unix_stream_recvmsg(struct pt_regs *ctx)
{
    finish(ctx, 0);
    return 0;
}

int enter_unix_dgram_recvmsg(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), (int)PT_REGS_PARM4(ctx));
    return 0;
}

int exit_unix_dgram_recvmsg(struct pt_regs *ctx)
{
    finish(ctx, 0);
    return 0;
}

int enter_inet_sendpage(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_inet_sendpage(struct pt_regs *ctx)
{
    finish(ctx, 1);
    return 0;
}

int enter_unix_stream_sendpage(struct pt_regs *ctx)
{
    remember(PT_REGS_PARM1(ctx), 0);
    return 0;
}

int exit_unix_stream_sendpage(struct pt_regs *ctx)
{
    finish(ctx, 1);
    return 0;
}

#endif

// sock:inet_sock_set_state (sk, oldstate, newstate): a TCP socket that reaches CLOSE is done;
// its entry goes before the struct sock can be reused, and its counts to its owner. One that
// connects, listens or is made by a listener for a new connection (SYN_RECV from LISTEN; not a
// simultaneous open, from SYN_SENT) begins anew: an entry at its address is an earlier socket's
// that its CLOSE did not find (made by a call that raced with it, say), and the new socket would
// count into it as its own (socket_entry does not check a TCP socket's inode).
int on_tcp_state(struct bpf_raw_tracepoint_args *ctx)
{
    int old = (int)ctx->args[1], state = (int)ctx->args[2];
    if (state != TCP_CLOSE && state != TCP_SYN_SENT && state != TCP_LISTEN
        && !(state == TCP_SYN_RECV && old != TCP_SYN_SENT))
        return 0;
    u64 id = socket_id(ctx->args[0]);
    if (id)
        forget_socket(id, 0);
    return 0;
}

// Run by the agent (BPF_PROG_TEST_RUN; args: the socket's id, inode, owner's PID and start) for
// a socket that it found gone (its owner ended, or holds it no more) but the kernel freed without a
// tracepoint: forgotten as a closed TCP socket is, if its entry is still that socket's. Returns 1 if
// this run folded its counts into its owner's closed_traffic.
int forget_gone(struct bpf_raw_tracepoint_args *ctx)
{
    return forget_socket(ctx->args[0], ctx);
}

