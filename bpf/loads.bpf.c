// When a process may have mapped a new shared library: glibc's and musl's dynamic linkers call
// _dl_debug_state (the hook debuggers put a breakpoint on) once the libraries an executable links
// are mapped at its start, and at each dlopen and dlclose. The agent then reads the process's
// memory map and puts its uprobes on a librcl.so it has not seen before the process gets to
// publish, so per-topic counts start with the first message whenever a node loads ROS 2, however
// rarely the agent is scraped.
//
// The call is rare (a process start, a library load): nothing here runs on a hot path.
#include <uapi/linux/ptrace.h>
#define DROPS 1
#include "drums.h"

// The processes to look at, a u32 each (16 bytes a record with its header): 2,048 records, far
// more than processes start while the agent reads one memory map. When it is full the agent
// reads every process's map again.
BPF_RINGBUF_OUTPUT(loads, 8);

int on_debug_state(struct pt_regs *ctx)
{
    u32 tgid = bpf_get_current_pid_tgid() >> 32;
    if (loads.ringbuf_output(&tgid, sizeof(tgid), 0))
        count_drop(0);
    return 0;
}
