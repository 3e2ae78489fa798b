"""The probes that run without BPF (/proc and sock_diag), checked against real processes and real
connections whose counts are known exactly, as root and as an unprivileged user, and fed garbage."""
import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time

import pytest

from drums.kernel.sockdiag import TCP_STATES, TcpConnection, dump_tcp
from drums.metrics import Snapshot
from drums.probes.procsched import (
    CLOCK_TICK,
    ProcSchedProbe,
    Schedstat,
    parse_schedstat,
    parse_stat,
    parse_switches,
)
from drums.probes.sched import PROCESS_CPU, PROCESS_SWITCHES, THREAD_CPU, THREAD_RUNQ, THREAD_RUNQ_WAITS, THREAD_SWITCHES
from drums.probes.sockdiag_sockets import SockDiagSocketsProbe, application_bytes
from drums.probes import tcp
from drums.probes.sockets import SOCKET
from drums.proctable import ProcessTable
from tests.conftest import TIME_SCALE, wait_until

STATE = {name: number for number, name in TCP_STATES.items()}
NETNS = str(os.stat("/proc/self/ns/net").st_ino)
SENT, REPLIED = 1_234_567, 54_321  # not multiples of any segment size
BURN = 0.5  # CPU seconds each burner thread uses


def comm(pid, tid=None) -> str:
    with open(f"/proc/{pid}/task/{tid or pid}/comm") as f:
        return f.read().rstrip("\n")


def switches_now(pid) -> dict[int, tuple[int, int]]:
    """Every thread's (voluntary, involuntary) switches, read straight from /proc."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/status") as f:
            out[int(tid)] = parse_switches(f.read())
    return out


def stop(pid):
    """SIGSTOP the process and wait until every thread is stopped, so its counters hold still."""
    os.kill(pid, signal.SIGSTOP)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        states = set()
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    states.add(f.read().rsplit(")", 1)[1].split()[0])
            except FileNotFoundError:
                pass  # a thread that was just joined can still be listed for a moment
        if states == {"T"}:
            return
        time.sleep(0.005)
    raise AssertionError(f"process {pid} did not stop")


# --- sockets over sock_diag -------------------------------------------------------------------

# Connects, sends SENT bytes, reads REPLIED, reports its port and socket inode, then on a line from
# the test shuts its sending side (FIN) and waits.
SOCKET_CHILD = r"""
import os, socket, sys
host, port, sent, replied = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
s = socket.create_connection((host, port))
s.sendall(b"s" * sent)
got = 0
while got < replied:
    chunk = s.recv(65536)
    assert chunk
    got += len(chunk)
