"""`drums foxglove`: the channels of one or more agents (drums.foxglove.channels) served live over
the Foxglove WebSocket protocol (the Foxglove SDK's server), with the ROS graph as the agents see it
for Foxglove's Topic Graph (the protocol's connection graph). A command of its own, as `drums top`
is, not a part of the agent: it follows many agents, and it costs the robot nothing when no one
looks. A client that does not read loses its oldest messages past a backlog, and is disconnected
when its control messages fill one too: its memory stays bounded."""
from __future__ import annotations

from drums.errors import UsageError
from drums.foxglove.channels import follow
from drums.top.collector import Collector
from drums.top.model import Frame

BACKLOG = 1024  # messages buffered per client (the SDK's queue: each of the data and the control plane)


def connection_graph(frame: Frame) -> dict[str, tuple[set, set]]:
    """Each ROS topic's publishing and subscribing nodes, as the agents' graphs have them."""
    out: dict[str, tuple[set, set]] = {}
    for agent in frame.live():
        for e in agent.latest.endpoints:
            pubs, subs = out.setdefault(e["topic"], (set(), set()))
            (pubs if e["kind"] == "publisher" else subs).add(e["node"])
    return out


def run(urls: list[str], token: str, interval: float, address: str, port: int, detector: str = "") -> int:
    import foxglove
    collector = Collector(urls, token, interval, detector)  # (which checks the URLs first)
    context = foxglove.Context()
    try:
        server = foxglove.start_server(name="drums", host=address, port=port, context=context,
                                       capabilities=[foxglove.Capability.ConnectionGraph],
                                       message_backlog_size=BACKLOG)
    except Exception as e:  # the SDK's own error for an address it cannot bind
        raise UsageError(f"--address {address} --port {port}: {e}") from None
    shown: list = [None]

    def publish_graph(frame: Frame) -> None:
        topics = connection_graph(frame)
        if topics == shown[0]:
            return
        graph = foxglove.ConnectionGraph()
        for topic, (pubs, subs) in sorted(topics.items()):
            graph.set_published_topic(topic, sorted(pubs))
            graph.set_subscribed_topic(topic, sorted(subs))
        server.publish_connection_graph(graph)
        shown[0] = topics
    print(f"drums foxglove: serving ws://{address}:{server.port} (Foxglove: open a Foxglove WebSocket connection)",
          flush=True)
    try:
        follow(collector, context, interval, publish_graph)
    finally:
        server.stop()
    return 0
