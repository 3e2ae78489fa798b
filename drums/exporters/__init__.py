"""Where the agent's data leaves it. The ports are here, light to import, for the command line."""

STREAM_PORT = 9970  # the ZeroMQ stream of job samples
# The header of /metrics and /graph that says when the agent read the counters they show (Unix
# time, seconds): a rate over two reads is right whatever the requests' own delays were.
READ_AT = "X-Drums-Read-At"