print(s.getsockname()[1], os.fstat(s.fileno()).st_ino, flush=True)
sys.stdin.readline()
s.shutdown(socket.SHUT_WR)
print("shut", flush=True)
sys.stdin.read()
"""


def _loopback(family, host) -> bool:
    try:
        with socket.socket(family) as s:
            s.bind((host, 0))
    except OSError:
        return False
    return True


def _recv_exactly(sock, n) -> int:
    got = 0
    while got < n:
        chunk = sock.recv(min(65536, n - got))
        assert chunk, "peer closed early"
        got += len(chunk)
    return got


def _until(take, predicate, seconds=2.0):
    """The first snapshot for which predicate holds (the last ACK may still be on its way), or the last."""
    deadline = time.monotonic() + seconds
    while True:
        snap = take()
        if predicate(snap) or time.monotonic() > deadline:
            return snap
        time.sleep(0.01)


@pytest.mark.parametrize("family,host,shown", [(socket.AF_INET, "127.0.0.1", "127.0.0.1"),
                                               (socket.AF_INET6, "::1", "[::1]")])
@pytest.mark.kernel
def test_sockets_fallback_counts_exact_bytes_of_a_child_connection(proctable, collect, family, host, shown):
    if not _loopback(family, host):
        pytest.skip(f"no {host} here")
    probe = SockDiagSocketsProbe(proctable)
    probe.start()
    assert (probe.status.attached, probe.status.attach_type) == (True, "sock_diag")
    with socket.create_server((host, 0), family=family) as listener:
        lport = listener.getsockname()[1]
        child = subprocess.Popen([sys.executable, "-c", SOCKET_CHILD, host, str(lport), str(SENT), str(REPLIED)],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            listener.settimeout(10 * TIME_SCALE)  # a child python starting under emulation on 5.10 took longer
            server, _ = listener.accept()
            with server:
                server.settimeout(10 * TIME_SCALE)
                assert _recv_exactly(server, SENT) == SENT
                server.sendall(b"r" * REPLIED)
                cport, child_inode = map(int, child.stdout.readline().split())
                probe.set_pids([child.pid, os.getpid()])
                theirs = (str(child.pid), comm(child.pid), "tcp", f"{shown}:{cport}", f"{shown}:{lport}",
                          NETNS, str(child_inode))
                ours = (str(os.getpid()), comm(os.getpid()), "tcp", f"{shown}:{lport}", f"{shown}:{cport}",
                        NETNS, str(os.fstat(server.fileno()).st_ino))
                expected = {theirs: (SENT, REPLIED), ours: (REPLIED, SENT)}

                def counts(snap):
                    sent, received = snap.values(SOCKET["sent_bytes"]), snap.values(SOCKET["received_bytes"])
                    # Only this connection: the test process may hold others (earlier tests' clients).
                    return {k: (sent[k], received[k]) for k in sent if k in (theirs, ours)
                            or (k[0] in (theirs[0], ours[0]) and f":{lport}" in k[3] + k[4])}

                # Open: the child connected (its SYN is in its bytes_acked), we accepted.
                snap = _until(lambda: collect(probe), lambda s: counts(s) == expected)
                assert counts(snap) == expected  # the listener is not a connection: no series

                # Half-closed: the child's FIN is in its bytes_acked and in our bytes_received.
                child.stdin.write("shut\n")
                child.stdin.flush()
                assert child.stdout.readline() == "shut\n"

                def closing(snap):
                    by_port = {c.local_port: c for c in dump_tcp() if c.state != STATE["LISTEN"]
                               and {c.local_port, c.remote_port} == {lport, cport}}
                    return ({by_port[cport].state, by_port[lport].state}
                            == {STATE["FIN_WAIT2"], STATE["CLOSE_WAIT"]}) and counts(snap) == expected

                snap = _until(lambda: collect(probe), closing)
                raw = {c.local_port: c for c in dump_tcp() if {c.local_port, c.remote_port} == {lport, cport}}
                assert (raw[cport].bytes_acked, raw[lport].bytes_received) == (SENT + 2, SENT + 1)
                assert counts(snap) == expected
        finally:
            child.kill()
            child.wait()


def _conn(state="ESTABLISHED", acked=0, received=0) -> TcpConnection:
    return TcpConnection(family=socket.AF_INET, state=STATE[state], local_address="127.0.0.1", local_port=1,
                         remote_address="127.0.0.1", remote_port=2, inode=1, uid=0, cookie=1,
                         bytes_acked=acked, bytes_received=received)


@pytest.mark.parametrize("state,connected,acked,received,expected", [
    ("ESTABLISHED", True, 101, 50, (100, 50)),  # our SYN
    ("ESTABLISHED", False, 100, 50, (100, 50)),
    ("FIN_WAIT1", True, 101, 50, (100, 50)),  # FIN sent, not acknowledged yet
    ("FIN_WAIT2", True, 102, 50, (100, 50)),  # SYN and FIN
    ("CLOSE_WAIT", False, 100, 51, (100, 50)),  # their FIN
    ("LAST_ACK", False, 100, 51, (100, 50)),
    ("CLOSING", True, 101, 51, (100, 50)),
    ("ESTABLISHED", True, 0, 0, (0, 0)),  # never below zero
])
def test_application_bytes_take_syn_and_fin_out_of_sequence_counts(state, connected, acked, received, expected):
    assert application_bytes(_conn(state, acked, received), connected) == expected


# --- scheduling from /proc ---------------------------------------------------------------------

# One thread burns BURN CPU seconds and exits, a second burns as much, renames itself and waits;
# the main thread then reports their thread_time() and its process_time(), and waits for lines:
# "spawn" starts a thread that blocks, "join" lets it exit.
SCHED_CHILD = r"""
import json, os, sys, threading, time
burn = float(sys.argv[1])
done, stop = [], threading.Event()
def burner(stay):
    t0 = time.thread_time()
    while time.thread_time() - t0 < burn:
        pass
    tid = threading.get_native_id()
    if stay:
        with open(f"/proc/self/task/{tid}/comm", "w") as f:
            f.write("burner")
    done.append((tid, time.thread_time()))
    if stay:
        stop.wait()
