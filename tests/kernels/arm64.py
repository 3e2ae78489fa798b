"""The arm64 row's root file system: this machine's root cannot serve an arm64 kernel, so a Debian
arm64 root is made once under ROOT (debootstrap, its arm64 programs run here by qemu-user-static's
binfmt handler) with Python, bcc and Drums' locked dependencies in a venv at the checkout's own
path, and the checkout's working tree is copied in before each run. virtme-ng boots the kernel over
it under qemu-system-aarch64 (`vng --arch arm64 --root`). ROS 2's wheels are x86_64 only: the
ROS 2 tests are not run there.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess

ROOT = "/var/cache/drums/rootfs-arm64"
SUITE = "bookworm"
PACKAGES = ("python3", "python3-venv", "python3-bpfcc", "libbpf1", "bpftool", "iproute2", "kmod", "busybox-static",
            "procps", "ca-certificates")
# What the tests need of the test lock, beside the agent's own lock.
TEST_PINS = ("pytest", "pluggy", "iniconfig", "packaging", "prometheus-client")
COPIED = ("drums", "tests", "bpf", "pyproject.toml")
_BINFMT = "/proc/sys/fs/binfmt_misc"


def _run(argv: list[str], what: str) -> None:
    got = subprocess.run(argv, capture_output=True, text=True)
    if got.returncode:
        tail = (got.stderr.strip() or got.stdout.strip()).splitlines()[-1:] or ["failed"]
        raise RuntimeError(f"{what}: {tail[0][:300]}")


def _binfmt() -> None:
    """Make this machine run arm64 programs through qemu-user-static (debootstrap's second stage, pip)."""
    if not os.path.exists(f"{_BINFMT}/register"):
        subprocess.run(["mount", "-t", "binfmt_misc", "binfmt_misc", _BINFMT], capture_output=True)
    if not os.path.exists(f"{_BINFMT}/qemu-aarch64"):
        subprocess.run(["update-binfmts", "--enable", "qemu-aarch64"], capture_output=True)
    if not os.path.exists(f"{_BINFMT}/qemu-aarch64"):
        raise RuntimeError("this machine cannot run arm64 programs: qemu-user-static's binfmt handler "
                           "(qemu-aarch64) is not registered (apt-get install qemu-user-static)")


def _pins(lock: str, names: tuple[str, ...] | None) -> str:
    """The entries of a lock file (each a `name==version` line and its hashes) for `names`, or all."""
    with open(lock) as f:
        blocks = re.split(r"(?m)^(?=[A-Za-z0-9_.-]+==)", f.read())
    return "".join(b for b in blocks if re.match(r"[A-Za-z0-9_.-]+==", b)
                   and (names is None or b.split("==")[0] in names))


def _chroot(root: str, *argv: str) -> list[str]:
    return ["chroot", root, *argv]


def root(checkout: str, mirror: str, shared: tuple[str, ...] = (), modules: str = "") -> str:
    """The arm64 root, made if missing, with the checkout's working tree copied in at its own path,
    a place for each of this machine's `shared` folders, which the guest mounts at their own paths,
    and the kernel's `modules` (in a shared folder) linked where modprobe looks for them."""
    made = os.path.join(ROOT, ".drums-made")
    inside = ROOT + checkout
    if not os.path.exists(made):
        _binfmt()
        if not os.path.exists(os.path.join(ROOT, "usr", "bin", "python3")):
            shutil.rmtree(ROOT, ignore_errors=True)
            _run(["debootstrap", "--arch=arm64", "--variant=minbase", f"--include={','.join(PACKAGES)}", SUITE,
                  ROOT, mirror], f"debootstrap --arch=arm64 {SUITE}")
        # What reaches the package registries from here reaches them from there.
        for path in ("/etc/resolv.conf", "/etc/hosts", "/etc/ssl/certs/ca-certificates.crt", "/etc/pip.conf"):
            if os.path.exists(path):
                shutil.copy(path, ROOT + path)
        os.makedirs(inside, exist_ok=True)
        with open(os.path.join(ROOT, "tmp", "requirements.lock"), "w") as f:
            f.write(_pins(os.path.join(checkout, "requirements.lock"), None)
                    + _pins(os.path.join(checkout, "requirements-test.lock"), TEST_PINS))
        _run(_chroot(ROOT, "python3", "-m", "venv", "--system-site-packages", f"{checkout}/.venv"), "venv")
        _run(_chroot(ROOT, f"{checkout}/.venv/bin/pip", "install", "-q", "--disable-pip-version-check",
                     "--only-binary", ":all:", "--no-deps", "-r", "/tmp/requirements.lock"), "pip install (arm64)")
        open(made, "w").close()
    for path in shared:
        os.makedirs(ROOT + path, exist_ok=True)
    if modules:
        link = os.path.join(ROOT, "lib", "modules", os.path.basename(modules))
        os.makedirs(os.path.dirname(link), exist_ok=True)
        if os.path.islink(link) or os.path.exists(link):
            os.unlink(link)
        os.symlink(modules, link)
    for name in COPIED:
        target = os.path.join(inside, name)
        if os.path.isdir(target):
            shutil.rmtree(target)
        elif os.path.exists(target):
            os.unlink(target)
        source = os.path.join(checkout, name)
        if os.path.isdir(source):
            shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(source, target)
    return ROOT
