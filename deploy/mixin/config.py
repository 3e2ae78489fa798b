"""The mixin's settings, read from config.yaml and expected_rates.yaml, and the label matchers
every rule and panel is built from. A key that is missing, unknown or of the wrong kind stops the
build with one line (ConfigError), before anything is written."""
import dataclasses
import os
import re

import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(HERE, "config.yaml")
EXPECTED_RATES = os.path.join(HERE, "expected_rates.yaml")

DURATION = re.compile(r"^([0-9]+(ms|s|m|h|d|w|y))+$")  # a Prometheus duration, as `for:` takes it


class ConfigError(Exception):
    pass


class Duration(str):
    """A Prometheus duration such as 5m, checked when the config is read."""


@dataclasses.dataclass(frozen=True)
class Config:
    selector: str
    robot_label: str
    host_label: str
    target_labels: list
    runbook_url: str
    agent_down_for: Duration
    host_unreachable_for: Duration
    probe_detached_for: Duration
    fallback_attach_types: list
    probe_degraded_for: Duration
    probe_collect_failing_for: Duration
    graph_stale_for: Duration
    node_gone_lookback: Duration
    node_gone_for: Duration
    node_cpu_saturated_cores: float
    node_cpu_saturated_for: Duration
    memory_leak_bytes_per_second: float
    memory_leak_for: Duration
    runqueue_latency_p99_seconds: float
    runqueue_latency_for: Duration
    host_cpu_busy_ratio: float
    host_cpu_saturated_for: Duration
    topic_stalled_min_rate: float
    topic_stalled_for: Duration
    topic_stalled_ignore: list
    topic_below_expected_for: Duration
    deadline_misses: float
    deadline_missed_for: Duration
    topic_loss_ratio: float
    topic_loss_for: Duration
    topic_flood_rate: float
    topic_flood_rates: dict
    topic_flood_for: Duration
    edge_bandwidth_collapse_ratio: float
    edge_bandwidth_min_bytes_per_second: float
    edge_bandwidth_collapse_for: Duration
    retransmit_ratio: float
    retransmit_for: Duration
    qos_incompatible_for: Duration
    tcp_mss_bytes: float
    map_fill_ratio: float
    map_fill_for: Duration
    dropped_events_for: Duration
    budget_folding_for: Duration
    # from expected_rates.yaml: topic -> least messages per second on a robot
    expected_rates: dict = dataclasses.field(default_factory=dict)

    def matchers(self, *extra: str) -> str:
        """The agents' selector and `extra` matchers, comma-joined: `job="drums",topic="/a"`."""
        return ",".join((self.selector, *extra))

    def series(self, metric: str, *extra: str) -> str:
        """A selector of one metric of the agents: `metric{job="drums",...}`."""
        return f"{metric}{{{self.matchers(*extra)}}}"

    def label(self, name: str) -> str:
        """An alert template's reference to a label of the firing series."""
        return "{{ $labels.%s }}" % name


def _checked(path: str, key: str, value, kind):
    if kind is Duration:
        if not isinstance(value, str) or not DURATION.match(value):
            raise ConfigError(f"{path}: {key}: {value!r} is not a Prometheus duration such as 5m")
        return Duration(value)
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise ConfigError(f"{path}: {key}: {value!r} is not a number >= 0")
        return value
    if not isinstance(value, kind):
        raise ConfigError(f"{path}: {key}: {value!r} is not a {kind.__name__}")
    return value


def _yaml(path: str) -> dict:
    try:
        with open(path) as f:
            data = yaml.safe_load(f) or {}  # an empty file is an empty mapping
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{path}: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys to values")
    return data


def load(config_path: str = CONFIG, expected_rates_path: str = EXPECTED_RATES) -> Config:
    data = _yaml(config_path)
    kinds = {f.name: f.type for f in dataclasses.fields(Config) if f.name != "expected_rates"}
    missing, unknown = sorted(kinds.keys() - data.keys()), sorted(data.keys() - kinds.keys())
    if missing or unknown:
        raise ConfigError(f"{config_path}: missing keys {missing}, unknown keys {unknown}")
    values = {key: _checked(config_path, key, data[key], kind) for key, kind in kinds.items()}
    rates = _yaml(expected_rates_path)
    for topic, rate in rates.items():
        if not isinstance(topic, str) or not topic.startswith("/"):
            raise ConfigError(f"{expected_rates_path}: {topic!r} is not a topic name such as /scan")
        _checked(expected_rates_path, topic, rate, float)
    return Config(**values, expected_rates=rates)
