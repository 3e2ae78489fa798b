"""Socket addresses as users read them: 127.0.0.1:80, [::1]:80; and the address this host is
reached at."""
from __future__ import annotations

import ipaddress
import re
import socket
from functools import lru_cache

AF_INET, AF_INET6 = 2, 10
V4_MAPPED = b"\0" * 10 + b"\xff\xff"  # the prefix of an IPv4 address mapped into IPv6


@lru_cache(maxsize=65536)  # the same few addresses come back at every collect
def endpoint(family: int, raw: bytes, port: int) -> str:
    """Format a kernel address (4 or 16 bytes, network order) and a host-order port."""
    if family == AF_INET:
        return f"{socket.inet_ntop(socket.AF_INET, raw[:4])}:{port}"
    if family == AF_INET6:
        if raw[:12] == V4_MAPPED:
            return f"{socket.inet_ntop(socket.AF_INET, raw[12:16])}:{port}"
        return f"[{socket.inet_ntop(socket.AF_INET6, raw[:16])}]:{port}"
    return ""


def parse_endpoint(text: str) -> tuple[int, bytes, int] | None:
    """(family, address in network order, port) of what endpoint() wrote, None for anything else."""
    host, _, port = text.rpartition(":")
    family = AF_INET6 if host.startswith("[") else AF_INET
    try:
        return family, socket.inet_pton(family, host.strip("[]")), int(port)
    except (OSError, ValueError):
        return None


def hostport(host: str, port: int) -> str:
    """host:port, with an IPv6 address in brackets as URLs and Prometheus targets want it."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


_DNS_NAME = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)(\.(?!-)[A-Za-z0-9-]{1,63}(?<!-))*\.?")


def is_address(text: str) -> bool:
    """Whether `text` is an IP address or a DNS name: what a host may be reached at."""
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        return len(text) <= 253 and _DNS_NAME.fullmatch(text) is not None


# Documentation addresses (RFC 5737, RFC 3849): a UDP connect to them picks the route that other
# hosts' traffic takes without sending anything, and nothing real ever answers there.
_ROUTED = ((socket.AF_INET, "203.0.113.1"), (socket.AF_INET6, "2001:db8::1"))


def primary_address() -> str:
    """This host's address as other hosts see it: the source address of the default route, else
    the address its name resolves to, else its name."""
    for family, far in _ROUTED:
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                s.connect((far, 9))
                return s.getsockname()[0]
        except OSError:
            continue  # no route of that family
    name = socket.gethostname()
    try:
        return socket.gethostbyname(name)
    except OSError:
        return name


def is_loopback(address: str) -> bool:
    try:
        return address == "localhost" or ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False
