"""The agent as users run it: `drums agent` in its own process, scraped over HTTP."""
import ctypes
import gzip
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

import psutil
import pytest

from drums.client import Agent
from drums.selfcost import MEMORY_EVERY
from tests.agentproc import free_port, running_agent, samples, scrape, series_begun, serving
from tests.conftest import TEST_PIN_ROOT, connected_pairs, eventually, offered_paths, settle, spliced_from


@pytest.fixture(scope="module")
def agent():
    with running_agent() as url:
        yield url


def test_promtool_finds_nothing_in_live_metrics(agent):
    text = scrape(agent)
    result = subprocess.run(["promtool", "check", "metrics"], input=text, capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout == "" and result.stderr == "", result.stdout + result.stderr


def test_a_scrape_asked_for_gzip_is_the_same_page_gzipped(agent):
    request = urllib.request.Request(agent, headers={"Accept-Encoding": "gzip"})
    with urllib.request.urlopen(request, timeout=10) as reply:
        assert reply.headers["Content-Encoding"] == "gzip"
        text = gzip.decompress(reply.read()).decode()
    plain = scrape(agent)  # another collect: the same series, other values
    assert [line.split(" ")[0] for line in text.splitlines() if "drums_probe_attached" in line] == \
        [line.split(" ")[0] for line in plain.splitlines() if "drums_probe_attached" in line]
    assert len(gzip.compress(text.encode())) * 5 < len(text)  # label text compresses at least 5 to 1


def test_a_page_says_when_its_counters_were_read_so_a_rate_over_two_is_true(agent):
    # Two reads of a process that burns one thread: its CPU seconds over the time between the
    # agent's reads of its counters (not between the requests: each may wait on a loaded host)
    # stay within what one core can give.
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    client = Agent(agent.rsplit("/", 1)[0])

    def read():
        began = time.time()
        text, at = client.read("/metrics")
        assert began <= at <= time.time()
        cpu = samples(text, "drums_process_cpu_seconds_total")
        seconds = next((v for k, v in cpu.items() if dict(k)["pid"] == str(burner.pid)), None)
        assert seconds is not None, "the burner has no series yet"
        return seconds, at

    try:
        # A page may be read before the burner was first switched out, so before it has a series.
        before, t0 = eventually(read, timeout=10)
        time.sleep(2)
        after, t1 = read()
        assert 0.3 <= (after - before) / (t1 - t0) <= 1.03, (before, t0, after, t1)
        _, at = client.read("/graph?format=json")
        assert t1 < at <= time.time()
    finally:
        burner.kill()
        burner.wait()


def attached(url: str) -> dict[str, tuple[str, float]]:
    return {dict(k)["probe"]: (dict(k)["attach_type"], v) for k, v in samples(scrape(url), "drums_probe_attached").items()}


@pytest.mark.kernel
def test_every_probe_attached_with_its_attach_type(agent, record_property):
    from drums.probes import loads, rcl, rtps, sched, sockets, tcp
    best = {cls.name: offered_paths(cls)[0] for cls in (sockets.SocketsProbe, sched.SchedProbe, tcp.TcpProbe,
                                                         rtps.RtpsProbe, rcl.RclProbe, loads.LoadsProbe)}
    seen = attached(agent)
    record_property("attached", json.dumps({probe: path for probe, (path, _) in seen.items()}))  # make test-kernels' row
    # Where the graph is ros2 (rclpy importable) the per-topic probes run too. Each BPF probe takes
    # the best path this kernel offers (tp_btf for sockets and sched on Linux >= 6.6).
    from drums.graph.registry import default
    ros2 = {"rtps": (best["rtps"], 1), "rcl": (best["rcl"], 1), "loads": (best["loads"], 1)} \
        if default() == "ros2" else {}
    assert seen == {"sockets": (best["sockets"], 1), "sched": (best["sched"], 1),
                               "tcp": (best["tcp"], 1), "host": ("psutil", 1), "process": ("psutil", 1),
                               "latency": ("icmp", 1), **ros2}


@pytest.mark.kernel
def test_attach_holds_a_probe_to_the_path_it_names():
    from drums.probes import sched
    path = offered_paths(sched.SchedProbe)[-1]
    with running_agent("--probe", "sockets", "--probe", "sched", "--attach", "sockets=fallback",
                       "--attach", f"sched={path}", "--strict") as url:
        assert attached(url) == {"sockets": ("sock_diag", 1), "sched": (path, 1)}


@pytest.mark.kernel
def test_with_splice_tracepoints_what_splice_takes_from_a_socket_is_counted():
    """`--splice-tracepoints`, on this kernel's first path (a kernel without kprobes: the syscall
    tracepoints): a socket's series grows by exactly what splice(2) took from it."""
    r, w = os.pipe()
    try:
        with running_agent("--probe", "sockets", "--splice-tracepoints", "--pid", str(os.getpid())) as url, \
                connected_pairs(1) as [(tx, rx)]:
            ino = str(os.fstat(rx.fileno()).st_ino)

            def received() -> float:
                found = [v for labels, v in samples(scrape(url), "drums_socket_received_bytes_total").items()
                         if dict(labels).get("inode") == ino]
                assert len(found) == 1, f"series of socket {ino}: {found}"
                return found[0]
            spliced_from(tx, rx, 1000, (r, w))
            begun = eventually(received, 10)  # a series counts from the scrape that first saw it
            spliced_from(tx, rx, 1 << 20, (r, w))

            def grown() -> None:
                assert received() == begun + (1 << 20)
            eventually(grown, 10)
    finally:
        os.close(r)
        os.close(w)


@pytest.mark.kernel
def test_without_kernel_btf_the_agent_counts_with_the_btf_file_it_is_given(tmp_path):
    """A kernel built without BTF (Raspberry Pi OS's): the agent, with /sys/kernel/btf hidden in a
    mount namespace of its own, takes its struct offsets from the file it is given (a copy of this
    kernel's BTF, as pahole would make it), each BPF probe takes a path that needs no kernel BTF,
    and the bytes a child sends and the CPU it burns once its series began are counted exactly."""
    from drums.kernel.features import Features
    from drums.probes import sched, sockets, tcp
    btf = tmp_path / "vmlinux.btf"
    shutil.copy("/sys/kernel/btf/vmlinux", btf)
    without = Features(str(btf))
    without.__dict__["has_btf"] = False
    best = {cls.name: next(p.name for p in cls.paths if p.requires(without) is None)
            for cls in (sockets.SocketsProbe, sched.SchedProbe, tcp.TcpProbe)}
    assert best["sockets"] in ("raw_tracepoint", "kprobe") and best["sched"] == "raw_tracepoint"
    hide = ("unshare", "--mount", "--propagation", "private", "sh", "-c",
            'mount -t tmpfs none /sys/kernel/btf && exec "$@"', "hide")
    with running_agent("--btf", str(btf), "--probe", "sockets", "--probe", "sched", "--probe", "tcp", "--strict",
                       under=hide) as url:
        assert attached(url) == {p: (path, 1) for p, path in best.items()}
        size = 1_234_567
        with socket.create_server(("127.0.0.1", 0)) as server:
            child = subprocess.Popen([sys.executable, "-c", f"""
import socket, sys, time
s = socket.create_connection(("127.0.0.1", {server.getsockname()[1]}))
s.send(b"a")
print(flush=True); sys.stdin.readline()
s.sendall(b"b" * {size})
end = time.process_time() + 0.5
while time.process_time() < end: pass
print(flush=True); sys.stdin.readline()"""], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            conn, _ = server.accept()
            child.stdout.readline()
            clock = ((~child.pid) << 3) | 2  # its process CPU clock
            try:
                series_begun(url, "drums_process_socket_sent_bytes_total", child.pid)
                series_begun(url, "drums_process_cpu_seconds_total", child.pid)
                # Once the child sleeps its CPU time is the kernel's own runtime at its last switch-out:
                # the agent's value then and the clock's are the same moment (read sooner, the series
                # might have begun while the child still ran to its read).
                settle(child.pid)
                cpu_before = series_begun(url, "drums_process_cpu_seconds_total", child.pid)
                began = time.clock_gettime(clock)
                child.stdin.write("go\n")
                child.stdin.flush()
                got = 0
                while got < size + 1:
                    got += len(conn.recv(1 << 20))
                child.stdout.readline()

                def counted():
                    text = scrape(url)
                    sent = {dict(k)["pid"]: v for k, v in samples(text, "drums_process_socket_sent_bytes_total").items()}
                    cpu = {dict(k)["pid"]: v for k, v in samples(text, "drums_process_cpu_seconds_total").items()}
                    pid = str(child.pid)
                    assert sent.get(pid) == size and cpu.get(pid, 0) > 0, (sent.get(pid), cpu.get(pid))
                    return cpu[pid]
                cpu = eventually(counted, timeout=10) - cpu_before
                kernel = time.clock_gettime(clock) - began
                assert abs(cpu - kernel) <= 1e-6, (cpu, kernel)
            finally:
                child.stdin.close()
                child.wait()
                conn.close()


def test_exited_process_series_gone_within_two_scrapes(agent):
    child = subprocess.Popen([sys.executable, "-c", "import sys, time\n"
                              "print(time.process_time(), flush=True); sys.stdin.readline()\n"
                              "end = time.process_time() + 0.3\n"
                              "while time.process_time() < end: pass\n"
                              "print(time.process_time(), flush=True)\nsys.stdin.read()"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    pid = str(child.pid)
    began = float(child.stdout.readline())
    series_begun(agent, "drums_process_cpu_seconds_total", child.pid)
    child.stdin.write("go\n")
    child.stdin.flush()
    burned = float(child.stdout.readline()) - began
    cpu = samples(scrape(agent), "drums_process_cpu_seconds_total")
    assert any(dict(k)["pid"] == pid and burned - 0.05 <= v <= burned + 0.05 for k, v in cpu.items()), (burned, cpu)
    child.stdin.close()
    child.wait()
    gone_after = None
    for n in (1, 2):
        text = scrape(agent)
        if f'pid="{pid}"' not in text:
            gone_after = n
            break
    assert gone_after is not None, "exited process still exported after two scrapes"


def test_unknown_path_is_404_and_agent_keeps_serving(agent):
    base = agent.rsplit("/", 1)[0]
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(base + "/nope", timeout=5)
    assert e.value.code == 404
    assert "drums_agent_cpu_seconds_total" in scrape(agent)


def test_clients_that_hang_up_before_the_answer_cost_no_traceback(agent):
    """A scrape takes tens of milliseconds; a client gone by then must not put a traceback in the
    log (the fixture checks the log when the agent stops)."""
    host, port = agent.split("/")[2].split(":")
    for _ in range(5):
        with socket.create_connection((host, int(port))) as s:
            s.sendall(b"GET /metrics HTTP/1.0\r\n\r\n")
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # reset on close
    assert "drums_agent_cpu_seconds_total" in scrape(agent)


@pytest.mark.parametrize("argv, message", [
    (["agent", "--port", "70000"], "--port: 70000 is not a port"),
    (["record", "--output", "/etc/hostname"], "--output /etc/hostname: File exists"),
    (["record", "--output", "/nonexistent/x.mcap"], "--output /nonexistent/x.mcap: No such file or directory"),
    (["record", "--output", "/tmp/x.mcap", "--agent", "ftp://x"], "--agent ftp://x: an agent's URL is http://HOST:PORT"),
    (["record"], "the following arguments are required: --output"),
    (["agent", "--port", "http"], "'http' is not a whole number"),
    (["agent", "--bogus"], "unrecognized arguments: --bogus"),
    (["agent", "--pid", "2147483646"], "--pid 2147483646: no such process"),
    (["agent", "--process-name", "(["], "not a regular expression"),
    (["agent", "--no-probe", "nope"], "invalid choice: 'nope'"),
    (["agent", "--attach", "sockets"], "'sockets' is not PROBE=PATH"),
    (["agent", "--attach", "sockets=pigeon"],
     "probe sockets has no such path (tp_btf, raw_tracepoint, fentry, kprobe, fallback)"),
    (["agent", "--attach", "host=kprobe"], "probe host has no such path (it has no attach paths)"),
    (["agent", "--probe", "sched", "--attach", "sockets=kprobe"], "--attach sockets=...: no such probe runs"),
    (["frobnicate"], "invalid choice: 'frobnicate'"),
    (["agent", "--btf", "/etc/passwd"], "--btf: not a BTF blob (bad magic)"),
    (["doctor", "--btf", "/nonexistent"], "--btf: cannot read kernel BTF at /nonexistent: No such file or directory"),
    (["agent", "--graph", "auto", "--graph-file", "robot.yaml"], "--graph-file is read by --graph static only, not by --graph auto"),
    (["graph", "--graph", "ros1", "--graph-file", "robot.yaml"], "--graph-file is read by --graph static only, not by --graph ros1"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message):
    out = subprocess.run([sys.executable, "-m", "drums", *argv], capture_output=True, text=True, timeout=30)
    assert out.returncode == 2
    assert out.stdout == ""
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("drums: ") and message in lines[0], out.stderr


def test_sigterm_that_the_kernel_hands_to_another_thread_stops_the_agent():
    """The kernel may deliver a SIGTERM for the process to any of its threads; Python runs the
    handler in the main thread, which must wake to do so (an agent waiting untimed slept through
    it until killed). Sent to each other thread in turn, with tgkill, it stops the agent."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "drums", "agent", "--port", str(port), "--stream-port", "0",
                             "--probe", "host", "--graph", "auto"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        serving(proc, f"http://127.0.0.1:{port}/metrics")
        others = [int(t) for t in os.listdir(f"/proc/{proc.pid}/task") if int(t) != proc.pid]
        assert others
        tgkill = {"x86_64": 234, "aarch64": 131}[os.uname().machine]  # the syscall's number
        assert ctypes.CDLL(None, use_errno=True).syscall(tgkill, proc.pid, others[-1], signal.SIGTERM) == 0
        assert proc.wait(timeout=10) == 0
    finally:
        proc.kill()
        proc.wait()


def test_sigusr2_writes_what_each_thread_does_to_the_log_and_the_agent_goes_on():
    """`kill -USR2` on a stuck agent says where each of its threads is, and stops nothing."""
    logs: list[str] = []
    with running_agent("--probe", "host", "--graph", "auto", bpf=False, logs=logs) as url:
        port = urllib.parse.urlsplit(url).port
        (agent,) = [p for p in psutil.process_iter(["cmdline"])
                    if "agent" in (p.info["cmdline"] or []) and str(port) in (p.info["cmdline"] or [])]
        agent.send_signal(signal.SIGUSR2)
        time.sleep(0.5)
        assert scrape(url) and agent.is_running()
    threads = re.findall(r"^(?:Current thread|Thread) 0x[0-9a-f]+", logs[0], re.M)
    assert len(threads) >= 3 and 'File "' in logs[0], logs[0][-2000:]


@pytest.mark.parametrize("taken, said", [("--port", "cannot listen on"),
                                         ("--stream-port", "cannot publish the stream on")])
def test_port_in_use_is_one_line(taken, said):
    """The /metrics port, or the stream's, which is held from start though ZeroMQ comes later."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        ports = {"--port": "0", "--stream-port": "0", taken: str(port)}
        out = subprocess.run([sys.executable, "-m", "drums", "agent", "--probe", "host",
                              *[arg for flag, value in ports.items() for arg in (flag, value)]],
                             capture_output=True, text=True, timeout=30)
    assert out.returncode == 2
    assert out.stderr.strip() == f"drums: {said} 127.0.0.1:{port}: Address already in use"


def test_strict_refuses_when_a_probe_cannot_attach(tmp_path):
    # Hide kernel BTF from the agent's view by running it without privileges: BPF probes cannot attach.
    nobody = shutil.which("setpriv")
    assert nobody, "setpriv (util-linux) is needed for this test"
    out = subprocess.run([nobody, "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-m",
                          "drums", "agent", "--port", "0", "--stream-port", "0", "--strict"],
                         capture_output=True, text=True, timeout=30, cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.startswith("drums: probe sockets: not root") and "(--strict)" in out.stderr


def check_graph_live(url: str) -> None:
    text = scrape(url)
    assert samples(text, "drums_graph_stale") == {(("adapter", "ros2"),): 0.0}
    assert samples(text, "drums_graph_entities")[(("kind", "host"),)] == 1


def test_without_ebpf_every_probe_runs_on_a_fallback(tmp_path):
    """As an unprivileged user no BPF program can load: the agent runs on /proc and sock_diag."""
    port = free_port()
    proc = subprocess.Popen(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable,
                             "-m", "drums", "agent", "--port", str(port), "--stream-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                text = scrape(f"http://127.0.0.1:{port}/metrics")
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()
                time.sleep(0.1)
        attached = {dict(k)["probe"]: (dict(k)["attach_type"], v)
                    for k, v in samples(text, "drums_probe_attached").items()}
        # The per-topic probes have no fallback: nothing outside the kernel sees RTPS or rcl calls.
        assert attached == {"sockets": ("sock_diag", 1), "sched": ("proc", 1), "tcp": ("sock_diag", 1),
                            "host": ("psutil", 1), "process": ("psutil", 1), "rtps": ("none", 0),
                            "rcl": ("none", 0), "loads": ("none", 0), "latency": ("icmp-unprivileged", 1)}
        assert samples(text, "drums_process_cpu_seconds_total")
        # The ros2 graph works unprivileged too (HOME is still /root here: rclpy must not need to
        # write ~/.ros/log), and the graph lists this host.
        eventually(lambda: check_graph_live(f"http://127.0.0.1:{port}/metrics"), timeout=20)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    log = proc.stdout.read()
    assert "Traceback" not in log
    for probe in ("sockets", "sched", "tcp"):
        assert f"probe {probe} uses" in log and "not root" in log, log


def test_healthz_says_what_each_source_does_and_readyz_waits_for_the_graph(agent, monkeypatch):
    base = agent.rsplit("/", 1)[0]

    def ready():
        try:
            assert scrape(base + "/readyz") == "ready\n"
        except urllib.error.HTTPError as e:
            raise AssertionError(e.read()) from None
    eventually(ready, timeout=20)
    health = json.loads(scrape(base + "/healthz"))
    assert (health["status"], health["degraded"]) == ("ok", [])
    assert health["graph"] == {"adapter": "ros2", "read": True, "stale": False, "error": "", "truncated": ""}
    assert health["probes"]["rcl"] == {"attached": True, "attach_type": "uprobe", "reason": ""}

    # A ROS 1 master that is not there: the agent serves, says it is degraded, and is not ready.
    monkeypatch.setenv("ROS_MASTER_URI", f"http://127.0.0.1:{free_port()}/")
    with running_agent("--graph", "ros1", "--probe", "host") as url:
        base = url.rsplit("/", 1)[0]
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(base + "/readyz", timeout=5)
        assert e.value.code == 503
        assert e.value.read().decode().startswith("not ready: the ros1 graph has not been read yet")

        def degraded():
            health = json.loads(scrape(base + "/healthz"))
            assert (health["status"], health["degraded"]) == ("degraded", ["graph ros1"])
            assert health["graph"]["read"] is False and health["graph"]["stale"] is True
        eventually(degraded, timeout=10)


def test_version():
    out = subprocess.run([sys.executable, "-m", "drums", "--version"], capture_output=True, text=True, timeout=30)
    assert (out.returncode, out.stdout, out.stderr) == (0, "drums 0.1.0\n", "")


def test_the_systemd_unit_starts_the_agent_as_it_is_written(tmp_path):
    """ExecStart of deploy/systemd/drums-agent.service, with this checkout's venv for /opt/drums and
    a token file of the test's own (no systemd runs here to start the unit itself)."""
    with open("deploy/systemd/drums-agent.service") as f:
        (line,) = [line for line in f if line.startswith("ExecStart=")]
    argv = line.split("=", 1)[1].split()
    assert argv[:2] == ["/opt/drums/.venv/bin/drums", "agent"]
    token = tmp_path / "token"
    token.write_text("s3cret\n")
    token.chmod(0o600)
    argv = [str(token) if a == "/etc/drums/token" else a for a in argv[2:]]
    with running_agent(*argv, address="127.0.0.1", bpf=False) as url:
        assert "drums_probe_attached" in scrape(url)
        request = urllib.request.Request(url.rsplit("/", 1)[0] + "/drums/v1/monitor/host", data=b"{}", method="POST")
        with pytest.raises(urllib.error.HTTPError) as e:  # off loopback: the token is needed
            urllib.request.urlopen(request, timeout=5)
        assert e.value.code == 401
    pins = f"/sys/fs/bpf/drums_agent_{urllib.parse.urlsplit(url).port}"
    assert os.listdir(pins)  # --keep-loaded: the kernel goes on counting until the next start
    out = subprocess.run([sys.executable, "-m", "drums", "unload", "--pin-dir", pins], capture_output=True, text=True)
    assert out.returncode == 0 and not os.path.exists(pins), out.stderr


@pytest.mark.parametrize("command", [["graph", "--graph", "ros1"], ["sd", "--graph", "ros1", "--output", "targets.json"]])
def test_a_graph_that_cannot_be_read_is_said_once(command, tmp_path):
    uri = f"http://127.0.0.1:{free_port()}/"
    out = subprocess.run([sys.executable, "-m", "drums", *command], capture_output=True, text=True, timeout=60,
                         cwd=tmp_path, env={**os.environ, "ROS_MASTER_URI": uri})
    assert (out.returncode, out.stdout) == (2, "")
    assert out.stderr == f"drums: the ROS master at {uri} refused the connection\n"


def _agent_process(url: str) -> psutil.Process:
    port = str(urllib.parse.urlsplit(url).port)
    (proc,) = [p for p in psutil.process_iter(["cmdline"])
               if p.info["cmdline"] and "agent" in p.info["cmdline"] and port in p.info["cmdline"]]
    return proc


def _mapped_files(pid: int) -> set[str]:
    """The paths of the files a process has mapped (its libraries among them)."""
    with open(f"/proc/{pid}/maps") as f:
        return {line.split()[-1] for line in f if "/" in line}


def test_the_agent_never_maps_the_bpf_compiler(agent):
    """bcc's compiler (LLVM, some 50 MB of the agent's own memory) stays in the loader children,
    though this agent started cold and compiled every probe; choosing a probe's attach path does
    not ask bcc about the paths after the one that loaded."""
    libraries = _mapped_files(_agent_process(agent).pid)
    assert [lib for lib in libraries if "LLVM" in lib or "libbcc" in lib or "clang" in lib] == []


def _graph_read(agent: str) -> None:
    """Waits until the agent is ready: its graph has been read."""
    def ready() -> None:
        try:
            urllib.request.urlopen(agent.replace("/metrics", "/readyz"), timeout=5)
        except urllib.error.HTTPError as e:
            raise AssertionError(e.read()) from None
    eventually(ready, timeout=20)


def test_neither_the_agent_nor_its_ros2_reader_loads_what_it_does_not_use(agent):
    """They speak no TLS, and OpenSSL's library is 3-4 MB of each one's own memory: Python's ssl and
    _hashlib modules (which load it) stay out, also once the reader has created its rclpy node. And
    numpy, which rclpy's service messages import and the reader never uses (10 MB), is not loaded
    in the reader: its extension module is not mapped."""
    proc = _agent_process(agent)

    def reader():
        found = [c for c in proc.children() if c.name() == "drums-graph"]
        assert found, proc.children()
        return found[0]
    graph = eventually(reader, timeout=10)
    _graph_read(agent)  # the reader's node is made by now

    def libraries(p) -> set:
        return {os.path.basename(path).split(".")[0] for path in _mapped_files(p.pid)}
    unused = {"_ssl", "_hashlib", "_multiarray_umath", "_yaml"}
    assert libraries(proc) & unused == {"_multiarray_umath"}
    assert libraries(graph) & unused == set()


def _printed(code: str) -> str:
    """What a fresh Python running `code` prints: what it imports is its own."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip()


def test_an_rclpy_helper_imports_neither_numpy_nor_yaml_nor_the_message_generator():
    """What rclpy imports and never runs in Drums' children: once a helper has started as they do
    (rclchild.start_helper), made its node and published a DiagnosticArray, none of numpy, yaml,
    rosidl_generator_py's code generator and the lark parser it loads is imported; numpy still
    comes at its first use."""
    code = """if True:
        import sys
        from drums.rclchild import RCLPY_ARGS, Arrays, start_helper
        start_helper("test")
        import rclpy
        rclpy.init(args=RCLPY_ARGS)
        arrays = Arrays("/drums_test_helper")
        said = arrays.publish('{"status": [{"level": 0, "name": "a", "message": "", "hardware_id": "", "values": [["k", "v"]]}]}')
        loaded = sorted(m for m in ("numpy", "yaml", "rosidl_generator_py.generate_py_impl", "lark")
                        if type(sys.modules.get(m)).__name__ == "module")
        from service_msgs.msg import ServiceEventInfo
        print(repr(said), loaded, ServiceEventInfo().client_gid.tolist(), type(sys.modules["numpy"]).__name__)
    """
    assert _printed(code) == "'' [] " + str([0] * 16) + " module"


def test_the_agent_imports_an_http_client_and_re2_only_once_it_uses_them():
    """urllib.request (with http.client and email, 1.3 MB) is imported when the latency probe first
    asks a peer agent its time, and RE2 (1.5 MB) with the first name pattern: not by an agent
    without latency targets or patterns."""
    code = ("import sys; import drums.probes.registry, drums.exporters.http, drums.agent, drums.cli; "
            "print(sorted(m for m in ('urllib.request', 'http.client', 'email', 'statistics', 're2') if m in sys.modules))")
    assert _printed(code) == "[]"


def test_the_probes_collect_without_importing_numpy_ma():
    """np.unique and np.isin (numpy 2.4) import numpy.ma at their first call, 1.2 MB: the sockets
    and sched probes, loaded in the kernel and collected twice over sockets, threads and processes
    that come and go (forty a collect, for np.isin's sorting path), take their distinct PIDs and
    memberships without them."""
    code = f"""if True:
        import socket, subprocess, sys, threading
        from drums.agent import Agent
        from drums.kernel.features import Features
        from drums.probes import registry
        from drums.proctable import ProcessTable
        table = ProcessTable()
        agent = Agent(registry.build(Features(), table, names=["sockets", "sched"], pin_root={TEST_PIN_ROOT + "_numpy_ma"!r}), table)
        agent.start(strict=True)
        try:
            for _ in range(2):
                a, b = socket.socketpair()
                worker = threading.Thread(target=lambda: (a.send(b"x" * 100), b.recv(100)))
                worker.start(); worker.join(); a.close(); b.close()
                crowd = [subprocess.Popen(["sleep", "5"]) for _ in range(40)]
                snap = agent.collect()
                for p in crowd:
                    p.kill(); p.wait()
        finally:
            agent.stop(unload=True)
        print(len(snap.series) > 0, "numpy.ma" in sys.modules)
    """
    assert _printed(code) == "True False"


def test_self_metrics_have_a_row_per_process_of_the_agent(agent):
    """The agent and each helper it started (here the ROS 2 graph reader), by role; CPU as the
    kernel counts it for each process, read before and after the scrape."""
    proc = _agent_process(agent)

    def named() -> dict:  # the reader names itself once Python has started in it
        processes = {"agent": proc} | {c.name().removeprefix("drums-"): c for c in proc.children()}
        assert "graph" in processes, processes
        return processes
    processes = eventually(named, timeout=10)
    _graph_read(agent)  # the reader has done its imports: its memory holds still
    before = {role: sum(p.cpu_times()[:2]) for role, p in processes.items()}
    text = scrape(agent)
    after = {role: sum(p.cpu_times()[:2]) for role, p in processes.items()}
    cpu = {dict(k)["role"]: v for k, v in samples(text, "drums_agent_cpu_seconds_total").items()}
    assert set(cpu) == set(processes)
    for role in processes:  # within a clock tick: the agent reads itself through times(2), psutil through /proc
        assert before[role] - 0.01 <= cpu[role] <= after[role] + 0.01, (role, before[role], cpu[role], after[role])
    rss = {dict(k)["role"]: v for k, v in samples(text, "drums_agent_resident_memory_bytes").items()}
    uss = {dict(k)["role"]: v for k, v in samples(text, "drums_agent_unique_memory_bytes").items()}
    for role, p in processes.items():
        assert 10 * 2 ** 20 < uss[role] <= rss[role], (role, uss[role], rss[role])
        assert abs(rss[role] - p.memory_info().rss) < 0.2 * rss[role], (role, rss[role], p.memory_info().rss)


def _maps_memory(pins: str) -> dict[str, int]:
    """Per probe, what the kernel says its maps hold (bpftool's bytes_memlock of each map pinned in
    its folder under `pins`)."""
    kernel = {}
    for folder in os.listdir(pins):
        for name in os.listdir(os.path.join(pins, folder)):
            shown = subprocess.run(["bpftool", "-j", "map", "show", "pinned", os.path.join(pins, folder, name)],
                                   capture_output=True, text=True)
            if shown.returncode == 0:  # else a link, pinned beside the maps
                probe = folder.rsplit("-", 1)[0]
                kernel[probe] = kernel.get(probe, 0) + json.loads(shown.stdout)["bytes_memlock"]
    return kernel


def test_each_probes_maps_kernel_memory_is_said_and_none_of_it_is_counted_as_the_agents(agent):
    """drums_probe_map_memory_bytes: for each probe, what the kernel says its maps hold, read again
    every 5 s (a hash map made without preallocation, as the rcl probe's, grows with its entries):
    exact for each whose figure held still from before the agent's last read to after the scrape
    (always those of preallocated maps only). No map stays mapped into the agent between collects:
    its unique memory would count the kernel's pages as its own (the threads' slots, read in place
    at each collect: 1.6 MB)."""
    pins = f"/sys/fs/bpf/drums_agent_{urllib.parse.urlsplit(agent).port}"
    before = _maps_memory(pins)
    time.sleep(MEMORY_EVERY + 0.5)
    said = {dict(k)["probe"]: v for k, v in samples(scrape(agent), "drums_probe_map_memory_bytes").items()}
    after = _maps_memory(pins)
    still = {probe for probe in after if before.get(probe) == after[probe]}
    assert {"sched", "sockets", "tcp"} <= still and set(said) == set(after), (before, after, said)
    assert {probe: said[probe] for probe in still} == {probe: after[probe] for probe in still}
    assert said["sched"] > 2 ** 20
    with open(f"/proc/{_agent_process(agent).pid}/maps") as f:
        mapped = [line.split()[0] for line in f if "bpf-map" in line]
    assert sum(int(end, 16) - int(start, 16) for start, end in (r.split("-") for r in mapped)) < 2 ** 20, mapped


SENDER = ("import socket, sys\nsrv = socket.create_server(('127.0.0.1', 0))\n"
          "c = socket.create_connection(srv.getsockname()); s, _ = srv.accept()\n"
          "c.send(b'x'); s.recv(1)\nprint('ready', flush=True); sys.stdin.readline()\n"
          "c.sendall(b'x' * 12345); s.recv(1 << 16)\nprint('sent', flush=True)\nsys.stdin.read()")


def test_a_second_agent_or_an_unload_on_the_same_pins_is_refused_and_the_first_keeps_counting():
    """A second agent on the same pin directory would adopt the first's programs and, on stopping,
    remove them from under it (found when two agents were run side by side)."""
    with running_agent("--probe", "sockets") as url:
        pins = f"/sys/fs/bpf/drums_agent_{url.rsplit(':', 1)[1].split('/')[0]}"
        for argv in (["agent", "--port", "0", "--stream-port", "0", "--probe", "sockets"], ["unload"]):
            out = subprocess.run([sys.executable, "-m", "drums", *argv, "--pin-dir", pins], capture_output=True,
                                 text=True, timeout=60)
            assert out.returncode == 2, out
            assert out.stderr.splitlines() == [f"drums: another drums agent (pid {_agent_pid(url)}) uses the pins "
                                               f"in {pins}: stop it, or give this one a --pin-dir of its own"]
        sender = subprocess.Popen([sys.executable, "-c", SENDER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  text=True)
        try:
            assert sender.stdout.readline() == "ready\n"
            series_begun(url, "drums_process_socket_sent_bytes_total", sender.pid)
            sender.stdin.write("go\n")
            sender.stdin.flush()
            assert sender.stdout.readline() == "sent\n"
            key = (("pid", str(sender.pid)), ("process", os.path.basename(sys.executable)[:15]), ("protocol", "tcp"))

            def counted():
                assert samples(scrape(url), "drums_process_socket_sent_bytes_total").get(key) == 12345
            eventually(counted, timeout=10)
        finally:
            sender.kill()
            sender.wait()
    assert not os.path.exists(f"/run/drums/{pins.strip('/').replace('/', '_')}.lock")  # let go, and removed


def _agent_pid(url: str) -> int:
    port = int(url.rsplit(":", 1)[1].split("/")[0])
    return next(c.pid for c in psutil.net_connections("tcp") if c.laddr.port == port and c.status == "LISTEN")
