// TCP health: retransmitted segments, resets and state changes, per connection and per host.
// The kernel keeps no per-connection count of these; the smoothed RTT it does keep is read by the
// agent from tcp_info. All hooks are on slow paths, never on the data path.
//
// Offsets of struct sock fields come from BTF.
#define DROPS 2
#define MARKED_KEY u64
#include "drums.h"

#define TCP_STATES 13  // TCP_ESTABLISHED (1) .. TCP_NEW_SYN_RECV (12)

struct tcp_conn_t {
    u32 netns;
    u16 family;
    u16 lport;        // host byte order
    u16 rport;        // host byte order
    u16 state;        // TCP_CLOSE: closed, kept until the agent has exported it once
    u8 laddr[16];
    u8 raddr[16];
    u64 retransmits;  // the kernel's own count (tcpi_total_retrans), as of the last retransmit
    u64 state_changes;
    u64 resets_sent;
    u64 resets_received;
    u64 marked;       // the generation in which the connection was last marked changed (see below)
};

// Host-wide totals: never deleted, so they never go backwards when connections close.
struct tcp_totals_t {
    u64 retransmits;
    u64 resets_sent;
    u64 resets_received;
    u64 entered[TCP_STATES];  // transitions into each state
};

// Sized like the sockets probe's map. Closed connections stay until the agent exports them (a
// reset comes with or right after the close); LRU, so that without an agent the oldest go first.
BPF_TABLE("lru_hash", u64, struct tcp_conn_t, tcp_conns, 32768);
// Added to atomically although per CPU: under PREEMPT_RT a program runs with migration, not
// preemption, disabled, and another program on its CPU can come between a load and its store.
BPF_PERCPU_ARRAY(tcp_totals, struct tcp_totals_t, 1);

static __always_inline void read_identity(struct tcp_conn_t *c, u64 sk)
{
    read_endpoints(sk, &c->family, &c->netns, &c->lport, &c->rport, c->laddr, c->raddr);
}

static __always_inline struct tcp_conn_t *conn_entry(u64 sk)
{
    struct tcp_conn_t *c = tcp_conns.lookup(&sk);
    if (c)
        return c;
    struct tcp_conn_t fresh = {};
    read_identity(&fresh, sk);
    // What a connection older than the entry retransmitted is in its own count from the start,
    // so that its next retransmit adds to the host total only itself.
    u32 total = 0;
    bpf_probe_read_kernel(&total, 4, (void *)(sk + TP_TOTAL_RETRANS_OFF));
    fresh.retransmits = total;
    if (tcp_conns.insert(&sk, &fresh) != 0) {
        count_drop(0);
        return 0;
    }
    return tcp_conns.lookup(&sk);
}

static __always_inline struct tcp_totals_t *totals(void)
{
    int zero = 0;
    return tcp_totals.lookup(&zero);
}

