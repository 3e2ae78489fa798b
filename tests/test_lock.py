"""`make test` runs on exactly the versions the lock files pin (scripts/setup.sh installs them)."""
import os
import re
from importlib.metadata import PackageNotFoundError, version

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def pins(name: str) -> dict[str, str]:
    """{package: version} of the lock file's lines whose markers hold for this interpreter."""
    with open(os.path.join(ROOT, name)) as f:
        text = f.read()
    out = {}
    for line in re.findall(r"^[A-Za-z0-9].*?(?= \\$|$)", text, re.M):
        req = Requirement(line)
        if req.marker is None or req.marker.evaluate():
            (spec,) = req.specifier
            out[canonicalize_name(req.name)] = spec.version
    return out


def test_every_locked_package_is_installed_at_its_pinned_version():
    locked = pins("requirements-test.lock")
    assert len(locked) > 50  # the test extra pulls ROS 2 in: a short list means a broken parse
    installed = {}
    for name in locked:
        try:
            installed[name] = version(name)
        except PackageNotFoundError:
            installed[name] = None
    assert installed == locked


def test_the_agent_lock_agrees_with_the_test_lock():
    agent, test = pins("requirements.lock"), pins("requirements-test.lock")
    assert agent and {name: test.get(name) for name in agent} == agent
