"""Socket addresses as users read them: 127.0.0.1:80, [::1]:80."""
from __future__ import annotations

import ipaddress

AF_INET, AF_INET6 = 2, 10


def endpoint(family: int, raw: bytes, port: int) -> str:
    """Format a kernel address (4 or 16 bytes, network order) and a host-order port."""
    if family == AF_INET:
        return f"{ipaddress.IPv4Address(raw[:4])}:{port}"
    if family == AF_INET6:
        addr = ipaddress.IPv6Address(raw[:16])
        mapped = addr.ipv4_mapped
        return f"{mapped}:{port}" if mapped else f"[{addr}]:{port}"
    return ""
