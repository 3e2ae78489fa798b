// Shared by every Drums BPF program: attach path numbers, the ABI constants the programs use, and
// the maps of dropped events and change marks. The loader writes this file into each program's
// text (drums/kernel/loader.py): bcc rewrites map calls only in the text it compiles.
// Constants are spelled out rather than taken from headers that may belong to another kernel;
// every one of them is part of the stable user-space ABI.
#ifndef DRUMS_H
#define DRUMS_H

#define ATTACH_RAW_TRACEPOINT 1
#define ATTACH_FENTRY 2
#define ATTACH_KPROBE 3
#define ATTACH_TRACEPOINT 4  // perf-event tracepoints, pinned as BPF links
#define ATTACH_UPROBE 5
#define ATTACH_TP_BTF 6  // raw tracepoints whose programs see typed arguments (drums/kernel/tracing.py)

// Loads a scalar or pointer field of a kernel struct: directly where the program runs as a BTF
// tracepoint program (the verifier knows the pointer's type and checks the load), else through
// bpf_probe_read_kernel, a helper call that costs as much as the rest of a small program.
// CURRENT_TASK_AS(typed) is the running task, typed likewise where it can be (Linux >= 5.11).
// The _AS forms take that as a constant argument instead, for a program of another type in a
// tp_btf build (a syscall tracepoint's sees no typed pointers).
#define TYPED (DRUMS_ATTACH == ATTACH_TP_BTF)
#define KREAD_AS(typed, dst, addr)                                                \
    do {                                                                          \
        if (typed)                                                                \
            (dst) = *(typeof(dst) *)(addr);                                       \
        else                                                                      \
            bpf_probe_read_kernel(&(dst), sizeof(dst), (void *)(addr));          \
    } while (0)
#define CURRENT_TASK_AS(typed) ((typed) ? (u64)bpf_get_current_task_btf() : bpf_get_current_task())
#define KREAD(dst, addr) KREAD_AS(TYPED, dst, addr)

// Hides a value's range from the compiler, so that the bounds check or mask written after it stays
// on the register the access uses: Linux 6.1's verifier loses a bound once the compiler spills the
// checked copy, or drops a mask it knows changes nothing.
#define OPAQUE(v) asm volatile("" : "+r"(v))

#ifndef AF_UNIX
#define AF_UNIX 1
#endif
#ifndef AF_INET
#define AF_INET 2
#endif
#ifndef AF_INET6
#define AF_INET6 10
#endif
#ifndef SOCK_STREAM
#define SOCK_STREAM 1
#endif
#ifndef IPPROTO_TCP
#define IPPROTO_TCP 6
#endif
#ifndef IPPROTO_UDP
#define IPPROTO_UDP 17
#endif
#ifndef IPPROTO_UDPLITE
#define IPPROTO_UDPLITE 136
#endif
#ifndef EINTR
#define EINTR 4
#endif
#ifndef EAGAIN
#define EAGAIN 11
#endif
// The kernel's restart codes (ERESTARTSYS to ERESTART_RESTARTBLOCK): a call stopped or interrupted
// by a signal is restarted, or returns EINTR; no application ever sees them.
#define ERESTARTSYS 512
#define ERESTART_RESTARTBLOCK 516
#ifndef MSG_PEEK
#define MSG_PEEK 2
#endif
#ifndef TCP_SYN_SENT
#define TCP_SYN_SENT 2
#endif
#ifndef TCP_SYN_RECV
#define TCP_SYN_RECV 3
#endif
#ifndef TCP_CLOSE
#define TCP_CLOSE 7
#endif
#ifndef TCP_LISTEN
#define TCP_LISTEN 10
#endif

struct sock;
struct msghdr;
struct socket;
struct page;
struct pipe_inode_info;

