"""`drums detect`: anomaly detection over every series of one or more agents (or of a Prometheus
server), attributed to the graph's entities.

Data enters from sources (agents' /metrics, Prometheus), is kept as a history array, judged by the
checks, and leaves as anomalies and graph changes (lines, a JSON-lines log, /metrics).
"""
