"""The cardinality budget in the agent as users run it: with room for one entity of each kind, every
counter, `other` included, only grows while entities send over TCP and UDP, exit, and win their
own series."""
import json
import socket
import subprocess
import sys
import threading
import time

from prometheus_client.parser import text_string_to_metric_families

from tests.agentproc import running_agent, scrape

# A process with a TCP and a connected UDP pair of its own, in one of three roles:
# quiet: sends 20 kB over each, says "done", waits for its stdin to close;
# hog: says "done" and keeps sending about 1 MB/s over each until its stdin closes;
# riser: is quiet until it reads a line, then sends all it can until its stdin closes.
WORKER = """# drums-budget-worker
import socket, sys, threading, time
srv = socket.create_server(("127.0.0.1", 0)); tc = socket.create_connection(srv.getsockname()); ts, _ = srv.accept()
uc, us = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
us.bind(("127.0.0.1", 0)); uc.connect(us.getsockname())
threading.Thread(target=lambda: [None for _ in iter(lambda: ts.recv(1 << 16), b"")], daemon=True).start()
def send(n):
    tc.sendall(b"x" * n)
    for _ in range(n // 1000):
        uc.send(b"y" * 1000); us.recv(2000)
def keep_sending(n, pause):
    while True:
        send(n); time.sleep(pause)
role = sys.argv[1]
if role == "hog":
    threading.Thread(target=keep_sending, args=(20_000, 0.02), daemon=True).start()
else:
    send(20_000)
print("done", flush=True)
if role == "riser":
    sys.stdin.readline()
    threading.Thread(target=keep_sending, args=(1_000_000, 0), daemon=True).start()
sys.stdin.read()
"""
QUIET_BYTES = 20_000

LIMITS = ("--max-processes", "1", "--max-threads", "1", "--max-sockets", "1", "--max-connections", "1")
# The agent watches the workers alone: a busier process elsewhere on the host (`make test` runs the
# demo robot beside this) would take the one slot the hog is meant to hold.
WORKERS_ONLY = ("--process-name", "drums-budget-worker")


