"""Where the agent's data leaves it. The ports are here, light to import, for the command line."""

STREAM_PORT = 9970  # the ZeroMQ stream of job samples
