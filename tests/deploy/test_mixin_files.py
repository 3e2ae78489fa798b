"""The mixin's files: the checked-in output is what the code renders from the config now, every
series and label its rules and panels read is one the agent exports (or a rule records), every
alert has its runbook section, and a mistake in the config is one line and exit code 2."""
import importlib.util
import json
import os
import re
import subprocess
import sys

import pytest
import yaml

from deploy.mixin import build, config
from drums.metrics import HISTOGRAM
from drums.docs import all_metrics

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
RUNBOOKS = os.path.join(ROOT, "docs", "runbooks.md")
PROMETHEUS_OWN = {"up": (), "scrape_duration_seconds": (), "scrape_samples_scraped": (),
                  "ALERTS": ("alertname", "alertstate", "severity")}
SELECTOR = re.compile(r"([a-zA-Z_:][a-zA-Z0-9_:]*)\{([^}]*)\}")
MATCHER = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)\s*(?:=~|!~|!=|=)\s*"')
GROUPING = re.compile(r"\b(?:by|without|on|ignoring|group_left|group_right)\s*\(([^)]*)\)")
NAME = re.compile(r"\b(drums[_:][a-zA-Z0-9_:]*)")


def checked_in() -> dict[str, str]:
    files = {}
    for folder, _, names in os.walk(build.OUT):
        for name in names:
            path = os.path.join(folder, name)
            with open(path) as f:
                files[os.path.relpath(path, build.OUT)] = f.read()
    return files


def rule_groups(name: str) -> list[dict]:
    with open(os.path.join(build.OUT, name)) as f:
        return yaml.safe_load(f)["groups"]


def alerting_rules() -> list[dict]:
    return [rule for group in rule_groups("prometheus_alerts.yaml") for rule in group["rules"]]


def expressions() -> list[tuple[str, str]]:
    """(where, PromQL) of every rule, panel query and variable query of the checked-in output."""
    out = []
    for name in ("prometheus_rules.yaml", "prometheus_alerts.yaml"):
        for group in rule_groups(name):
            out += [(f"{name}: {r.get('record') or r.get('alert')}", r["expr"]) for r in group["rules"]]
    for path, text in checked_in().items():
        if path.endswith(".json"):
            board = json.loads(text)
            out += [(f"{path}: variable {v['name']}", v["query"]) for v in board["templating"]["list"]
                    if v["type"] == "query"]
            out += [(f"{path}: {p['title']}", t["expr"]) for p in board["panels"] for t in p.get("targets", ())]
    return out


# The dashboards are built with the Grafana Foundation SDK, which has no release for Python 3.10.
needs_sdk = pytest.mark.skipif(importlib.util.find_spec("grafana_foundation_sdk") is None,
                               reason="grafana-foundation-sdk needs Python >= 3.11")


@needs_sdk
def test_the_checked_in_output_is_what_the_code_renders():
    rendered = build.rendered(config.load())
    stale = sorted(path for path in rendered.keys() | checked_in().keys()
                   if rendered.get(path) != checked_in().get(path))
    assert stale == [], f"run `.venv/bin/python -m deploy.mixin.build` and commit deploy/mixin/out: {stale}"
    assert sorted(rendered) == ["dashboards/drums-agent.json", "dashboards/drums-fleet.json",
                                "dashboards/drums-host.json", "dashboards/drums-node.json",
                                "dashboards/drums-topic.json", "prometheus_alerts.yaml", "prometheus_rules.yaml"]


@needs_sdk
def test_the_build_writes_every_file_and_removes_what_it_no_longer_renders(tmp_path):
    (tmp_path / "dashboards").mkdir()
    (tmp_path / "dashboards" / "drums-old.json").write_text("{}")
    assert build.main(["--out", str(tmp_path)]) == 0
    written = {str(p.relative_to(tmp_path)): p.read_text() for p in tmp_path.rglob("*") if p.is_file()}
    assert written == build.rendered(config.load())


