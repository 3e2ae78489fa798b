"""Identity that follows the kernel, in the real agent: a process renamed or exec'd carries its new
name, a PID that comes back is the new process's, and a TCP connection whose addresses are reused
is one series that never goes back."""
import os
import socket
import struct
import subprocess
import sys
import time

import pytest

from tests.agentproc import assert_monotonic, running_agent, scrape
from tests.conftest import eventually

# A parent that names itself, forks a child that burns a little CPU (so that it has sched rows) and
# sleeps, prints the child's PID, and kills it when its stdin closes. With a PID to aim at, it sets
# ns_last_pid so that the child gets that PID: the child is then a new process with an old PID,
# made by fork alone (no exec, no rename of its own to tell the agent).
PARENT = r'''
import ctypes, os, sys, time
ctypes.CDLL(None).prctl(15, sys.argv[1].encode(), 0, 0, 0)
if int(sys.argv[2]):
    with open("/proc/sys/kernel/ns_last_pid", "w") as f:
        f.write(str(int(sys.argv[2]) - 1))
pid = os.fork()
if pid == 0:
    began = time.process_time()
    while time.process_time() - began < 0.05:
        pass
    time.sleep(3600)
print(pid, flush=True)
sys.stdin.read()
os.kill(pid, 9)
os.waitpid(pid, 0)
'''


def process_labels(text: str) -> dict[str, set[str]]:
    """pid -> the `process` labels it has in one scrape, over every drums_process_* series."""
    out: dict[str, set[str]] = {}
    for line in text.splitlines():
        if line.startswith("drums_process_") and 'pid="' in line and 'process="' in line:
            pid = line.split('pid="', 1)[1].split('"', 1)[0]
            out.setdefault(pid, set()).add(line.split('process="', 1)[1].split('"', 1)[0])
    return out


def named(url: str, pid: int, name: str) -> None:
    labels = process_labels(scrape(url))
    assert all(len(names) == 1 for names in labels.values()), {p: n for p, n in labels.items() if len(n) > 1}
    assert labels.get(str(pid)) == {name}, labels.get(str(pid))


@pytest.fixture(scope="module")
def agent():
    """The agent; once every test of the module has run, its counters have never gone backwards."""
    with running_agent("--graph", "auto") as url:
        first = scrape(url)
        yield url
        assert_monotonic([first, scrape(url)])


def test_a_renamed_or_exec_d_process_carries_its_new_name(agent):
    proc = subprocess.Popen([sys.executable, "-c", "import ctypes, sys, time\n"
                             "sys.stdin.readline()\n"
                             "ctypes.CDLL(None).prctl(15, b'drums-renamed', 0, 0, 0)\n"
                             "sys.stdin.readline()\n"
                             "import os; os.execvp('sh', ['sh', '-c', 'read x'])"],
                            stdin=subprocess.PIPE, text=True)
    try:
        eventually(lambda: named(agent, proc.pid, os.path.basename(sys.executable)[:15]), timeout=10)
        proc.stdin.write("\n")
        proc.stdin.flush()
        eventually(lambda: named(agent, proc.pid, "drums-renamed"), timeout=10)
        proc.stdin.write("\n")
        proc.stdin.flush()
        eventually(lambda: named(agent, proc.pid, "sh"), timeout=10)
    finally:
        proc.kill()
        proc.wait()


def test_a_pid_that_comes_back_is_the_new_process(agent):
    first = subprocess.Popen([sys.executable, "-c", PARENT, "drums-first", "0"], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    pid = int(first.stdout.readline())
    eventually(lambda: named(agent, pid, "drums-first"), timeout=10)
    first.stdin.close()
    first.wait()
    for _ in range(5):  # another process may take the PID first on a busy machine: aim again
        second = subprocess.Popen([sys.executable, "-c", PARENT, "drums-second", str(pid)], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
        if int(second.stdout.readline()) == pid:
            break
        second.stdin.close()
        second.wait()
    else:
        pytest.fail(f"PID {pid} could not be reused")
    try:
        eventually(lambda: named(agent, pid, "drums-second"), timeout=10)
    finally:
        second.stdin.close()
        second.wait()


def connection_values(url: str, names: tuple[str, ...], local: str, remote: str) -> tuple[float, ...]:
    """The one sample of each of the connection's series in one scrape (a closed connection is in
    one scrape only; two samples of a series would fail Prometheus's whole scrape)."""
    text = scrape(url)
    out = []
    for name in names:
        found = [float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                 if line.startswith(name + "{") and f'local="{local}"' in line and f'remote="{remote}"' in line]
        assert len(found) == 1, (name, found)
        out.extend(found)
    return tuple(out)


def test_a_connection_that_reuses_the_addresses_of_a_closed_one_is_one_series_that_never_goes_back(agent):
    server = socket.create_server(("127.0.0.1", 0))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        client_port = s.getsockname()[1]
    local, remote = f"127.0.0.1:{client_port}", f"127.0.0.1:{server.getsockname()[1]}"

    def connect_and_reset(close: bool) -> socket.socket:
        c = socket.socket()
        c.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close sends a reset
        c.bind(("127.0.0.1", client_port))
        c.connect(server.getsockname())
        server.accept()[0].close()
        if close:
            c.close()
        return c
    names = ("drums_tcp_connection_resets_sent_total", "drums_tcp_connection_state_changes_total")

    def both() -> tuple[float, ...]:
        return connection_values(agent, names, local, remote)
    connect_and_reset(close=True)  # SYN_SENT, ESTABLISHED, CLOSE_WAIT, CLOSE; a reset
    second = connect_and_reset(close=False)  # the same addresses, while the first is still in the map
    seen = [both()]  # the two summed: its series begins, from zero (what they counted is in `other`)
    seen.append(both())  # the first exported and forgotten, what it counted kept in the series
    second.close()
    time.sleep(0.1)
    seen.append(both())  # the second closed too: a reset, CLOSE
    server.close()
    assert seen == [(0, 0), (0, 0), (1, 1)]