def counters(text: str) -> dict[tuple, float]:
    """Every counter sample (histogram buckets, sums and counts too), by name and labels."""
    out = {}
    for family in text_string_to_metric_families(text):
        if family.type in ("counter", "histogram"):
            for s in family.samples:
                if s.name.endswith(("_total", "_bucket", "_sum", "_count")):
                    out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def worker(role: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", WORKER, role], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "done"
    return p


def end(p: subprocess.Popen) -> None:
    p.stdin.close()
    p.wait()


def own_series(page: dict, pid: int) -> bool:
    return any(name.startswith("drums_process_") and dict(labels).get("pid") == str(pid) for name, labels in page)


def test_every_counter_of_every_kind_only_grows_as_entities_exit_fold_and_get_promoted():
    with running_agent(*LIMITS, *WORKERS_ONLY) as url:
        pages, stop = [], threading.Event()

        def scraper():
            while not stop.is_set():
                pages.append(counters(scrape(url)))
                time.sleep(0.2)

        t = threading.Thread(target=scraper)
        t.start()
        try:
            hog = worker("hog")  # takes each kind's one slot and keeps it busy
            time.sleep(1.5)
            quiet = [worker("quiet") for _ in range(3)]  # folded into `other`
            time.sleep(1)
            for p in quiet:  # they leave `other` by exiting, with rows of TCP and of UDP
                end(p)
            time.sleep(1)
            riser = worker("riser")  # folded at first
            time.sleep(1)
            rose_at = len(pages)
            riser.stdin.write("go\n")
            riser.stdin.flush()
            time.sleep(1.5)  # far busier than the hog: promoted, and the hog folded
            end(riser)
            end(hog)
            time.sleep(1)
        finally:
            stop.set()
            t.join()

    backwards = [(key, before[key], after[key]) for before, after in zip(pages, pages[1:])
                 for key in before.keys() & after.keys() if after[key] < before[key]]
    assert not backwards, backwards[:10]
    # The run did what it says: the riser had no series of its own until it rose, and then had;
    # the quiet ones never had; `other` holds their TCP and their UDP bytes.
    assert any(own_series(page, hog.pid) for page in pages)
    assert not any(own_series(page, riser.pid) for page in pages[:rose_at])
    assert any(own_series(page, riser.pid) for page in pages[rose_at:])
    assert not any(own_series(page, p.pid) for page in pages for p in quiet)
    other = {dict(labels)["protocol"]: v for (name, labels), v in pages[-1].items()
             if name == "drums_process_socket_sent_bytes_total" and dict(labels)["pid"] == "other"}
    assert other.get("tcp", 0) >= 3 * QUIET_BYTES and other.get("udp", 0) >= 3 * QUIET_BYTES, other


# Forks `n` children a few tens of milliseconds apart. Each names itself drums-churn, sends a TCP
# connection of 10-20 kB, one UDP datagram of 1,000 bytes and one unix datagram of 500 bytes, lives
# 0.05 to 1.5 s and exits; the launcher reaps them as they end and prints what they sent in all.
# (Its own command line does not name drums-churn: the agent is to choose the children alone.)
LAUNCHER = """
import ctypes, json, os, random, socket, sys, time
tcp_port, udp_port, unix_path, n = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
rng, libc = random.Random(5), ctypes.CDLL(None)
sent = {"tcp": 0, "udp": 0, "unix": 0}
children = set()
for _ in range(n):
    size, life = rng.randint(10_000, 20_000), rng.uniform(0.05, 1.5)
    pid = os.fork()
    if pid == 0:
        libc.prctl(15, b"drums-" + b"churn", 0, 0, 0)
        socket.create_connection(("127.0.0.1", tcp_port)).sendall(b"t" * size)
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM).sendto(b"u" * 1000, ("127.0.0.1", udp_port))
        socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM).sendto(b"x" * 500, unix_path)
        time.sleep(life)
        os._exit(0)
    children.add(pid)
    sent["tcp"] += size; sent["udp"] += 1000; sent["unix"] += 500
    time.sleep(rng.uniform(0, 0.05))
    while children and (done := os.waitpid(-1, os.WNOHANG)[0]):
        children.discard(done)
for pid in children:
    os.waitpid(pid, 0)
print(json.dumps(sent), flush=True)
"""


def test_churning_processes_are_counted_once_on_raw_scrapes_and_in_prometheus(tmp_path):
    """200 processes come and go (most between two scrapes), under --process-name and a budget of
    3 processes, scraped by a real Prometheus every second. Every series begins at 0 and never
    goes back; summed over the series, what each grew by in Prometheus' raw samples is exactly
    what the processes sent, per protocol; and Prometheus' sum(increase()) agrees within its own
    extrapolation (a series' increase stretched past its last sample, by its own average rate)."""
    from tests.deploy.promproc import api, instant, running_prometheus
    tcp = socket.create_server(("127.0.0.1", 0), backlog=256)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    unix = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    unix.bind(str(tmp_path / "sink"))
    held, stop = [], threading.Event()

    def drain(sock):
        sock.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(sock.accept()[0]) if sock is tcp else sock.recv(2000)
            except OSError:
                pass
    sinks = [threading.Thread(target=drain, args=(s,)) for s in (tcp, udp, unix)]
    for t in sinks:
        t.start()
    name = "drums_process_socket_sent_bytes_total"
    try:
        with running_agent("--max-processes", "3", "--max-threads", "3", "--max-sockets", "3",
                           "--max-connections", "3", "--process-name", "drums-churn") as url, \
                running_prometheus("drums", url.split("/")[2], {}, []) as prom:
            time.sleep(3)  # scraped a few times before the churn
            began = time.time()
            launcher = subprocess.run(
                [sys.executable, "-c", LAUNCHER, str(tcp.getsockname()[1]), str(udp.getsockname()[1]),
                 str(tmp_path / "sink"), "200"], capture_output=True, text=True, timeout=120)
            assert launcher.returncode == 0, launcher.stderr
            sent = json.loads(launcher.stdout)
            time.sleep(4)  # the last ended processes' finals scraped, and a scrape after
            ended = time.time()
            window = int(ended - began) + 3
            raw = api(prom, "query", query=f"{name}[{window}s]", time=f"{ended:.3f}")["result"]
            summed = {r["metric"]["protocol"]: float(r["value"][1]) for r in instant(
                prom, f"sum by (protocol) (increase({name}[{window}s] @ {ended:.3f}))")}
    finally:
        stop.set()
        for t in sinks:
            t.join()
        for s in [tcp, udp, unix, *held]:
            s.close()
    grew, stretched, series = {}, {}, {}
    for r in raw:
        protocol, samples = r["metric"]["protocol"], [(float(t), float(v)) for t, v in r["values"]]
        values = [v for _, v in samples]
        series[protocol] = series.get(protocol, 0) + 1
        assert values[0] == 0, (r["metric"].get("process"), r["metric"].get("pid"), samples[:5], began)  # a series begins at 0
        assert all(b >= a for a, b in zip(values, values[1:])), (r["metric"], values)
        grew[protocol] = grew.get(protocol, 0) + values[-1]
        if len(samples) > 1 and values[-1]:  # what Prometheus may add past the last sample
            sampled = samples[-1][0] - samples[0][0]
            stretched[protocol] = stretched.get(protocol, 0) + values[-1] * 1.1 * sampled / (len(samples) - 1) / sampled
    assert grew == sent, (grew, sent, series)
    for protocol, truth in sent.items():
        assert truth <= summed[protocol] <= truth + stretched.get(protocol, 0), (protocol, summed, truth, stretched)