def test_every_series_and_label_read_is_exported_or_recorded():
    cfg = config.load()
    targets = {"job", "instance", cfg.robot_label, cfg.host_label}
    declared = {}
    for _, metrics in all_metrics():
        for m in metrics:
            names = [m.name] if m.kind != HISTOGRAM else [m.name + s for s in ("_bucket", "_sum", "_count")]
            for name in names:
                declared[name] = set(m.labels) | targets | ({"le"} if name.endswith("_bucket") else set())
    recorded = {r["record"] for g in rule_groups("prometheus_rules.yaml") for r in g["rules"]}
    known_labels = set().union(*declared.values()) | {"quantile"}
    wrong = []
    for where, expr in expressions():
        wrong += [(where, name) for name in NAME.findall(expr) if name not in declared and name not in recorded]
        for metric, matchers in SELECTOR.findall(expr):
            allowed = declared.get(metric) or (set(PROMETHEUS_OWN.get(metric, ())) | known_labels)
            wrong += [(where, f"{metric}{{{label}}}") for label in MATCHER.findall(matchers) if label not in allowed]
        for labels in GROUPING.findall(expr):
            wrong += [(where, label) for label in re.split(r"\s*,\s*", labels.strip())
                      if label and label not in known_labels]
    assert wrong == []
    assert len(expressions()) > 100


def test_every_alert_has_a_severity_its_annotations_and_a_runbook_section():
    cfg = config.load()
    with open(RUNBOOKS) as f:
        text = f.read()
    sections = re.findall(r"^## (\S+)\n\n\*\*Means\.\*\*.*?\n\n\*\*Look\.\*\*.*?\n\n\*\*Do\.\*\*", text,
                          re.MULTILINE | re.DOTALL)
    alerts = alerting_rules()
    names = sorted({rule["alert"] for rule in alerts})
    assert sorted(sections) == names == sorted(re.findall(r"^## (\S+)$", text, re.MULTILINE))
    assert len(names) == 23
    for rule in alerts:
        assert rule["labels"]["severity"] in ("critical", "warning", "info"), rule["alert"]
        assert rule["annotations"]["runbook_url"] == f"{cfg.runbook_url}#{rule['alert'].lower()}"
        assert sorted(rule["annotations"]) == ["description", "runbook_url", "summary"]


@pytest.mark.parametrize("mistake, message", [
    (lambda c: c.pop("selector"), "missing keys ['selector'], unknown keys []"),
    (lambda c: c.update(topic_flood_ratio=3), "missing keys [], unknown keys ['topic_flood_ratio']"),
    (lambda c: c.update(agent_down_for="2 minutes"),
     "agent_down_for: '2 minutes' is not a Prometheus duration such as 5m"),
    (lambda c: c.update(map_fill_ratio="high"), "map_fill_ratio: 'high' is not a number >= 0"),
])
def test_a_mistake_in_the_config_is_one_line_and_nothing_is_written(tmp_path, mistake, message):
    with open(config.CONFIG) as f:
        settings = yaml.safe_load(f)
    mistake(settings)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(settings))
    run = subprocess.run([sys.executable, "-m", "deploy.mixin.build", "--config", str(tmp_path / "config.yaml"),
                          "--out", str(tmp_path / "out")], cwd=ROOT, capture_output=True, text=True)
    assert (run.returncode, run.stdout) == (2, "")
    assert run.stderr.splitlines() == [f"deploy.mixin.build: {tmp_path / 'config.yaml'}: {message}"]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("entry, message", [("scan: 10", "'scan' is not a topic name such as /scan"),
                                             ("/scan: fast", "/scan: 'fast' is not a number >= 0")])
def test_expected_rates_must_be_topics_and_rates(tmp_path, entry, message):
    (tmp_path / "rates.yaml").write_text(entry + "\n")
    with pytest.raises(config.ConfigError) as e:
        config.load(config.CONFIG, str(tmp_path / "rates.yaml"))
    assert str(e.value) == f"{tmp_path / 'rates.yaml'}: {message}"
