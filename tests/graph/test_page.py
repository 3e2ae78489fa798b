"""The agent's page at `/`, in Debian's headless Chromium: the live graph of real ROS 2 nodes drawn
by the agent, its hosts and probes, updated when a node starts; and a screenshot that is not blank."""
from __future__ import annotations

import re
import socket
import struct
import subprocess
import zlib

import pytest

from tests.agentproc import running_agent
from tests.conftest import eventually

CHROMIUM = ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def chromium(*args: str, profile) -> str:
    done = subprocess.run([*CHROMIUM, f"--user-data-dir={profile}", *args], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def rendered(url: str, profile) -> str:
    """The page's DOM after its scripts ran for a few seconds (its first refresh included)."""
    return chromium("--virtual-time-budget=4000", "--dump-dom", url, profile=profile)


def colours(png: bytes) -> int:
    """How many different byte values the image's pixel rows hold: a blank page has one or two."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    at, data = 8, b""
    while at < len(png):
        length, kind = struct.unpack(">I4s", png[at:at + 8])
        if kind == b"IDAT":
            data += png[at + 8:at + 8 + length]
        at += 12 + length
    return len(set(zlib.decompress(data)))


@pytest.fixture(scope="module")
def agent():
    with running_agent("--graph", "ros2", "--probe", "rcl", "--probe", "loads", "--probe", "sched",
                       "--probe", "process") as url:
        yield url.rsplit("/", 1)[0] + "/"


def test_the_page_shows_the_live_graph_and_follows_it(agent, ros_nodes, tmp_path):
    ros_nodes("talker", "page_talker")
    ros_nodes("listener", "page_listener")

    def shows(*names):
        dom = rendered(agent, tmp_path / "profile")
        texts = set(re.findall(r">([^<>]+)</text>", dom))
        assert set(names) <= texts, texts
        return dom
    dom = eventually(lambda: shows("/page_talker", "/page_listener", "/chatter"), timeout=30)
    state = re.search(r'<span id="state"[^>]*>([^<]*)<', dom).group(1)
    assert state.startswith(f"{socket.gethostname()}, graph ros2, "), state
    hosts = re.search(r'<ul id="hosts">(.*?)</ul>', dom).group(1)
    assert hosts.startswith(f"<li>{socket.gethostname()}"), hosts
    assert "<li>rcl: uprobe</li>" in re.search(r'<ul id="probes">(.*?)</ul>', dom).group(1)
    ros_nodes("idle", "page_latecomer")
    eventually(lambda: shows("/page_latecomer"), timeout=30)


def test_a_screenshot_of_the_page_is_not_blank(agent, tmp_path):
    blank, page = tmp_path / "blank.png", tmp_path / "page.png"
    chromium("--window-size=1000,700", f"--screenshot={blank}", "about:blank", profile=tmp_path / "p1")
    chromium("--window-size=1000,700", "--virtual-time-budget=4000", f"--screenshot={page}", agent,
             profile=tmp_path / "p2")
    assert colours(blank.read_bytes()) <= 8
    assert colours(page.read_bytes()) > 50
