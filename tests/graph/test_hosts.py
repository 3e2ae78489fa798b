"""The hosts of the graph and where they are reached: announced by the agents of a ROS 2 domain,
and written by `drums sd` as a Prometheus file_sd target file that a real Prometheus, configured
as the README shows, reads and scrapes."""
from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import textwrap
import time
import urllib.request

import pytest
import yaml

from drums.graph.model import Host
from drums.graph.ros2 import announced
from drums.netfmt import primary_address
from tests.agentproc import free_port, running_agent, scrape
from tests.conftest import eventually

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
EXAMPLE = os.path.join(ROOT, "examples", "static-graph.yaml")
REFUSED = f"http://127.0.0.1:{free_port()}"  # nothing listens there
HOSTS = """
    host: arm
    hosts:
      - {name: arm, address: 10.0.0.2, agent_port: 9970}
      - {name: base, address: "fd00::3"}
      - {name: camera, address: camera.local}
    nodes: [{name: /planner, process: no-such-process-5e1c}]
"""


def graph_hosts(base: str) -> dict[str, tuple[str, str]]:
    """name -> (address, agent) of the hosts in an agent's /graph."""
    vertices = json.loads(scrape(base + "/graph?format=json"))["nodes"]
    return {v["name"]: (v["address"], v["agent"]) for v in vertices if v["kind"] == "host"}


def named(name: str) -> tuple[str, ...]:
    """A command that runs the next one with a host name of its own (a UTS namespace): two agents
    on one machine stand for two hosts."""
    return ("unshare", "--uts", "sh", "-c", f'hostname {name} && exec "$@"', "sh")


def test_agents_on_one_ros2_domain_list_each_others_hosts_while_they_run():
    with running_agent("--graph", "ros2", "--probe", "host", "--advertise", "127.0.0.2",
                       under=named("robot-a")) as a:
        with running_agent("--graph", "ros2", "--probe", "host", "--advertise", "127.0.0.3",
                           under=named("robot-b")) as b:
            a, b = a.rsplit("/", 1)[0], b.rsplit("/", 1)[0]
            both = {"robot-a": ("127.0.0.2", f"http://127.0.0.2:{a.rsplit(':', 1)[1]}"),
                    "robot-b": ("127.0.0.3", f"http://127.0.0.3:{b.rsplit(':', 1)[1]}")}

            def listed():
                assert (graph_hosts(a), graph_hosts(b)) == (both, both)
            eventually(listed, timeout=10)
            # The announcements are Drums' own: neither a node nor a topic of the robot's graph.
            text = scrape(a + "/graph?format=text")
            assert "/drums/agents" not in text and "_drums_graph" not in text, text
        # robot-b's agent stopped: its reader said goodbye, and robot-a no longer lists it.
        def alone():
            assert graph_hosts(a) == {"robot-a": both["robot-a"]}
        eventually(alone, timeout=5)


@pytest.mark.parametrize("text, host", [
    ('{"host": "arm", "address": "10.0.0.2", "agent": "http://10.0.0.2:9969"}',
     Host("arm", "10.0.0.2", "http://10.0.0.2:9969")),
    ('{"host": "arm", "address": "", "agent": "", "later": 1}', Host("arm")),
    ("not JSON", None),
    ('["arm"]', None),
    ('{"host": "arm", "address": "10.0.0.2"}', None),
    ('{"host": "", "address": "", "agent": ""}', None),
    ('{"host": "arm", "address": "10.0.0.2; rm", "agent": ""}', None),
    ('{"host": "arm", "address": 10, "agent": ""}', None),
    ('{"host": "arm", "address": "", "agent": "ftp://10.0.0.2:21"}', None),
    ('{"host": "arm", "address": "", "agent": "http://10.0.0.2"}', None),
    ('{"host": "arm", "address": "", "agent": "http://10.0.0.2:99999"}', None),
])
def test_an_announcement_is_taken_only_when_well_formed(text, host):
    assert announced(text) == host


def test_the_primary_address_is_the_source_of_the_default_route():
    route = subprocess.run(["ip", "-4", "route", "get", "203.0.113.1"], capture_output=True, text=True, check=True)
    assert primary_address() == re.search(r" src (\S+)", route.stdout)[1]


def sd(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "drums", "sd", *args], capture_output=True, text=True, timeout=60,
                          cwd=cwd)


