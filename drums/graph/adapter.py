"""The one interface of the middleware adapters, and the thread that keeps the graph current.

An adapter's `poll()` returns the whole graph as the middleware describes it now, or raises
GraphError. The Follower applies each good state to the Graph; after a failed, garbled or
overdue poll the last good graph stays, marked stale, and one line is logged per new reason.
"""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from typing import Callable

from drums.errors import GraphError
from drums.graph.model import Graph, GraphState

log = logging.getLogger("drums")


class Adapter:
    name = ""
    interval = 1.0  # seconds between polls
    # A one-shot reader takes the graph as complete `settle` s after its first answer, once nothing
    # has changed for a second (drums.cli.QUIET).
    settle = 0.0

    def start(self) -> None:
        """Raise GraphError if the adapter cannot run at all (e.g. rclpy missing)."""

    def poll(self) -> GraphState:
        raise NotImplementedError

    def stop(self) -> None:
        pass

    def hear_from(self, tcp_changes: Callable[[], int | None], ran: Callable[[], dict[int, float] | None]) -> None:
        """What the agent's probes can tell an adapter that reads the host itself (see AutoAdapter):
        a count that moves when a TCP socket changes state, and each process's CPU seconds."""


class ChildAdapter(Adapter):
    """An adapter whose middleware client runs in a child process (`python -m <module>`) that
    prints one JSON object per line: {"state": ...} or {"error": "..."}, or {"answer": "..."} for a
    passenger (see Ros2Adapter.carry). The child is restarted when it exits; a child silent for
    `timeout` seconds makes polls fail."""

    module = ""
    env: dict[str, str] = {}  # for the child, where the environment does not set them already
    child_args: list[str] = []  # for the child's command line, after --interval

    def __init__(self, interval: float = 0.5, timeout: float = 5.0):
        self.interval = interval
        self.timeout = timeout
        self._proc: subprocess.Popen | None = None
        self._latest: GraphState | None = None
        self._error = ""
        self._heard_at = 0.0
        self._lock = threading.Lock()
        self._spawning = threading.Lock()
        self._answers: Callable[[subprocess.Popen, str], None] | None = None  # a passenger's

    def respawn(self, old: subprocess.Popen | None) -> subprocess.Popen:
        """The child now: a new one if `old` is still it (killed first if it runs), for the adapter
        whose child exited and for a passenger whose child stopped answering, whichever comes first."""
        with self._spawning:
            if self._proc is old:
                if old is not None and old.poll() is None:
                    old.kill()
                    old.wait()
                self._spawn()
            return self._proc

    def _spawn(self) -> None:
        self._proc = subprocess.Popen([sys.executable, "-m", self.module, "--interval", str(self.interval),
                                       *self.child_args],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                      text=True, env={**self.env, **os.environ})
        self._heard_at = time.monotonic()
        threading.Thread(target=self._read, args=(self._proc,), daemon=True, name=f"{self.name}-reader").start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            try:
                message = json.loads(line)
                if isinstance(message, dict) and "answer" in message and self._answers is not None:
                    self._answers(proc, str(message["answer"]))
                    continue
                if "error" in message:
                    state, error = None, str(message["error"])[:500]
                else:
                    state, error = GraphState.from_dict(message.get("state")), ""
            except (ValueError, AttributeError, GraphError) as e:
                state, error = None, f"unreadable line from the {self.name} reader: {e}"
            with self._lock:
                self._heard_at = time.monotonic()
                self._error = error
                if state is not None:
                    self._latest = state

    def start(self) -> None:
        """Start the child and wait (up to `timeout`) for its first word: a graph, or why not."""
        self.respawn(None)
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline and self._proc.poll() is None:
            with self._lock:
                if self._latest is not None or self._error:
                    break
            time.sleep(0.05)
        with self._lock:
            if self._latest is None and self._error:
                raise GraphError(self._error)

    def poll(self) -> GraphState:
        proc = self._proc
        if proc.poll() is not None:
            code = proc.returncode
            with self._lock:
                error = self._error
            self.respawn(proc)
            raise GraphError(error or f"the {self.name} reader exited with {code}; restarted")
        with self._lock:
            silent = time.monotonic() - self._heard_at
            if silent > self.timeout:
                raise GraphError(f"the {self.name} reader has said nothing for {silent:.0f} s")
            if self._error:
                raise GraphError(self._error)
            if self._latest is None:
                raise GraphError(f"the {self.name} reader has not described the graph yet")
            return self._latest

    def stop(self) -> None:
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        if self._answers is not None:  # a child that publishes leaves its DDS domain at the end of its input
            try:
                proc.stdin.close()
                proc.wait(2 * self.interval + 1)
                return
            except (OSError, subprocess.TimeoutExpired):
                pass
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Follower:
    """Polls an adapter every interval in a thread of its own and updates the graph."""

    def __init__(self, adapter: Adapter, graph: Graph):
        self.adapter = adapter
        self.graph = graph
        self._stop = threading.Event()
        self._started = threading.Event()
        self._start_error = ""
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"graph-{adapter.name}")

    def start(self, wait: bool = False) -> None:
        """Start the adapter and follow it in the background; with wait, return once it has
        started, raising GraphError if it could not."""
        self._thread.start()
        if wait:
            self._started.wait()
            if self._start_error:
                raise GraphError(self._start_error)

    def poll_once(self) -> None:
        try:
            state = self.adapter.poll()
        except Exception as e:  # garbage from the middleware must not end the thread
            if str(e) != self.graph.error:
                log.warning("graph (%s): %s; keeping the last good graph, marked stale", self.adapter.name, e)
            self.graph.failed(str(e))
            return
        if self.graph.error:
            log.info("graph (%s): reading again", self.adapter.name)
        if state.truncated and state.truncated != self.graph.truncated:
            log.warning("graph (%s): truncated: %s", self.adapter.name, state.truncated)
        self.graph.update(state)

    def _run(self) -> None:
        try:
            self.adapter.start()
        except GraphError as e:
            self._start_error = f"graph ({self.adapter.name}): {e}"
            log.warning("%s; the agent goes on without a graph", self._start_error)
            self.graph.failed(str(e))
            return
        finally:
            self._started.set()
        while not self._stop.is_set():
            self.poll_once()
            self._stop.wait(self.adapter.interval)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(10)
        self.adapter.stop()
