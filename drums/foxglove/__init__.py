"""Drums in Foxglove: what `drums top` shows of one or more agents, as Foxglove channels.

channels.py turns a frame of top's model into a message per node, topic, edge and host (flat JSON
whose fields plot directly in Foxglove's Plot panel) and the detector's anomalies into Log
messages; record.py writes them to an MCAP file (`drums record`).
"""
