"""`drums detect`: anomaly detection over every series of one or more agents (or of a Prometheus
server), attributed to the graph's entities.

Data enters from sources (agents' /metrics, Prometheus), is kept as a history array, judged by the
checks, and leaves as anomalies and graph changes (lines, a JSON-lines log, /metrics).

Its defaults live here, where the command line reads them without loading numpy.
"""

DEFAULT_PORT = 9971  # the detector's /metrics and /anomalies
GRACE = 120.0  # seconds the series of a node that started, restarted or gained an edge are left alone
