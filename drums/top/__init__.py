"""`drums top`: the nodes, topics, edges, connections and hosts of one or more agents, live.

main.py starts it; collector.py fetches (threads: polls of each agent's graph and /metrics, top's
jobs and their stream, and the anomalies of `drums detect`) into model.py; views.py and hosts.py turn a frame of the model into tables
(table.py: sort, filter, fit); app.py shows them full-screen (Textual), screen.py as text or JSON.
"""

VIEWS = ("nodes", "topics", "edges", "connections", "hosts", "anomalies")
