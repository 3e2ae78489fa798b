"""/healthz and /readyz: whether the agent runs, and whether what it serves is whole.

/healthz answers 200 while the agent serves, with what each source is doing (each probe attached,
on its fallback or missing; the graph live or stale): the liveness check of a service manager or
an orchestrator, and the first page a person reads when numbers look wrong. /readyz answers 200
once the graph has been read (an agent without a graph is ready at once), 503 with the reason
until then: before that every per-node series would be missing.
"""
from __future__ import annotations

import json

from drums.exporters.http import JSON, HttpError
from drums.graph.model import Graph
from drums.probes.base import Probe


def health(probes: list[Probe], graph: Graph | None, adapter: str) -> dict:
    sources = {p.name: {"attached": p.status.attached, "attach_type": p.status.attach_type,
                        "reason": p.status.reason} for p in probes}
    degraded = [name for name, s in sources.items() if not s["attached"] or s["reason"]]
    out = {"status": "degraded" if degraded else "ok", "degraded": degraded, "probes": sources}
    if graph is not None:
        out["graph"] = {"adapter": adapter, "read": graph.updated_at > 0, "stale": bool(graph.error),
                        "error": graph.error, "truncated": graph.truncated}
        if graph.error or graph.truncated:
            out["status"] = "degraded"
            out["degraded"].append(f"graph {adapter}")
    return out


def healthz(probes: list[Probe], graph: Graph | None, adapter: str) -> tuple[bytes, str]:
    return json.dumps(health(probes, graph, adapter)).encode() + b"\n", JSON


def readyz(graph: Graph | None, adapter: str) -> tuple[bytes, str]:
    if graph is not None and graph.updated_at == 0:
        why = f": {graph.error}" if graph.error else ""
        raise HttpError(503, f"not ready: the {adapter} graph has not been read yet{why}")
    return b"ready\n", "text/plain; charset=utf-8"
