"""The cardinality budget in the agent as users run it: with room for one entity of each kind, every
counter, `other` included, only grows while entities send over TCP and UDP, exit, and win their
own series."""
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
