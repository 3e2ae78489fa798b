"""The job API under a schema-driven fuzzer: schemathesis generates requests from the OpenAPI document
a real `drums agent` serves (/drums/v1/openapi.json), valid and invalid ones, and checks every answer
against that document; the agent must answer them all without a 5xx, a traceback or a leak."""
import json
import subprocess
import sys
import time
import urllib.request
from urllib.parse import urlsplit

import psutil

from tests.agentproc import running_agent, samples, scrape
from tests.test_api import PROBES, call

TOKEN = "fuzz-token"
READ_ONLY = (["info"], ["jobs"], ["openapi.json"])  # paths under /drums/v1 that take only GET
MIN_REQUESTS = 2000
# Bytes of USS. The agent watches the whole host, and its memory follows the host's processes: in
# the second lane, beside the main lane's hundreds, it grew 7.5 and 9.7 MB in fresh CI runs. So the
# fuzzer runs in the main lane, one test at a time.
MAX_GROWTH = 5 << 20


def fuzz(api: str, tmp_path, name: str, max_examples: int, *args: str) -> list[dict]:
    """One `schemathesis run` with every check against the agent's own document; asserts that no
    check failed and no request errored, and returns the HAR entries: every request it really sent,
    with its answer."""
    har, report = tmp_path / f"{name}.har", tmp_path / f"{name}.json"
    # The CLI rather than the Python API: it runs every phase (coverage's boundary and wrong-method
    # cases, fuzzing, stateful) and every check, and reports what it sent.
    out = subprocess.run(
        [sys.executable, "-m", "schemathesis.cli", "run", f"{api}/openapi.json", "--checks", "all",
         "--max-examples", str(max_examples), "--request-timeout", "10", "--generation-database", "none",
         "--no-color", "--report", "json,har", "--report-har-path", str(har), "--report-json-path", str(report),
         *args], capture_output=True, text=True, timeout=120, cwd=tmp_path)  # its .schemathesis cache too
    result = json.loads(report.read_text())
    assert (result["exit_code"], result["failures"], result["errors"]) == (0, [], []), out.stdout[-20000:]
    assert out.returncode == 0, out.stdout[-20000:] + out.stderr
    entries = json.loads(har.read_text())["log"]["entries"]
    # Our own reading of every answer, besides schemathesis's checks: never a 5xx, and JSON whenever
    # there is a body (204 has none).
    assert [e["request"]["url"] for e in entries if e["response"]["status"] >= 500] == []
    for e in entries:
        response = e["response"]
        if response["status"] == 204:
            assert response["content"]["size"] == 0, e
        else:
            assert response["content"]["mimeType"] == "application/json", e
            assert "error" in json.loads(response["content"]["text"]) or response["status"] < 300, e
    return entries


def agent_process(url: str) -> psutil.Process:
    """The `drums agent` running_agent started for `url`: our child with its port on the command line."""
    port = str(urlsplit(url).port)
    found = [p for p in psutil.Process().children() if "agent" in p.cmdline() and port in p.cmdline()]
    assert len(found) == 1, found
    return found[0]


def uss(agent: psutil.Process) -> int:
    """The agent's unique memory at rest: the least of a few readings, so that an allocation that
    is only passing through (a thread's stack, a sample being taken) is not counted as growth."""
    readings = []
    for _ in range(5):
        readings.append(agent.memory_full_info().uss)
        time.sleep(0.1)
    return min(readings)


def clear_jobs(api: str) -> None:
    """Deletes every job, so that memory is compared between two agents in the same state."""
    code, listing = call("GET", f"{api}/jobs")
    assert code == 200
    for job in listing["jobs"]:
        assert call("DELETE", f"{api}/monitor/{job['id']}", token=TOKEN) == (204, None)
    assert call("GET", f"{api}/jobs") == (200, {"jobs": []})
    time.sleep(0.5)  # the jobs thread finishes a sample it may have started for a deleted job


def test_the_api_survives_a_schema_driven_fuzzer(tmp_path):
    (tmp_path / "token").write_text(TOKEN)
    (tmp_path / "token").chmod(0o600)
    # With a token even on loopback: the run that carries it reaches every mutation, the run that
    # does not gets the 401s.
    with running_agent(*PROBES, "--token-file", str(tmp_path / "token")) as url:
        agent = agent_process(url)
        api = url.rsplit("/", 1)[0] + "/drums/v1"
        auth = ("-H", f"Authorization: Bearer {TOKEN}")
        start = time.monotonic()
        # Warm-up: imports, the document, thread stacks and the allocator's arenas, first used here.
        fuzz(api, tmp_path, "warm-up", 100, *auth)
        clear_jobs(api)
        before = uss(agent)

        with_token = fuzz(api, tmp_path, "with-token", 200, *auth)
        statuses = {(e["request"]["method"], e["response"]["status"]) for e in with_token}
        # The token opened the mutations: jobs were made, changed and deleted.
        assert {("POST", 201), ("POST", 200), ("DELETE", 204)} <= statuses, statuses

        jobs = [(j["id"], j["interval"]) for j in call("GET", f"{api}/jobs")[1]["jobs"]]
        without_token = fuzz(api, tmp_path, "without-token", 40)
        # Without the token no mutation went through: a 401, or the 405 of a read-only path.
        for e in without_token:
            method, path = e["request"]["method"], urlsplit(e["request"]["url"]).path
            parts = [p for p in path[len("/drums/v1"):].split("/") if p]  # as the agent splits it
            if method in ("POST", "DELETE"):
                assert e["response"]["status"] == (405 if parts in READ_ONLY else 401), e
        # Nothing made or changed without the token. A job may have ended meanwhile by itself: its
        # lease ran out, or its process ended (the fuzzer's jobs carry leases and PIDs of its own).
        after = [(j["id"], j["interval"]) for j in call("GET", f"{api}/jobs")[1]["jobs"]]
        assert set(after) <= set(jobs), set(after) - set(jobs)
        took = time.monotonic() - start

        clear_jobs(api)
        growth = uss(agent) - before
        sent = len(with_token) + len(without_token)
        print(f"\n{sent} requests in {took:.1f} s (with the warm-up); agent USS {before / 2**20:.1f} MiB, "
              f"grew {growth / 2**10:+.0f} KiB")
        assert sent >= MIN_REQUESTS, sent
        assert growth < MAX_GROWTH, f"the agent's USS grew {growth} bytes"
        assert agent.is_running() and agent.status() != psutil.STATUS_ZOMBIE
        assert urllib.request.urlopen(f"{api}/info", timeout=10).status == 200
        # Still collecting: every probe's last collect succeeded.
        assert samples(scrape(url), "drums_probe_collect_success") == {
            (("probe", p),): 1.0 for p in ("sockets", "sched", "process", "host")}
    # running_agent has stopped the agent: exit status 0, no traceback in its log, no pins left.
