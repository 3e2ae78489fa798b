"""Prometheus file-based service discovery (file_sd_configs): one target group per host of the
graph, {"targets": ["<address>:<port>"], "labels": {"host": "<name>"}}.

The target is where the host's agent said it listens (its URL), else the host's address with the
agents' port, else its name with that port, for Prometheus to resolve through DNS: a host without
an agent then shows as a target that is down rather than not at all.
"""
from __future__ import annotations

import json
import os
import tempfile
from urllib.parse import urlsplit

from drums.errors import GraphError, UsageError
from drums.graph.model import Host
from drums.netfmt import hostport


def target_groups(hosts: list[Host], port: int) -> list[dict]:
    groups = []
    for host in sorted(hosts, key=lambda h: h.name):
        url = urlsplit(host.agent)
        target = hostport(url.hostname, url.port or port) if url.hostname else hostport(host.address or host.name, port)
        groups.append({"targets": [target], "labels": {"host": host.name}})
    return groups


def hosts_of(document: str, source: str) -> list[Host]:
    """The hosts of a graph exported as JSON (an agent's /graph?format=json)."""
    try:
        vertices = json.loads(document)["nodes"]
        return [Host(v["name"], v.get("address", ""), v.get("agent", "")) for v in vertices if v.get("kind") == "host"]
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise GraphError(f"{source}: not a graph in JSON ({type(e).__name__}: {e})") from None


def write(path: str, groups: list[dict]) -> None:
    """Replace the file whole, by rename: Prometheus reads it whenever it changes, and takes a
    half-written file for a broken one."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        # A name that does not end like the file: a file_sd glob (*.json) never matches it.
        fd, temporary = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", dir=folder)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(json.dumps(groups, indent=1) + "\n")
            os.chmod(temporary, 0o644)  # Prometheus usually runs as a user of its own
            os.replace(temporary, path)
        except BaseException:
            os.unlink(temporary)
            raise
    except OSError as e:
        raise UsageError(f"--output {path}: {e.strerror or e}") from None