def test_a_static_graph_of_three_hosts_gives_three_target_groups(tmp_path):
    (tmp_path / "robot.yaml").write_text(textwrap.dedent(HOSTS))
    out = tmp_path / "targets" / "drums.json"
    out.parent.mkdir()
    done = sd("--graph", "static", "--graph-file", str(tmp_path / "robot.yaml"), "--output", str(out))
    assert (done.returncode, done.stderr) == (0, "")
    # The announced agent's port where there is one, --port's default elsewhere; IPv6 in brackets.
    assert json.loads(out.read_text()) == [
        {"targets": ["10.0.0.2:9970"], "labels": {"host": "arm"}},
        {"targets": ["[fd00::3]:9969"], "labels": {"host": "base"}},
        {"targets": ["camera.local:9969"], "labels": {"host": "camera"}}]
    assert os.listdir(out.parent) == ["drums.json"]  # the temporary file was renamed, none left
    assert oct(os.stat(out).st_mode & 0o777) == "0o644"  # readable by a Prometheus of another user
    assert done.stdout == f"{out}: 10.0.0.2:9970, [fd00::3]:9969, camera.local:9969\n"


def test_a_host_without_an_address_is_listed_by_name_on_the_port_given(tmp_path):
    (tmp_path / "robot.yaml").write_text("host: arm-7\nnodes: [{name: /planner}]\n")
    out = tmp_path / "drums.json"
    done = sd("--graph", "static", "--graph-file", str(tmp_path / "robot.yaml"), "--output", str(out), "--port", "9100")
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text()) == [{"targets": ["arm-7:9100"], "labels": {"host": "arm-7"}}]


