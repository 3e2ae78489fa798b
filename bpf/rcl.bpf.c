// Messages published and taken per ROS 2 publisher and subscription, counted by uprobes on
// librcl's rcl_publish* and rcl_take* functions. On one host Fast DDS moves samples over shared
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
// The subscription a thread passed to rcl_take, kept until it returns. Task-local storage, not a
// hash keyed by thread: a hash update costs about 0.5 us here, where this is a pointer lookup.
BPF_TASK_STORAGE(takes, u64);
BPF_ARRAY(dropped, u64, 2);

static __always_inline void count_drop(int which)
{
    u64 *d = dropped.lookup(&which);
    if (d)
        __sync_fetch_and_add(d, 1);
}

static __always_inline void count(u32 op, u64 handle)
{
    struct handle_key_t key = {.tgid = bpf_get_current_pid_tgid() >> 32, .op = op, .handle = handle};
    u64 zero = 0;
    u64 *n = handles.lookup_or_try_init(&key, &zero);
    if (n)
        __sync_fetch_and_add(n, 1);
    else
        count_drop(1);
}

int on_publish(struct pt_regs *ctx)
{
    count(PUBLISHED, PT_REGS_PARM1(ctx));
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
    if (PT_REGS_RC(ctx) == 0)
        count(TAKEN, h);
    return 0;
}
