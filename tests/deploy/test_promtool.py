"""The shipped rules pass Prometheus's own checks: `promtool check rules` on each file, and
`promtool test rules` on deploy/mixin/tests, where every alert has a case in which it fires and
one in which it stays silent."""
import glob
import os
import re
import subprocess

import yaml

from deploy.mixin import build
from tests.deploy.test_mixin_files import alerting_rules, rule_groups

TESTS = os.path.join(os.path.dirname(build.OUT), "tests")
PROMTOOL = "/usr/bin/promtool"


def test_promtool_check_rules_finds_every_rule_and_nothing_wrong():
    for name in ("prometheus_rules.yaml", "prometheus_alerts.yaml"):
        count = sum(len(group["rules"]) for group in rule_groups(name))
        run = subprocess.run([PROMTOOL, "check", "rules", os.path.join(build.OUT, name)], capture_output=True,
                             text=True)
        assert run.returncode == 0, run.stdout + run.stderr
        assert re.findall(r"SUCCESS: (\d+) rules found", run.stdout) == [str(count)], run.stdout
    assert [sum(len(g["rules"]) for g in rule_groups(n)) for n in ("prometheus_rules.yaml",
                                                                   "prometheus_alerts.yaml")] == [26, 25]


def test_promtool_unit_tests_pass():
    files = sorted(glob.glob(os.path.join(TESTS, "*.test.yaml")))
    run = subprocess.run([PROMTOOL, "test", "rules", *files], capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.count("SUCCESS") == len(files) == 5


def test_every_alert_fires_in_one_case_and_stays_silent_in_another():
    firing, silent = {}, {}
    for path in glob.glob(os.path.join(TESTS, "*.test.yaml")):
        with open(path) as f:
            for group in yaml.safe_load(f)["tests"]:
                for case in group.get("alert_rule_test", ()):
                    tally = firing if case["exp_alerts"] else silent
                    tally[case["alertname"]] = tally.get(case["alertname"], 0) + 1
    names = {rule["alert"] for rule in alerting_rules()}
    assert sorted(firing) == sorted(silent) == sorted(names)
    assert (sum(firing.values()), sum(silent.values())) == (24, 30)
