"""The job API of `drums agent` (/drums/v1), over HTTP, against known processes and traffic."""
import json
import os
import socket
import subprocess
import sys
import urllib.error
import urllib.request

import psutil
import pytest

from tests.agentproc import running_agent, scrape
from tests.conftest import eventually

PROBES = ("--probe", "sockets", "--probe", "sched", "--probe", "process", "--probe", "host", "--graph", "auto")

# Burns argv[1] s of CPU, connects to port argv[2] and sends argv[3] bytes, says so, then waits.
CLIENT = r'''
import socket, sys, time
while time.process_time() < float(sys.argv[1]): pass
s = socket.create_connection(("127.0.0.1", int(sys.argv[2])))
s.sendall(b"x" * int(sys.argv[3]))
print(time.process_time(), s.getsockname()[1], flush=True)
sys.stdin.read()
'''


@pytest.fixture(scope="module")
def api():
    with running_agent(*PROBES) as url:
        yield url.rsplit("/", 1)[0] + "/drums/v1"


def call(method: str, url: str, body=None, token: str = ""):
    data = body if isinstance(body, bytes) or body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, method=method)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as reply:
            text = reply.read()
            return reply.status, json.loads(text) if text else None
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def sample_of(api: str, job: str, check, timeout: float = 10):
    """The job's latest sample once `check(series)` holds."""
    def ready():
        code, job_view = call("GET", f"{api}/monitor/{job}")
        assert code == 200, job_view
        series = (job_view["sample"] or {}).get("series", [])
        assert check(series), f"{job}: {series}"
        return series
    return eventually(ready, timeout)


def value(series, name, **labels):
    found = [s["value"] for s in series if s["name"] == name and labels.items() <= s["labels"].items()]
    assert len(found) <= 1, found
    return found[0] if found else None