#ifdef SK_FAMILY_OFF
// Family, network namespace, ports (host order) and addresses of a socket; IPv4 addresses fill
// the first 4 bytes. Offsets come from BTF (-D flags).
static __always_inline void read_endpoints(u64 sk, u16 *family, u32 *netns, u16 *lport, u16 *rport,
                                           u8 *laddr, u8 *raddr)
{
    u64 net = 0;
    u16 dport = 0;
    bpf_probe_read_kernel(family, 2, (void *)(sk + SK_FAMILY_OFF));
    bpf_probe_read_kernel(lport, 2, (void *)(sk + SK_NUM_OFF));
    bpf_probe_read_kernel(&dport, 2, (void *)(sk + SK_DPORT_OFF));
    *rport = ntohs(dport);
    bpf_probe_read_kernel(&net, sizeof(net), (void *)(sk + SK_NET_OFF));
    if (net)
        bpf_probe_read_kernel(netns, 4, (void *)(net + NET_INUM_OFF));
    if (*family == AF_INET) {
        bpf_probe_read_kernel(laddr, 4, (void *)(sk + SK_RCV_SADDR_OFF));
        bpf_probe_read_kernel(raddr, 4, (void *)(sk + SK_DADDR_OFF));
    } else if (*family == AF_INET6) {
        bpf_probe_read_kernel(laddr, 16, (void *)(sk + SK_V6_RCV_SADDR_OFF));
        bpf_probe_read_kernel(raddr, 16, (void *)(sk + SK_V6_DADDR_OFF));
    }
}
#endif

// The process a task belongs to if the task is its leader (a process being forked or reaped), else 0.
// Before Linux 5.12 a thread that execs shares the old leader's PID until that leader is released:
// only the task that is its own group leader counts.
#ifdef TASK_GROUP_LEADER_OFF
static __always_inline u32 leader_tgid(u64 task)
{
    u32 pid = 0, tgid = 0;
    u64 leader = 0;
    KREAD(pid, task + TASK_PID_OFF);
    KREAD(tgid, task + TASK_TGID_OFF);
    KREAD(leader, task + TASK_GROUP_LEADER_OFF);
    return pid == tgid && leader == task ? tgid : 0;
}
#endif

// When a task's process started: with the PID, what tells a process from a later one that got
// its PID. Needs TASK_GROUP_LEADER_OFF and TASK_START_TIME_OFF.
#ifdef TASK_GROUP_LEADER_OFF
static __always_inline u64 process_start_as(const int typed, u64 task)
{
    u64 leader = 0, start = 0;
    KREAD_AS(typed, leader, task + TASK_GROUP_LEADER_OFF);
    if (leader)
        KREAD_AS(typed, start, leader + TASK_START_TIME_OFF);
    return start;
}
#define process_start(task) process_start_as(TYPED, task)
#endif

// Events lost to a full map, by reason (the program's DROPS of them, numbered by its DROP_*
// constants): every program that has them declares DROPS before including this file.
#ifdef DROPS
BPF_ARRAY(dropped, u64, DROPS);

static __always_inline void count_drop(int which)
{
    u64 *d = dropped.lookup(&which);
    if (d)
        __sync_fetch_and_add(d, 1);
}
#endif

// Which entries of a probe's main map changed since the agent last read them, so that a scrape
// reads those and not the thousands that sat idle (drums/probes/entries.py, Marked): for programs
// that declare their map's key type as MARKED_KEY. The agent moves the generation on at each read
// and takes the keys marked in the one before; an entry is marked once per generation (its first
// change, or when it is gone: `marked` 0), in the set of the generation's parity, while the agent
// empties the other. generation[0]: the generation; [1]: marks lost to a full set (the agent then
// reads the map whole).
#ifdef MARKED_KEY
BPF_ARRAY(generation, u64, 2);
BPF_HASH(changed_even, MARKED_KEY, u8, 16384);
BPF_HASH(changed_odd, MARKED_KEY, u8, 16384);

static __always_inline void mark_changed(MARKED_KEY key, u64 *marked)
{
    int zero = 0, lost = 1;
    u64 *g = generation.lookup(&zero);
    if (!g || (marked && *marked == *g + 1))
        return;
    u64 gen = *g;
    if (marked)
        *marked = gen + 1;  // + 1: an entry made with marked 0 is not yet marked in generation 0
    u8 yes = 1;
    if (gen & 1 ? changed_odd.update(&key, &yes) : changed_even.update(&key, &yes)) {
        u64 *n = generation.lookup(&lost);
        if (n)
            __sync_fetch_and_add(n, 1);
    }
}
#endif

// The tracepoint records of syscalls:sys_enter_* and sys_exit_* (stable since they exist).
struct syscall_enter_t {
    u64 common;
    s64 nr;
    u64 args[6];
};

struct syscall_exit_t {
    u64 common;
    s64 nr;
    s64 ret;
};

#endif
