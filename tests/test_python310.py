"""What Python 3.10 can run (ROS 2 Humble's Ubuntu 22.04 has it): no syntax of a later Python in
the project's code, and, without the Grafana Foundation SDK (which has no release for 3.10), every
module of the agent, drums top, drums detect, the demo and the mixin's rules imports, and the whole
test suite is collected (only the tests that build dashboards are skipped then). Python 3.10 itself
is not installable here: this is its import rules, checked on this interpreter."""
import ast
import os
import pkgutil
import subprocess
import sys

import drums

CHECKOUT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WITHOUT_SDK = "import sys; sys.modules['grafana_foundation_sdk'] = None\n"  # importing it raises ImportError


def test_no_code_needs_a_python_later_than_3_10_to_parse():
    for folder in ("drums", "tests", "bench", "deploy", "demo", "scripts"):
        for root, _, names in os.walk(os.path.join(CHECKOUT, folder)):
            for name in names:
                if name.endswith(".py"):
                    path = os.path.join(root, name)
                    with open(path) as f:
                        ast.parse(f.read(), path, feature_version=(3, 10))


def test_without_the_dashboard_sdk_every_module_imports_and_every_test_is_collected(tmp_path):
    modules = [m.name for m in pkgutil.walk_packages(drums.__path__, "drums.") if m.name != "drums.__main__"]
    code = WITHOUT_SDK + "import importlib\n" + "".join(
        f"importlib.import_module({m!r})\n" for m in modules + ["deploy.mixin.build", "deploy.mixin.rules",
                                                              "deploy.mixin.alerts", "bench.readme"])
    out = subprocess.run([sys.executable, "-c", code], cwd=CHECKOUT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    with open(os.path.join(CHECKOUT, "demo", "robot.py")) as f:
        robot = f.read()
    out = subprocess.run([sys.executable, "-c", WITHOUT_SDK + "import ast, sys\n"
                          "for node in ast.parse(sys.stdin.read()).body:\n"
                          "    if isinstance(node, (ast.Import, ast.ImportFrom)):\n"
                          "        exec(compile(ast.Module([node], []), 'demo/robot.py', 'exec'))\n"],
                         input=robot, cwd=CHECKOUT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    out = subprocess.run([sys.executable, "-c", WITHOUT_SDK + "from deploy.mixin.build import main\n"
                          f"sys.exit(main(['--rules-only', '--out', {str(tmp_path)!r}]))"],
                         cwd=CHECKOUT, capture_output=True, text=True, timeout=120)  # as make demo runs it
    assert out.returncode == 0 and sorted(os.listdir(tmp_path)) == ["prometheus_alerts.yaml", "prometheus_rules.yaml"], \
        out.stderr
    collect = subprocess.run([sys.executable, "-c", WITHOUT_SDK + "import pytest\nsys.exit(pytest.main("
                              "['--collect-only', '-q', '-p', 'no:cacheprovider', '-o', 'addopts=', 'tests']))"],
                             cwd=CHECKOUT, capture_output=True, text=True, timeout=300)
    assert collect.returncode == 0, collect.stdout[-3000:] + collect.stderr[-2000:]
    assert " error" not in collect.stdout.splitlines()[-1], collect.stdout[-3000:]
