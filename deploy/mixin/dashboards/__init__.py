"""The mixin's Grafana dashboards, built as typed models with the Grafana Foundation SDK: a fleet
overview, a host, a ROS node, a topic and its edges, and the agent itself. They link to each other
(the Drums menu) and keep the robot, host, node and topic variables when they do."""
from deploy.mixin.config import Config
from deploy.mixin.dashboards import agent, fleet, host, node, topic
from deploy.mixin.dashboards.panels import numbered


def dashboards(cfg: Config) -> dict:
    """uid -> the dashboard's model (JSON through the SDK's encoder)."""
    return {module.UID: numbered(module.build(cfg)) for module in (fleet, host, node, topic, agent)}
