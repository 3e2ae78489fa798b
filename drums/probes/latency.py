"""Round-trip time from this host to others: the paper's latency monitor, a multi-target ping.

Each target is probed once per interval with a round of `count` echoes, by ICMP where this process
may send it (root, or a group in net.ipv4.ping_group_range), else by timing TCP connects: a SYN
answered by SYN-ACK or by a reset took one round trip either way. A target whose ICMP echoes all
go unanswered while a TCP connect is answered is probed by TCP from then on (ICMP filtered).

Where the target runs a Drums agent on the TCP port, each round also asks it the time
(/drums/v1/info), as NTP does: its clock less ours at the middle of the exchange is the offset,
right to within half the exchange. Delivery times across hosts are differences of two hosts'
realtime clocks, so this tells whether a millisecond of them is the network's or the clocks'.

Only targets the operator or the graph named are probed: the API cannot turn the agent into a
tool for scanning arbitrary hosts.
"""
from __future__ import annotations

import json
import logging
import math
import os
import socket
import threading
import time
from dataclasses import dataclass
from functools import cache

import icmplib

from drums.metrics import COUNTER, GAUGE, Metric, Snapshot
from drums.probes.base import Probe

log = logging.getLogger("drums")

LABELS = ("target", "method")
RTT_MIN = Metric("drums_latency_rtt_min_seconds", GAUGE, "Shortest round trip of the last round", LABELS,
                 additive=False)
RTT_MEAN = Metric("drums_latency_rtt_mean_seconds", GAUGE, "Mean round trip of the last round", LABELS,
                  additive=False)
RTT_MAX = Metric("drums_latency_rtt_max_seconds", GAUGE, "Longest round trip of the last round", LABELS,
                 additive=False)
LOSS = Metric("drums_latency_loss_ratio", GAUGE, "Fraction of the last round's probes left unanswered", LABELS,
              additive=False)
SENT = Metric("drums_latency_probes_sent_total", COUNTER,
              "Probes sent to the target, or tried (a name that does not resolve, no route)", LABELS)
LOST = Metric("drums_latency_probes_lost_total", COUNTER, "Probes sent to the target and left unanswered",
              LABELS)

CLOCK_OFFSET = Metric("drums_latency_clock_offset_seconds", GAUGE,
                      "The target's realtime clock less this host's, as the target's Drums agent said its time at the "
                      "last round (NTP's estimate: against the middle of the exchange)", ("target",), additive=False)
CLOCK_UNCERTAINTY = Metric("drums_latency_clock_offset_uncertainty_seconds", GAUGE,
                           "Half the exchange that measured the clock offset: the true offset is within this of it",
                           ("target",), additive=False)

METHODS = ("auto", "icmp", "tcp")
GAP = 0.05  # between the probes of one round
TIMEOUT = 1.0  # a probe unanswered this long is lost
TCP_PORT = 9969  # another Drums agent's port: open (SYN-ACK) or closed (reset), either answers
MAX_INFO = 1 << 16  # bytes of a peer's /drums/v1/info read at most


@cache
def _direct():
    """An HTTP opener that uses no proxy (a proxy would time itself). Made when a peer is first
    asked its time: urllib.request (with http.client and email) is 1.3 MB of an agent that has
    no latency targets, as most have none."""
    import urllib.request
    return urllib.request.build_opener(urllib.request.ProxyHandler({}))


@dataclass
class Round:
    method: str
    rtts: list[float]  # seconds, of the answered probes
    sent: int


@dataclass
class Watch:
    interval: float
    count: int
    method: str  # as asked: auto, icmp or tcp
    port: int
    stop: threading.Event
    thread: threading.Thread | None = None
    error: str = ""  # the last round's failure, logged once rather than every interval


def tcp_round(address: str, port: int, count: int) -> Round:
    rtts = []
    for i in range(count):
        if i:
            time.sleep(GAP)
        began = time.perf_counter()
        try:
            socket.create_connection((address, port), timeout=TIMEOUT).close()
        except ConnectionRefusedError:
            pass  # a reset came back: as good an echo as a SYN-ACK
        except OSError:
            continue
        rtts.append(time.perf_counter() - began)
    return Round("tcp", rtts, count)