def test_watch_writes_the_file_again_by_rename_when_the_hosts_change(tmp_path):
    graph = tmp_path / "robot.yaml"
    graph.write_text("host: arm\nhosts: [{name: arm, address: 10.0.0.2}]\n")
    out = tmp_path / "drums.json"
    proc = subprocess.Popen([sys.executable, "-m", "drums", "sd", "--graph", "static", "--graph-file", str(graph),
                             "--output", str(out), "--watch"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == f"{out}: 10.0.0.2:9969\n"
        first = os.stat(out).st_ino
        graph.write_text("host: arm\nhosts: [{name: arm, address: 10.0.0.2}, {name: base, address: 10.0.0.3}]\n")
        assert proc.stdout.readline() == f"{out}: 10.0.0.2:9969, 10.0.0.3:9969\n"
        assert json.loads(out.read_text()) == [{"targets": ["10.0.0.2:9969"], "labels": {"host": "arm"}},
                                               {"targets": ["10.0.0.3:9969"], "labels": {"host": "base"}}]
        assert os.stat(out).st_ino != first  # a new file renamed over the old: never half written
        assert sorted(os.listdir(tmp_path)) == ["drums.json", "robot.yaml"]
    finally:
        proc.terminate()
        proc.wait(10)
    assert proc.stderr.read() == ""


def test_watching_an_agent_that_goes_away_keeps_the_file_and_says_so_once(tmp_path):
    (tmp_path / "robot.yaml").write_text(textwrap.dedent(HOSTS))
    out = tmp_path / "drums.json"
    with running_agent("--graph", "static", "--graph-file", str(tmp_path / "robot.yaml"), "--probe", "host") as url:
        base = url.rsplit("/", 1)[0]
        proc = subprocess.Popen([sys.executable, "-m", "drums", "sd", "--agent", base, "--output", str(out), "--watch"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert proc.stdout.readline() == f"{out}: 10.0.0.2:9970, [fd00::3]:9969, camera.local:9969\n"
        written = out.read_text()
    try:
        assert proc.stderr.readline() == f"drums: --agent {base}: Connection refused; keeping {out} as it is\n"
        time.sleep(2.5)  # two more tries, said nothing of
        assert proc.poll() is None and out.read_text() == written
    finally:
        proc.terminate()
        proc.wait(10)
    assert proc.stderr.read() == "" and proc.stdout.read() == ""


@pytest.mark.parametrize("args, error", [
    (["--graph", "static"], "the following arguments are required: --output (see drums sd --help)"),
    (["--output", "x.json", "--port", "70000"], "argument --port: 70000 is not a port (0-65535) (see drums sd --help)"),
    (["--output", "x.json", "--agent", REFUSED, "--graph", "ros1"],
     "--agent takes the hosts of the agent's graph: not with --graph or --graph-file"),
    (["--output", "x.json", "--agent", REFUSED], f"--agent {REFUSED}: Connection refused"),
    (["--output", "/no/such/folder/drums.json", "--graph", "static", "--graph-file", EXAMPLE],
     "--output /no/such/folder/drums.json: No such file or directory"),
])
def test_bad_flags_and_unwritable_files_are_one_line_and_exit_2(args, error, tmp_path):
    done = sd(*args, cwd=tmp_path)
    assert (done.returncode, done.stdout, done.stderr) == (2, "", f"drums: {error}\n")
    assert os.listdir(tmp_path) == []


def documented_config() -> dict:
    """The prometheus.yml of the README's section on Prometheus discovery."""
    with open(os.path.join(ROOT, "README.md")) as f:
        section = f.read().split("## Prometheus discovery", 1)[1]
    return yaml.safe_load(re.search(r"```yaml\n(.*?)```", section, re.S)[1])


def test_promtool_accepts_the_documented_configuration(tmp_path):
    config = documented_config()
    assert config["scrape_configs"][0]["file_sd_configs"] == [{"files": ["/etc/prometheus/drums.json"]}]
    path = tmp_path / "prometheus.yml"
    path.write_text(yaml.safe_dump(config))
    done = subprocess.run(["promtool", "check", "config", str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "SUCCESS" in done.stdout, done.stdout + done.stderr


def api(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=5) as reply:
        return json.loads(reply.read())


def test_prometheus_scrapes_the_agent_that_drums_sd_found(tmp_path):
    """An agent announces its host on the ROS 2 graph; `drums sd --agent` writes it; Prometheus,
    configured as the README shows, discovers it with its host label and scrapes it."""
    host = socket.gethostname()
    with running_agent("--graph", "ros2", "--probe", "host") as metrics:
        base = metrics.rsplit("/", 1)[0]
        port = base.rsplit(":", 1)[1]

        def announced_itself():  # it listens on 127.0.0.1 only: that is what it announces, with its port
            assert graph_hosts(base) == {host: ("127.0.0.1", f"http://127.0.0.1:{port}")}
        eventually(announced_itself, timeout=10)
        targets = tmp_path / "drums.json"
        done = sd("--agent", base, "--output", str(targets))
        assert done.returncode == 0, done.stderr
        assert json.loads(targets.read_text()) == [{"targets": [f"127.0.0.1:{port}"], "labels": {"host": host}}]
        # Discovered here rather than asked of the agent: the same, the agent's announcement telling
        # more of this host than its name.
        here = tmp_path / "here.json"
        done = sd("--graph", "ros2", "--output", str(here))
        assert done.returncode == 0, done.stderr
        assert here.read_text() == targets.read_text()

        config = documented_config()
        config["global"] = {"scrape_interval": "1s"}
        config["scrape_configs"][0]["file_sd_configs"][0] = {"files": [str(targets)], "refresh_interval": "1s"}
        (tmp_path / "prometheus.yml").write_text(yaml.safe_dump(config))
        web = f"127.0.0.1:{free_port()}"
        prometheus = subprocess.Popen(["prometheus", f"--config.file={tmp_path / 'prometheus.yml'}",
                                       f"--storage.tsdb.path={tmp_path / 'data'}", f"--web.listen-address={web}"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            def scraped():
                assert prometheus.poll() is None, prometheus.stderr.read()
                try:
                    active = api(f"http://{web}/api/v1/targets")["data"]["activeTargets"]
                except OSError as e:
                    raise AssertionError(f"Prometheus does not answer yet: {e}") from None
                assert [(t["labels"], t["health"]) for t in active] == [
                    ({"host": host, "instance": f"127.0.0.1:{port}", "job": "drums"}, "up")], active
            eventually(scraped, timeout=30)
            # The agent's own series, as stored, carry the host label.
            result = api(f"http://{web}/api/v1/query?query=drums_graph_stale")["data"]["result"]
            assert [(r["metric"]["host"], r["value"][1]) for r in result] == [(host, "0")]
        finally:
            prometheus.terminate()
            prometheus.wait(10)
