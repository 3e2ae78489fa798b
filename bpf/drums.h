// Shared by every Drums BPF program: attach path numbers and the ABI constants the programs use.
// Constants are spelled out rather than taken from headers that may belong to another kernel;
// every one of them is part of the stable user-space ABI.
#ifndef DRUMS_H
#define DRUMS_H

#define ATTACH_RAW_TRACEPOINT 1
#define ATTACH_FENTRY 2
#define ATTACH_KPROBE 3

#ifndef AF_UNIX
#define AF_UNIX 1
#endif
#ifndef AF_INET
#define AF_INET 2
#endif
#ifndef AF_INET6
#define AF_INET6 10
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
#ifndef MSG_PEEK
#define MSG_PEEK 2
#endif
#ifndef TCP_CLOSE
#define TCP_CLOSE 7
#endif

struct sock;
struct msghdr;

#endif
