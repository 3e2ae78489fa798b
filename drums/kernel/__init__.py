"""What Drums reads of the kernel: BTF, features, the BPF loader, pinned maps, sock_diag."""

TRACEFS = "/sys/kernel/tracing"  # where tracefs is mounted (scripts/setup.sh mounts it)