@pytest.fixture
def traffic():
    """A listener here, and a child that burns CPU and sends it a known number of bytes."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    child = subprocess.Popen([sys.executable, "-c", CLIENT, "0.2", str(port), "12345"], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    conn, _ = listener.accept()
    got = 0
    while got < 12345:
        got += len(conn.recv(65536))
    burned, client_port = child.stdout.readline().split()
    yield child, float(burned), port, int(client_port)
    child.kill()
    child.wait()
    conn.close()
    listener.close()


def test_pid_job_samples_the_process(api, traffic):
    child, burned, _, _ = traffic
    code, job = call("POST", f"{api}/monitor/pid/{child.pid}", {"interval": 0.2})
    assert code == 201 and job["id"] == f"pid/{child.pid}" and job["interval"] == 0.2
    assert job["stream"]["key"] == f"{socket.gethostname()}:pid:{child.pid}"
    # A sample taken after the child's last CPU time was counted: a sample between its print and its
    # switch out (a moment later) would still lack the slice it was running; an agent that never
    # counts it fails here.
    series = sample_of(api, f"pid/{child.pid}", lambda s: value(s, "drums_process_socket_sent_bytes_total",
                                                               protocol="tcp") is not None
                       and value(s, "drums_process_cpu_seconds_total") >= burned)
    assert value(series, "drums_process_socket_sent_bytes_total", protocol="tcp") == 12345
    assert value(series, "drums_socket_sent_bytes_total", protocol="tcp") == 12345  # its one socket's own row
    assert burned <= value(series, "drums_process_cpu_seconds_total") <= burned + 0.05
    assert value(series, "drums_process_resident_memory_bytes") == pytest.approx(
        psutil.Process(child.pid).memory_info().rss, rel=0.05)
    assert {s["labels"]["pid"] for s in series} == {str(child.pid)}

    code, again = call("POST", f"{api}/monitor/pid/{child.pid}", {"interval": 2})
    assert (code, again["interval"]) == (200, 2.0)
    assert [j["id"] for j in call("GET", f"{api}/jobs")[1]["jobs"]] == [f"pid/{child.pid}"]
    assert call("DELETE", f"{api}/monitor/pid/{child.pid}") == (204, None)
    assert call("GET", f"{api}/monitor/pid/{child.pid}") == (404, {"error": f"no job pid/{child.pid}"})


def test_socket_jobs_by_port_and_direction(api, traffic):
    child, _, port, client_port = traffic
    for direction in ("src", "dst", "any"):
        assert call("POST", f"{api}/monitor/socket/tcp/{direction}/{port}", {"interval": 0.2})[0] == 201
    name = "drums_socket_received_bytes_total"
    src = sample_of(api, f"socket/tcp/src/{port}", lambda s: value(s, name, pid=str(os.getpid())))
    # The listening socket on the port carries nothing; the accepted one got the bytes.
    assert value(src, name, local=f"127.0.0.1:{port}", remote=f"127.0.0.1:{client_port}") == 12345
    dst = sample_of(api, f"socket/tcp/dst/{port}", lambda s: value(s, "drums_socket_sent_bytes_total"))
    assert [(s["labels"]["pid"], s["value"]) for s in dst if s["name"] == "drums_socket_sent_bytes_total"] == [
        (str(child.pid), 12345)]
    both = sample_of(api, f"socket/tcp/any/{port}", lambda s: len(s) >= len(src) + len(dst))
    assert sorted(json.dumps(s["labels"], sort_keys=True) for s in both if s["name"] == name) == sorted(
        json.dumps(s["labels"], sort_keys=True) for s in src + dst if s["name"] == name)
    for direction in ("src", "dst", "any"):
        assert call("DELETE", f"{api}/monitor/socket/tcp/{direction}/{port}")[0] == 204


def test_host_job_and_info(api):
    assert call("POST", f"{api}/monitor/host")[0] == 201
    series = sample_of(api, "host", lambda s: value(s, "drums_host_memory_total_bytes"))
    assert value(series, "drums_host_memory_total_bytes") == psutil.virtual_memory().total
    assert all(s["name"].startswith("drums_host_") for s in series)
    assert call("DELETE", f"{api}/monitor/host")[0] == 204
    code, info = call("GET", f"{api}/info")
    assert code == 200 and info["host"] == socket.gethostname() and info["token_required"] is False
    assert {p: v["attached"] for p, v in info["probes"].items()} == dict.fromkeys(
        ("sockets", "sched", "process", "host"), True)
    code, document = call("GET", f"{api}/openapi.json")
    assert code == 200 and set(document["paths"]) == {
        "/info", "/jobs", "/openapi.json", "/monitor/host", "/monitor/pid/{pid}", "/monitor/latency/{target}",
        "/monitor/socket/{protocol}/{direction}/{port}", "/monitor/topic/{topic}"}


def test_a_job_whose_lease_is_not_renewed_ends_by_itself(api):
    import time
    code, job = call("POST", f"{api}/monitor/host", {"interval": 0.5, "lease": 2})
    assert code == 201 and job["lease"] == 2 and 1.9 <= job["expires_in"] <= 2
    time.sleep(1.2)
    code, job = call("POST", f"{api}/monitor/host", {"interval": 0.5, "lease": 2})  # renewed: 2 s again
    assert code == 200 and job["expires_in"] >= 1.9
    time.sleep(1.2)
    assert [j["id"] for j in call("GET", f"{api}/jobs")[1]["jobs"]] == ["host"]  # 2.4 s old, renewed at 1.2

    def ended():
        assert call("GET", f"{api}/jobs") == (200, {"jobs": []})
    began = time.monotonic()
    eventually(ended, timeout=3)
    assert time.monotonic() - began < 1.5  # it ran out 2 s after its renewal, not later


def test_a_process_job_ends_with_its_process(api):
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    assert call("POST", f"{api}/monitor/pid/{proc.pid}", {"interval": 0.2})[0] == 201
    proc.stdin.close()
    proc.wait()

    def ended():
        assert call("GET", f"{api}/jobs") == (200, {"jobs": []})
    eventually(ended, timeout=2)


@pytest.mark.parametrize("method, path, body, code, error", [
    ("POST", "monitor/pid/abc", None, 400, "pid 'abc': a process ID is a whole number from 1 to 4194303"),
    ("POST", "monitor/pid/0", None, 400, "pid '0': a process ID is a whole number from 1 to 4194303"),
    ("POST", "monitor/pid/4194000", None, 404, "no process 4194000"),
    ("POST", "monitor/socket/sctp/src/1", None, 400, "protocol 'sctp': one of tcp, udp"),
    ("POST", "monitor/socket/tcp/up/1", None, 400, "direction 'up': one of src, dst, any"),
    ("POST", "monitor/socket/tcp/src/70000", None, 400, "port '70000': a whole number from 1 to 65535"),
    ("POST", "monitor/socket/tcp/src", None, 400, "a socket job is /drums/v1/monitor/socket/<tcp|udp>/<src|dst|any>/<port>"),
    ("POST", "monitor/topic/camera/im-age", None, 400, "topic 'camera/im-age': a ROS topic name of letters, digits "
     "and _ between slashes, as in /drums/v1/monitor/topic/camera/image"),
    ("POST", "monitor/topic/nowhere", None, 404, "no topic /nowhere in the graph"),
    ("POST", "monitor/host", b"{bad", 400, "the body is not JSON (Expecting property name enclosed in double quotes: line 1 column 2 (char 1))"),
    ("POST", "monitor/host", [1], 400, "the body is a JSON object, not list"),
    ("POST", "monitor/host", b"\x0b", 400, "the body is not JSON (Expecting value: line 1 column 1 (char 0))"),
    ("POST", "monitor/host", b"\t", 400, "the body is not JSON (Expecting value: line 1 column 2 (char 1))"),
    ("POST", "monitor/host", {"interval": "x"}, 400, "interval: a number of seconds, not 'x'"),
    ("POST", "monitor/host", {"interval": 0}, 400, "interval: 0 s is outside 0.1-3600 s"),
    ("POST", "monitor/host", {"every": 1}, 400, "unknown field 'every': a host job takes interval, lease"),
    ("POST", "monitor/host", {"lease": 0.5}, 400, "lease: 0.5 s is outside 1-3600 s"),
    ("POST", "monitor/host", {"lease": True}, 400, "lease: a number of seconds, not True"),
    ("POST", "monitor/host", b"x" * (65 << 10), 413, "a body over 64 KiB"),
    ("POST", "monitor/cpu", None, 404, "no such path /drums/v1/monitor/cpu"),
    ("DELETE", "monitor/host", None, 404, "no job host"),
    ("PUT", "jobs", None, 405, "PUT: the API takes GET, POST and DELETE"),
    ("POST", "info", None, 405, "POST /drums/v1/info: only GET"),
])
def test_bad_requests_get_a_4xx_that_says_why(api, method, path, body, code, error):
    assert call(method, f"{api}/{path}", body) == (code, {"error": error})
    assert call("GET", f"{api}/jobs") == (200, {"jobs": []})


@pytest.mark.parametrize("request_head, code, reason", [
    # Bytes that str.isdigit() takes for digits but int() refuses ("\xb2" is a superscript two): the
    # HTTP parser refuses them before any of our code reads a number.
    (b"POST /drums/v1/monitor/pid/\xb2 HTTP/1.0\r\n", 400, b"illegal request line\n"),
    (b"POST /drums/v1/monitor/host HTTP/1.0\r\nContent-Length: \xb2\r\n", 400, b"bad Content-Length\n"),
    (b"GET /" + b"a" * (17 << 10) + b" HTTP/1.0\r\n", 431, b"a request head over 16 KiB\n"),
    (b"GET /" + b"a" * (17 << 10) + b" HTTP/1.0\r\nX: 1", 431, b"a request head over 16 KiB\n"),  # unfinished
    (b"GET /metrics HTTP/1.0\r\n" + b"".join(b"X-%d: 1\r\n" % i for i in range(65)), 431,
     b"more than 64 header lines\n"),
])
def test_requests_the_http_parser_refuses_are_a_4xx_that_says_why(api, request_head, code, reason):
    host, port = api.split("/")[2].split(":")
    with socket.create_connection((host, int(port))) as s:
        s.sendall(request_head + b"\r\n")
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
    head, _, body = answer.partition(b"\r\n\r\n")
    assert (head.split(b" ")[1], body) == (str(code).encode(), reason)
    assert b"\r\nconnection: close" in head.lower()


def test_a_body_nested_too_deep_or_sent_in_chunks_is_read(api):
    assert call("POST", f"{api}/monitor/host", b"[" * 60000) == (400, {"error": "the body is not JSON (nested too deep)"})

    def chunks():
        yield b'{"interval":'
        yield b' 2}'
    request = urllib.request.Request(f"{api}/monitor/host", data=chunks(), method="POST",
                                     headers={"Transfer-Encoding": "chunked"})
    with urllib.request.urlopen(request, timeout=10) as reply:
        assert (reply.status, json.loads(reply.read())["interval"]) == (201, 2.0)
    assert call("DELETE", f"{api}/monitor/host")[0] == 204


def test_off_loopback_the_agent_needs_a_token_and_mutations_carry_it(tmp_path):
    out = subprocess.run([sys.executable, "-m", "drums", "agent", "--address", "0.0.0.0", "--port", "0"],
                         capture_output=True, text=True, timeout=30, env={**os.environ, "DRUMS_TOKEN": ""})
    assert (out.returncode, out.stdout) == (2, "")
    assert out.stderr == ("drums: --address 0.0.0.0: off loopback the job API needs a token "
                          "(--token-file FILE or $DRUMS_TOKEN)\n")
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-token\n")
    token_file.chmod(0o640)  # a token others may read is refused, as ssh refuses such keys
    out = subprocess.run([sys.executable, "-m", "drums", "agent", "--address", "0.0.0.0", "--port", "0",
                          "--token-file", str(token_file)], capture_output=True, text=True, timeout=30)
    assert (out.returncode, out.stdout) == (2, "")
    assert out.stderr == f"drums: --token-file {token_file}: readable by others (mode 640); chmod 600 {token_file}\n"
    token_file.chmod(0o600)
    with running_agent("--address", "0.0.0.0", "--token-file", str(token_file), "--probe", "host",
                       "--graph", "auto", bpf=False) as url:  # beside the module's agent: no pins of its own
        api = url.rsplit("/", 1)[0] + "/drums/v1"
        for token in ("", "s3cret-toke", "s3cret-token2"):
            assert call("POST", f"{api}/monitor/host", token=token) == (
                401, {"error": "a valid token is needed: Authorization: Bearer <token>"})
        assert call("POST", f"{api}/monitor/host", token="s3cret-token")[0] == 201
        assert call("DELETE", f"{api}/monitor/host")[0] == 401
        assert call("DELETE", f"{api}/monitor/host", token="s3cret-token")[0] == 204
        assert "drums_host_memory_total_bytes" in scrape(url)  # Prometheus needs no token
        assert call("GET", f"{api}/info")[1]["token_required"] is True
