"""One agent per pin directory.

Two agents on one pin directory would share its programs and maps: the second adopts the first's
pins as a warm start, and whichever stops first removes them, which silently detaches the other's
programs while it still reports them attached. So an agent holds an exclusive lock named after
its pin directory while it runs, and `drums unload` takes the same lock before it removes pins.
"""
from __future__ import annotations

import fcntl
import os
from typing import IO

from drums.errors import UsageError

LOCK_DIR = "/run/drums"


class PinLock:
    """The held lock; close() lets it go and removes its file."""

    def __init__(self, f: IO, path: str):
        self._f, self.path = f, path

    def close(self) -> None:
        if not self._f.closed:
            os.unlink(self.path)  # before unlocking: whoever locks next makes a new file
            self._f.close()


def hold(pin_dir: str, lock_dir: str = LOCK_DIR) -> PinLock | None:
    """The lock of `pin_dir`, held until closed (or the process ends). None where the lock cannot
    be made (not root, or a read-only /run): such a process cannot pin programs either, or runs
    where no other agent can share its pins."""
    name = os.path.abspath(pin_dir).strip("/").replace("/", "_") or "root"
    path = os.path.join(lock_dir, f"{name}.lock")
    while True:
        try:
            os.makedirs(lock_dir, exist_ok=True)
            f = open(path, "a+")
        except OSError:
            return None
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "?"
            f.close()
            raise UsageError(f"another drums agent (pid {holder}) uses the pins in {pin_dir}: stop it, or give "
                             "this one a --pin-dir of its own") from None
        try:
            if os.stat(path).st_ino == os.fstat(f.fileno()).st_ino:
                break
        except FileNotFoundError:
            pass
        f.close()  # locked a file its holder removed as it let go: lock the new one
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return PinLock(f, path)
