"""YAML from files that people and other programs write (a static graph, the /diagnostics
thresholds): PyYAML's safe loader without anchors and aliases, whose expansion turns a few hundred
bytes into gigabytes (a "billion laughs"), and no more than MAX_BYTES, read as such.

Every refusal is a yaml.YAMLError, which the callers already turn into one line naming the file.
"""
from __future__ import annotations

import yaml

MAX_BYTES = 1 << 20  # a graph of a few thousand nodes and topics fits in a tenth of it


class _Plain(yaml.SafeLoader):
    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None):
            raise yaml.YAMLError(f"anchors and aliases are not taken (line {event.start_mark.line + 1})")
        return super().compose_node(parent, index)


def load(text: str):
    """The document in `text`: plain data, no anchors or aliases, at most MAX_BYTES."""
    if len(text) > MAX_BYTES:
        raise yaml.YAMLError(f"over {MAX_BYTES >> 10} KiB")
    loader = _Plain(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read(path: str) -> str:
    """The text of a YAML file, reading no more than one byte past MAX_BYTES (raises OSError)."""
    with open(path, encoding="utf-8", errors="replace") as f:
        text = f.read(MAX_BYTES + 1)
    if len(text) > MAX_BYTES:
        raise yaml.YAMLError(f"over {MAX_BYTES >> 10} KiB")
    return text
