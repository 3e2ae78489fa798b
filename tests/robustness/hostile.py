"""Hostile HTTP clients, each in a process of its own so that the scrapes timed beside them do not
share a GIL with them: `python -m tests.robustness.hostile slowloris|idle|scrapes HOST PORT N`.

- slowloris: holds N connections that send a request head a header line at a time (one line per
  connection every ROUND seconds) and never finish it; a connection the server closes is opened
  again on the next round, as the slowloris tool does.
- idle: holds N connections that send nothing.
- scrapes: N concurrent GETs of /metrics; prints each one's seconds (or null when it failed) and
  the body's drums_agent_collect_duration_seconds (which tells the snapshots apart) as JSON.

slowloris and idle print "holding K" once they hold as many as they could, then run until killed.
"""
import asyncio
import json
import resource
import sys
import time

ROUND = 2.0


def _more_files(n: int) -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(hard, n + 100), max(hard, n + 100)))


async def _open(host: str, port: int, head: bytes = b""):
    try:
        reader, writer = await asyncio.open_connection(host, port)
        if head:
            writer.write(head)
        return reader, writer
    except OSError:
        return None


async def _hold(host: str, port: int, n: int, trickle: bool) -> None:
    head = b"GET /metrics HTTP/1.1\r\nHost: drums\r\n" if trickle else b""
    held = [None] * n
    said = False
    line = 0
    while True:
        for i in range(0, n, 200):  # in batches: the listen backlog is not a test of its own
            batch = range(i, min(n, i + 200))
            reopened = await asyncio.gather(*(_open(host, port, head) for k in batch if held[k] is None))
            it = iter(reopened)
            for k in batch:
                if held[k] is None:
                    held[k] = next(it)
        if not said:
            print(f"holding {sum(c is not None for c in held)}", flush=True)
            said = True
        await asyncio.sleep(ROUND)
        line += 1
        for k, connection in enumerate(held):
            if connection is None:
                continue
            reader, writer = connection
            if reader.at_eof() or writer.is_closing():
                writer.close()
                held[k] = None
            elif trickle:
                writer.write(b"X-%d: %d\r\n" % (line, k))


async def _scrape(host: str, port: int) -> tuple[float | None, str | None]:
    began = time.monotonic()
    try:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), 10)
        writer.write(b"GET /metrics HTTP/1.1\r\nHost: drums\r\nConnection: close\r\n\r\n")
        answer = await asyncio.wait_for(reader.read(), 10)
        writer.close()
    except (OSError, asyncio.TimeoutError):
        return None, None
    head, _, body = answer.partition(b"\r\n\r\n")
    if not head.startswith(b"HTTP/1.1 200"):
        return None, None
    stamp = next((line.split()[-1].decode() for line in body.splitlines()
                  if line.startswith(b"drums_agent_collect_duration_seconds ")), None)
    return time.monotonic() - began, stamp


async def _scrapes(host: str, port: int, n: int) -> None:
    results = await asyncio.gather(*(_scrape(host, port) for _ in range(n)))
    print(json.dumps({"seconds": [r[0] for r in results], "snapshots": len({r[1] for r in results if r[1]})}))


def main(kind: str, host: str, port: str, n: str) -> None:
    _more_files(int(n))
    if kind == "scrapes":
        asyncio.run(_scrapes(host, int(port), int(n)))
    else:
        asyncio.run(_hold(host, int(port), int(n), trickle=kind == "slowloris"))


if __name__ == "__main__":
    main(*sys.argv[1:])