first = threading.Thread(target=burner, args=(False,))
first.start()
first.join()
threading.Thread(target=burner, args=(True,), daemon=True).start()
while len(done) < 2:
    time.sleep(0.01)
print(json.dumps({"exited": done[0], "alive": done[1], "process": time.process_time()}), flush=True)
release = threading.Event()
for line in sys.stdin:
    if line == "spawn\n":
        def blocker():
            for _ in range(50):
                time.sleep(0.001)
            release.wait()
        extra = threading.Thread(target=blocker)
        extra.start()
        time.sleep(0.3)
        print(extra.native_id, flush=True)
    elif line == "join\n":
        release.set()
        extra.join()
        print("joined", flush=True)
"""


def _command(child, line) -> str:
    os.kill(child.pid, signal.SIGCONT)
    child.stdin.write(line)
    child.stdin.flush()
    return child.stdout.readline().strip()


@pytest.mark.kernel
def test_proc_sched_matches_thread_and_process_time_and_switches(proctable, collect, features):
    probe = ProcSchedProbe(proctable)
    probe.start()
    assert (probe.status.attached, probe.status.attach_type) == (True, "proc")
    assert "no run-queue latency histogram" in probe.status.reason
    child = subprocess.Popen([sys.executable, "-c", SCHED_CHILD, str(BURN)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        report = json.loads(child.stdout.readline())
        stop(child.pid)
        probe.set_pids([child.pid])
        snap = collect(probe)
        truth = switches_now(child.pid)
        pid, name = str(child.pid), comm(child.pid)

        exited_tid, exited_time = report["exited"]
        tid, thread_time = report["alive"]
        cpu = snap.values(THREAD_CPU)
        assert abs(cpu[pid, str(tid), "burner"] - thread_time) <= 0.02 * thread_time
        assert not any(labels[1] == str(exited_tid) for labels in cpu)

        # utime and stime are each truncated to whole ticks; the kernel sums the threads (exited
        # ones included) in nanoseconds before converting, so the error does not grow with threads.
        process_cpu = snap.values(PROCESS_CPU)[pid, name]
        assert abs(process_cpu - report["process"]) <= 2 * CLOCK_TICK + 0.02 * report["process"]
        assert process_cpu >= exited_time + thread_time - 2 * CLOCK_TICK  # the exited burner counts

        threads = snap.values(THREAD_SWITCHES)
        runs = snap.values(THREAD_RUNQ_WAITS)
        assert {int(k[1]) for k in threads} == set(truth)
        for t, (vol, invol) in truth.items():
            labels = (pid, str(t), comm(child.pid, t))
            assert (threads[labels + ("voluntary",)], threads[labels + ("involuntary",)]) == (vol, invol)
            # The waits and their time, as the kernel counted and summed them (a wait can take 0 ns
            # on an idle host: the run queue's clock need not move between a wakeup and the run).
            with open(f"/proc/{pid}/task/{t}/schedstat") as f:
                _, waited, pcount = (int(x) for x in f.read().split())
            assert runs[labels] == pcount and abs(snap.values(THREAD_RUNQ)[labels] - waited / 1e9) <= 1e-9
            # Off the CPU, every switch out was followed by one wait on a run queue that ended in
            # running, and the first run followed one too: pcount counts exactly those waits. Not on
            # PREEMPT_RT, where a few switches of a thread go with no wait counted (seen: 4 of 2,640, 1 of 62).
            assert runs[labels] == vol + invol or features.preempt_rt and 0 <= vol + invol - runs[labels] <= 4 + 0.01 * (vol + invol)
        process = snap.values(PROCESS_SWITCHES)
        assert process[pid, name, "voluntary"] == sum(v for v, _ in truth.values())
        assert process[pid, name, "involuntary"] == sum(i for _, i in truth.values())

        # A thread that exits keeps its switches in the process's totals, as last collected.
        extra = int(_command(child, "spawn\n"))
        stop(child.pid)
        seen = collect(probe).values(THREAD_SWITCHES)
        extra_last = [v for k, v in sorted(seen.items()) if k[1] == str(extra)]  # involuntary, voluntary
        assert extra_last[1] >= 50
        before = collect(probe).values(PROCESS_SWITCHES)
        assert _command(child, "join\n") == "joined"
        # The join returns once the thread cleared its TID, a moment before the kernel releases it.
        wait_until(lambda: not os.path.exists(f"/proc/{child.pid}/task/{extra}"), "the joined thread released")
        stop(child.pid)
        after = collect(probe).values(PROCESS_SWITCHES)
        truth = switches_now(child.pid)
        assert extra not in truth
        assert after[pid, name, "voluntary"] == extra_last[1] + sum(v for v, _ in truth.values())
        assert after[pid, name, "involuntary"] == extra_last[0] + sum(i for _, i in truth.values())
        assert all(after[k] >= before[k] for k in before)
    finally:
        child.kill()
        child.wait()


def test_parsers_return_none_for_truncated_or_garbage_text():
    assert parse_schedstat("47406050 63550458 2281\n") == Schedstat(47406050, 63550458, 2281)
    status = "Name:\tx\nvoluntary_ctxt_switches:\t23\nnonvoluntary_ctxt_switches:\t2257\n"
    assert parse_switches(status) == (23, 2257)
    stat = "42 (a) b (c)) S 1 42 42 0 -1 4194304 10 0 0 0 7 3 0 0 20 0 1 0 12345 1000 100\n"
    assert parse_stat(stat) == (10, 12345)
    for text in ("", "\0\0\0", "1 2", "x y z", "12 34 5x\n"):
        assert parse_schedstat(text) is None
    for text in ("", status[:40], status.replace("2257", "22x7"), "voluntary_ctxt_switches:\t\n", "\xff" * 99):
        assert parse_switches(text) is None
    for text in ("", stat[:30], stat.replace("12345", "1e5"), "42 (a S 1 2", "no parenthesis " * 9):
        assert parse_stat(text) is None


def _write(path, text):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)


def test_bad_proc_files_skip_that_thread_or_process(tmp_path):
    proc = str(tmp_path)
    os.makedirs(f"{proc}/self/task")
    _write(f"{proc}/self/schedstat", "1 2 3\n")
    good_stat = "7 (robot) S 1 7 7 0 -1 0 0 0 0 0 30 20 0 0 20 0 2 0 500 0 0\n"
    switches = "voluntary_ctxt_switches:\t5\nnonvoluntary_ctxt_switches:\t2\n"
    for pid, stat in ((7, good_stat), (8, good_stat[:25]), (9, "\0garbage")):
        _write(f"{proc}/{pid}/stat", stat)
        _write(f"{proc}/{pid}/comm", "robot\n")
        _write(f"{proc}/{pid}/task/{pid}/status", switches)
        _write(f"{proc}/{pid}/task/{pid}/schedstat", "2000000000 500000000 9\n")
        _write(f"{proc}/{pid}/task/{pid}/comm", "robot\n")
    _write(f"{proc}/7/task/70/status", switches[:30])  # truncated: this thread is skipped
    _write(f"{proc}/7/task/71/status", switches)
    _write(f"{proc}/7/task/71/schedstat", "garbage")  # its switches still count
    _write(f"{proc}/7/task/71/comm", "worker\n")
    table = ProcessTable(proc)
    table.refresh()
    probe = ProcSchedProbe(table, proc=proc)
    probe.start()
    probe.set_pids([7, 8, 9, 10])  # 10 has no directory at all
    snap = Snapshot()
    probe.collect(snap)
    assert snap.values(PROCESS_CPU) == {("7", "robot"): 50 * CLOCK_TICK}
    assert snap.values(PROCESS_SWITCHES) == {("7", "robot", "voluntary"): 10, ("7", "robot", "involuntary"): 4}
    assert snap.values(THREAD_CPU) == {("7", "7", "robot"): 2.0}
    assert snap.values(THREAD_RUNQ) == {("7", "7", "robot"): 0.5}
    assert snap.values(THREAD_RUNQ_WAITS) == {("7", "7", "robot"): 9}
    assert set(snap.values(THREAD_SWITCHES)) == {("7", t, n, k) for t, n in (("7", "robot"), ("71", "worker"))
                                                 for k in ("voluntary", "involuntary")}


# --- without privileges ------------------------------------------------------------------------

# Run as nobody: one TCP connection and one burner thread of its own, read by both fallbacks.
UNPRIVILEGED = r"""
import json, os, socket, threading, time
from drums.metrics import Snapshot
from drums.probes.procsched import ProcSchedProbe
from drums.probes.sched import THREAD_CPU
from drums.probes.sockdiag_sockets import SockDiagSocketsProbe
from drums.probes import tcp
from drums.probes.sockets import SOCKET
from drums.proctable import ProcessTable
n = 300_001
listener = socket.create_server(("127.0.0.1", 0))
client = socket.create_connection(listener.getsockname())
server, _ = listener.accept()
client.sendall(b"x" * n)
got = 0
while got < n:
    got += len(server.recv(65536))
