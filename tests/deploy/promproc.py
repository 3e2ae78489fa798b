"""Debian's Prometheus in a process of its own, on a free port with a storage folder of its own,
scraping given targets every second with given rule files, and its HTTP API."""
import contextlib
import json
import subprocess
import tempfile
import urllib.error
import urllib.parse
import urllib.request

import pytest
import yaml

from tests.agentproc import free_port, serving

PROMETHEUS = "/usr/bin/prometheus"


def config(job: str, target: str, labels: dict[str, str], rule_files: list[str], also=()) -> dict:
    return {"global": {"scrape_interval": "1s", "scrape_timeout": "1s", "evaluation_interval": "1s"},
            "rule_files": rule_files,
            "scrape_configs": [{"job_name": j, "static_configs": [{"targets": [t], "labels": ls}]}
                               for j, t, ls in ((job, target, labels), *also)]}


@contextlib.contextmanager
def running_prometheus(job: str, target: str, labels: dict[str, str], rule_files: list[str], also=()):
    """Yields the base URL of a Prometheus scraping `target` (host:port) as `job` with these
    target labels, and the (job, target, labels) of `also`; stops it at the end and removes its
    storage."""
    with tempfile.TemporaryDirectory(prefix="drums-prometheus-") as folder:
        path = f"{folder}/prometheus.yml"
        with open(path, "w") as f:
            yaml.safe_dump(config(job, target, labels, rule_files, also), f)
        port = free_port()
        proc = subprocess.Popen([PROMETHEUS, f"--config.file={path}", f"--storage.tsdb.path={folder}/data",
                                 f"--web.listen-address=127.0.0.1:{port}", "--log.level=warn"],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        url = f"http://127.0.0.1:{port}"
        serving(proc, f"{url}/-/ready", "prometheus")
        try:
            yield url
        finally:
            proc.terminate()
            proc.wait(timeout=10)


def api(url: str, path: str, **params) -> object:
    """The `data` of a Prometheus API answer; an error answer fails the test with its message."""
    query = urllib.parse.urlencode(params, doseq=True)
    try:
        with urllib.request.urlopen(f"{url}/api/v1/{path}?{query}", timeout=10) as answer:
            body = json.load(answer)
    except urllib.error.HTTPError as e:
        body = json.load(e)
    if body["status"] != "success":
        pytest.fail(f"{path} {params}: {body.get('errorType')}: {body.get('error')}")
    return body["data"]


def instant(url: str, expr: str) -> list[dict]:
    """The series an instant query returns now: [{"metric": {...}, "value": [t, "v"]}, ...]."""
    return api(url, "query", query=expr)["result"]
