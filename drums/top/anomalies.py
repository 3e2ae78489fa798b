"""The Anomalies view of `drums top`: what `drums detect` flags now (its /anomalies), an incident
per group: the anomaly that names it, then the others of the incident under it."""
from __future__ import annotations

import time

from drums.top.model import Frame
from drums.top.table import Column, Row, Table

COLUMNS = [
    Column("entity", "ENTITY", name=True, least=12, keep=9),
    Column("what", "WHAT", name=True, least=8, keep=8),
    Column("change", "CHANGE", name=True, keep=7),
    Column("since", "SINCE", name=True, keep=6),
    Column("checks", "CHECKS", keep=3),
    Column("series", "SERIES", lambda v: "" if v is None else f"{v}", keep=4),
    Column("host", "HOST", name=True, keep=2),
]


def anomalies(frame: Frame) -> Table:
    rows = []
    for incident in (frame.anomalies or {}).get("incidents", []):
        found = [(e["entity"], a) for e in incident["entities"] for a in e["anomalies"]]
        leader = ""
        for entity, a in found:
            key = f"anomaly|{entity['host']}|{a['series']}"
            rows.append(Row(key, {
                "entity": f"{'' if not leader else '+ '}{entity['kind']} {entity['name']}", "what": a["what"],
                "change": a["change"], "since": time.strftime("%H:%M:%S", time.localtime(a["start"])),
                "checks": len(a["checks"]), "series": None if leader else len(found), "host": entity["host"]},
                group=leader))
            leader = leader or key
    return Table("anomalies", COLUMNS, rows, sort="series", spark="checks", note=frame.detector_error)
