"""The computation graph: adapters read it, join puts the kernel's counts on it."""

FORMATS = ("text", "json", "dot", "svg", "graphml")  # how `drums graph` and /graph write it