done, stop = [], threading.Event()
def burner():
    t0 = time.thread_time()
    while time.thread_time() - t0 < 0.3:
        pass
    done.append((threading.get_native_id(), time.thread_time()))
    stop.wait()
threading.Thread(target=burner, daemon=True).start()
while not done:
    time.sleep(0.01)
table = ProcessTable()
sched, sockets = ProcSchedProbe(table), SockDiagSocketsProbe(table)
out = {"uid": os.geteuid()}
for probe in (sched, sockets):
    probe.start()
    probe.set_pids([os.getpid()])
    out[probe.name] = probe.status.attach_type
ino = {os.fstat(s.fileno()).st_ino: role for s, role in ((client, "client"), (server, "server"))}
for _ in range(200):
    table.refresh()
    snap = Snapshot()
    sched.collect(snap)
    sockets.collect(snap)
    sent = {ino[int(k[6])]: v for k, v in snap.values(SOCKET["sent_bytes"]).items()}
    received = {ino[int(k[6])]: v for k, v in snap.values(SOCKET["received_bytes"]).items()}
    if sent.get("client") == n:
        break
    time.sleep(0.01)
tid, thread_time = done[0]
cpu = [v for k, v in snap.values(THREAD_CPU).items() if k[1] == str(tid)]
out.update(n=n, sent=sent, received=received, thread_time=thread_time, thread_cpu=cpu)
print(json.dumps(out))
"""


def test_both_fallbacks_work_as_an_unprivileged_user():
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("no setpriv (util-linux) here")
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    result = subprocess.run(
        [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c", UNPRIVILEGED],
        cwd=root, capture_output=True, text=True, timeout=60,
        env={"PATH": os.environ.get("PATH", ""), "PYTHONDONTWRITEBYTECODE": "1"},
    )
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    n = out["n"]
    assert (out["uid"], out["sched"], out["sockets"]) == (65534, "proc", "sock_diag")
    assert (out["sent"], out["received"]) == ({"client": n, "server": 0}, {"client": 0, "server": n})
    (cpu,) = out["thread_cpu"]
    assert abs(cpu - out["thread_time"]) <= 0.02 * out["thread_time"]


# ---- TCP health without eBPF ----------------------------------------------------------------------

def test_tcp_fallback_reads_rtt_and_host_counters_from_the_kernel():
    from drums.probes.tcp import SockDiagTcpProbe, parse_snmp_tcp

    probe = SockDiagTcpProbe()
    probe.start()
    assert probe.status.attach_type == "sock_diag"
    with socket.create_server(("127.0.0.1", 0)) as lst:
        client = socket.create_connection(lst.getsockname())
        server, _ = lst.accept()
        with client, server:
            client.sendall(b"x" * 1000)
            server.recv(1000)
            snap = Snapshot()
            probe.collect(snap)
            info = client.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 104)
            srtt_us = struct.unpack_from("=I", info, 68)[0]
            local = "%s:%d" % client.getsockname()
            remote = "%s:%d" % client.getpeername()
            rtt = {k: v for k, v in snap.values(tcp.CONN_RTT).items() if k == (local, remote)}
            assert rtt == {(local, remote): srtt_us / 1e6}
            netns = str(os.stat("/proc/self/ns/net").st_ino)
            assert snap.values(tcp.CONN_RETRANSMITS)[(local, remote, netns)] == 0
    with open("/proc/net/snmp") as f:
        after = parse_snmp_tcp(f.read())
    assert 0 <= after["RetransSegs"] - snap.values(tcp.RETRANSMITS)[()] <= 5  # only what others did since
    assert parse_snmp_tcp("Tcp: RtoAlgorithm\nTcp: banana\n") == {}
    assert parse_snmp_tcp("") == {}
