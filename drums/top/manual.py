"""What `?` shows: the keys, and what each view's columns say (lines short enough for 80 columns)."""

KEYS = """\
Keys
  n t e c h a views: Nodes, Topics, Edges, Connections, Hosts,
              Anomalies
  < >         sort by the column left or right of the current one
              (or click a column's title; click again to reverse)
  r           reverse the order
  /           filter: rows whose names hold the text
              (Enter keeps it, Escape clears it)
  p           Nodes: show or hide the processes that hold no node
  arrows, PgUp, PgDn, Home, End
              select a row: the line and sparkline under the table
              show its sort column over the last minutes
  ?           this help (Escape closes it)
  q, Ctrl-C   quit (the jobs top made on the agents are deleted)
"""

VIEWS = {
    "nodes": """\
Nodes: every ROS node of the agents' hosts (names start with /)
and every process that holds none
  CPU       % of one core (the nodes of a process show its CPU)
  MEM       resident memory
  RUNQ99    99th percentile of the waits for a CPU
  PUB TAKE  messages published and taken per second, all topics
  TX RX     bytes per second: a node's messages over UDP,
            a process's sockets""",
    "topics": """\
Topics: every topic of the graph
  PUBS SUBS  publishing and subscribing nodes
  RATE       messages published per second by its publishers
  JITTER     how much later than usual its late messages came:
             p99 less p50 of the time between two messages of a
             publisher over the last interval, its worst publisher
  BANDWIDTH  serialized bytes per second sent over UDP
             (shared memory carries none that can be counted)
  LOST       messages published to a subscriber and not taken
             by it, since top saw them flow""",
    "edges": """\
Edges: publisher -> subscriber on a topic
  RATE       samples received per second over UDP; else the
             messages the subscriber took, if this is its only
             publisher on the topic
  BANDWIDTH  bytes received per second (UDP samples; the socket
             of a ROS 1 connection)
  AGE        how old a message was when the subscriber took it,
             from the publisher's stamp (ROS 2), on average
  REPAIR     wire bytes beyond the samples' own (repairs), in %
  RETX RTT   TCP retransmits per second and smoothed round trip
             of a ROS 1 connection
  QOS        the middleware's QoS check: ok, or why not""",
    "connections": """\
Connections: every socket that moved bytes in the last interval
  RX TX  bytes per second received and sent
  RTT    the kernel's smoothed round trip (TCP)""",
    "hosts": """\
Hosts: each agent's host and its state: up; stale (no fresh
answer); down (not answering); no agent (a host of the graph
that no agent given to top watches). Under it, its network
interfaces (lo too) and the hosts it measures the round trip to
  CPU    % of all cores busy
  MEM    % of memory used
  LOAD   1-minute load average
  RX TX  bytes per second (the host's line leaves lo out)
  LATENCY  mean round trip (the host's line: the longest)""",
    "anomalies": """\
Anomalies: what `drums detect` (--detector) flags now, an incident
per group: the anomaly that names it, then the others (+) of it
  WHAT    the series: what it counts, and its process or thread
  CHANGE  against the series' median before it started
  SINCE   when it started
  CHECKS  how many of the five checks called it anomalous
  SERIES  anomalous series in the incident""",
}


def text(view: str) -> str:
    return f"{KEYS}\n{VIEWS[view]}\n"
