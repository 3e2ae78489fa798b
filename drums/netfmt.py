"""Socket addresses as users read them: 127.0.0.1:80, [::1]:80."""
from __future__ import annotations

import socket
from functools import lru_cache

AF_INET, AF_INET6 = 2, 10
_V4_MAPPED = b"\0" * 10 + b"\xff\xff"


@lru_cache(maxsize=65536)  # the same few addresses come back at every collect
def endpoint(family: int, raw: bytes, port: int) -> str:
    """Format a kernel address (4 or 16 bytes, network order) and a host-order port."""
    if family == AF_INET:
        return f"{socket.inet_ntop(socket.AF_INET, raw[:4])}:{port}"
    if family == AF_INET6:
        if raw[:12] == _V4_MAPPED:
            return f"{socket.inet_ntop(socket.AF_INET, raw[12:16])}:{port}"
        return f"[{socket.inet_ntop(socket.AF_INET6, raw[:16])}]:{port}"
    return ""