// sock:inet_sock_set_state (sk, oldstate, newstate)
int on_state(struct bpf_raw_tracepoint_args *ctx)
{
    u64 sk = ctx->args[0];
    u32 newstate = (u32)ctx->args[2];
    u16 protocol = 0;
    bpf_probe_read_kernel(&protocol, 2, (void *)(sk + SK_PROTOCOL_OFF));
    if (protocol != IPPROTO_TCP)
        return 0;  // the tracepoint also fires for SCTP and MPTCP subflows' parents
    struct tcp_totals_t *tot = totals();
    u64 state = newstate;
    OPAQUE(state);  // one register checked and used: LLVM 19 checked one copy and indexed with another
    if (tot && state < TCP_STATES)
        __sync_fetch_and_add(&tot->entered[state], 1);
    struct tcp_conn_t *c = tcp_conns.lookup(&sk);
    if (c && c->state == TCP_CLOSE && newstate != TCP_CLOSE) {
        // The struct sock now holds a new connection (the kernel reuses them at once): the closed
        // one moves to a key of its own until the agent has exported it: odd (a struct sock is
        // aligned), made of the time and the CPU, so no two moved entries that live at once share
        // it (a counter's fetch-and-add would need Linux 5.12).
        u64 moved = bpf_ktime_get_ns() << 12 | (bpf_get_smp_processor_id() & 0x7ff) << 1 | 1;
        struct tcp_conn_t closed = *c;
        closed.marked = 0;
        if (tcp_conns.update(&moved, &closed) == 0)
            mark_changed(moved, 0);
        tcp_conns.delete(&sk);
        mark_changed(sk, 0);  // whether or not a fresh entry takes its place
        c = 0;
    }
    if (!c) {
        if (newstate == TCP_CLOSE)
            return 0;
        c = conn_entry(sk);
        if (!c)
            return 0;
    }
    // A connecting socket enters SYN_SENT before it has a local port: refresh the identity, but
    // not at CLOSE, where the kernel has already released the port.
    if (newstate != TCP_CLOSE)
        read_identity(c, sk);
    c->state = newstate;
    __sync_fetch_and_add(&c->state_changes, 1);
    mark_changed(sk, &c->marked);
    return 0;
}

// tcp:tcp_retransmit_skb (sk, skb[, err])
// The kernel counts segments, not events: one retransmit of a GSO skb is several, and an attempt
// that fails after it was counted (the qdisc dropped it) is counted all the same; one that found
// the segment still in a host queue is not. So the connection takes the kernel's own count
// (tp->total_retrans, which the event follows), and the host what that count moved by.
int on_retransmit(struct bpf_raw_tracepoint_args *ctx)
{
    u64 sk = ctx->args[0];
    u32 total = 0;
    bpf_probe_read_kernel(&total, 4, (void *)(sk + TP_TOTAL_RETRANS_OFF));
    u64 moved = 0;
    struct tcp_conn_t *c = tcp_conns.lookup(&sk);
    if (c) {
        moved = (u32)(total - (u32)c->retransmits);
        __sync_fetch_and_add(&c->retransmits, moved);
    } else {
        // A connection older than the agent (or one a full map made it forget): what it
        // retransmitted before is in its own count, but only this attempt in the host's.
#ifdef RETRANSMIT_HAS_ERR
        moved = (int)ctx->args[2] == 0;
#else
        moved = 1;
#endif
        c = conn_entry(sk);
    }
    if (c)
        mark_changed(sk, &c->marked);
    struct tcp_totals_t *tot = totals();
    if (tot)
        __sync_fetch_and_add(&tot->retransmits, moved);
    return 0;
}

// tcp:tcp_retransmit_synack (sk, req): a listener's SYN-ACK sent again, which the kernel counts in
// its retransmitted segments (tcp_rtx_synack) though no connection has it yet: the host's alone.
int on_retransmit_synack(struct bpf_raw_tracepoint_args *ctx)
{
    struct tcp_totals_t *tot = totals();
    if (tot)
        __sync_fetch_and_add(&tot->retransmits, 1);
    return 0;
}

static __always_inline void count_reset(u64 sk, int sent)
{
    struct tcp_totals_t *tot = totals();
    if (tot) {
        __sync_fetch_and_add(sent ? &tot->resets_sent : &tot->resets_received, 1);
    }
    if (!sk)
        return;  // a reset answering a segment for no socket
    struct tcp_conn_t *c = tcp_conns.lookup(&sk);
    if (c) {
        __sync_fetch_and_add(sent ? &c->resets_sent : &c->resets_received, 1);
        mark_changed(sk, &c->marked);
    }
}

// tcp:tcp_send_reset (sk, skb[, reason])
int on_send_reset(struct bpf_raw_tracepoint_args *ctx)
{
    count_reset(ctx->args[0], 1);
    return 0;
}

// tcp:tcp_receive_reset (sk)
int on_receive_reset(struct bpf_raw_tracepoint_args *ctx)
{
    count_reset(ctx->args[0], 0);
    return 0;
}