def clock_offset(address: str, port: int) -> tuple[float, float] | None:
    """(the clock of the Drums agent at address:port less ours, half the exchange's time), None
    where no agent answers with its time."""
    host = f"[{address}]" if ":" in address else address
    began = time.time()
    try:
        with _direct().open(f"http://{host}:{port}/drums/v1/info", timeout=TIMEOUT) as answer:
            said = json.loads(answer.read(MAX_INFO))["time"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    ended = time.time()
    if isinstance(said, bool) or not isinstance(said, (int, float)) or not math.isfinite(said):
        return None
    return said - (began + ended) / 2, (ended - began) / 2


def icmp_round(address: str, count: int) -> Round:
    host = icmplib.ping(address, count=count, interval=GAP, timeout=TIMEOUT, privileged=os.geteuid() == 0)
    return Round("icmp", [r / 1000 for r in host.rtts], host.packets_sent)


class LatencyProbe(Probe):
    name = "latency"
    metrics = (RTT_MIN, RTT_MEAN, RTT_MAX, LOSS, SENT, LOST, CLOCK_OFFSET, CLOCK_UNCERTAINTY)

    def __init__(self):
        super().__init__()
        self._lock = threading.Lock()
        self._watches: dict[str, Watch] = {}
        self._last: dict[str, Round] = {}
        self._clocks: dict[str, tuple[float, float]] = {}  # target -> (offset, uncertainty) of its last round
        self._totals: dict[tuple[str, str], list[int]] = {}  # (target, method) -> [sent, lost]

    def start(self) -> None:
        self.status.attached = True
        self.status.attach_type = "icmp" if os.geteuid() == 0 else "icmp-unprivileged"

    def watch(self, target: str, interval: float, count: int = 3, method: str = "auto", port: int = TCP_PORT) -> None:
        """Probe `target` every `interval` s from now on; if it was probed already, with these
        settings from now on (its totals go on counting)."""
        w = Watch(interval, count, method, port, threading.Event())
        w.thread = threading.Thread(target=self._run, args=(target, w), name=f"latency {target}", daemon=True)
        with self._lock:
            old = self._watches.get(target)
            self._watches[target] = w
        if old is not None:
            old.stop.set()  # its round in flight is dropped: it is no longer the target's watch
        w.thread.start()

    def unwatch(self, target: str) -> None:
        with self._lock:
            w = self._watches.pop(target, None)
            self._last.pop(target, None)
            self._clocks.pop(target, None)
            for key in [k for k in self._totals if k[0] == target]:
                del self._totals[key]
        if w is not None:
            w.stop.set()

    def watched(self) -> set[str]:
        with self._lock:
            return set(self._watches)

    def stop(self) -> None:
        for target in self.watched():
            self.unwatch(target)

    def _run(self, target: str, w: Watch) -> None:
        method = w.method
        while not w.stop.is_set():
            began = time.monotonic()
            try:
                results = self._round(target, w, method)
            except (OSError, icmplib.ICMPLibError) as e:
                if str(e) != w.error:
                    log.warning("latency to %s: %s", target, e)
                w.error = str(e)
                results = [Round(method if method != "auto" else "icmp", [], w.count)]  # all lost
            if method == "auto" and results[-1].method == "tcp" and results[-1].rtts:
                method = "tcp"
            clock = clock_offset(target, w.port)
            with self._lock:
                if self._watches.get(target) is not w:
                    return  # unwatched while this round ran
                self._last[target] = results[-1]
                if clock is None:
                    self._clocks.pop(target, None)
                else:
                    self._clocks[target] = clock
                for result in results:  # every probe sent is counted, under the method that sent it
                    totals = self._totals.setdefault((target, result.method), [0, 0])
                    totals[0] += result.sent
                    totals[1] += result.sent - len(result.rtts)
            w.stop.wait(max(0.0, w.interval - (time.monotonic() - began)))

    def _round(self, target: str, w: Watch, method: str) -> list[Round]:
        """The round's probes, by method: the last is what the round measured."""
        if method == "tcp":
            return [tcp_round(target, w.port, w.count)]
        try:
            result = icmp_round(target, w.count)
        except icmplib.SocketPermissionError:
            if method == "icmp":
                raise
            return [tcp_round(target, w.port, w.count)]  # no ICMP socket for this process
        if method == "auto" and not result.rtts:
            # Unanswered: one TCP connect tells a host that is there (ICMP filtered on the way, and
            # TCP from the next round on) from one that is not.
            return [result, tcp_round(target, w.port, 1)]
        return [result]

    def collect(self, snap: Snapshot) -> None:
        with self._lock:
            last = dict(self._last)
            totals = {k: list(v) for k, v in self._totals.items()}
            clocks = dict(self._clocks)
        for target, r in sorted(last.items()):
            labels = (target, r.method)
            if r.rtts:
                snap.add(RTT_MIN, labels, min(r.rtts))
                snap.add(RTT_MEAN, labels, math.fsum(r.rtts) / len(r.rtts))
                snap.add(RTT_MAX, labels, max(r.rtts))
            if r.sent:
                snap.add(LOSS, labels, 1 - len(r.rtts) / r.sent)
        for (target, method), (sent, lost) in sorted(totals.items()):
            snap.add(SENT, (target, method), sent)
            snap.add(LOST, (target, method), lost)
        for target, (offset, uncertainty) in sorted(clocks.items()):
            snap.add(CLOCK_OFFSET, (target,), offset)
            snap.add(CLOCK_UNCERTAINTY, (target,), uncertainty)

