"""The kernels Drums is proven on besides the host's own: Debian's builds, pinned by version and hash.

Each is booted under qemu by `make test-kernels` (tests/kernels/run.py), which runs the portable part
of the test suite there (tests marked `kernel`) on every attach path that kernel offers. The CI
kernels run in `.ci/run` after `make test`. An archive that no longer serves a pinned version makes
that kernel fail to fetch, said in one line; pin the archive's current build then.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Package:
    name: str
    version: str
    sha256: str
    arch: str = ""  # another architecture's package (arm64); "" this machine's or any


@dataclass(frozen=True)
class Kernel:
    name: str  # as make test-kernels KERNELS=... takes it
    suite: str  # the Debian suite that serves it
    release: str  # what uname -r says in it
    image: Package
    headers: tuple[Package, ...]  # the flavour's, then the common ones (bcc compiles against both)
    ci: bool  # run by .ci/run
    robots: str  # which robots run such a kernel
    arch: str = ""  # "arm64": booted under qemu-system-aarch64 over a Debian arm64 root (tests/kernels/arm64.py)


def _pkgs(version: str, *pairs: tuple[str, str], arch: str = "") -> tuple[Package, ...]:
    return tuple(Package(name, version, sha, arch) for name, sha in pairs)


_V510, _V61, _V612 = "5.10.262-1", "6.1.192-3", "6.12.118-1~deb12u1"

MATRIX = (
    Kernel("5.10", "bullseye", "5.10.0-46-amd64",
           *_pkgs(_V510, ("linux-image-5.10.0-46-amd64-unsigned",
                          "c0e850b617fa3afedb2165b1a42cda53a487a9c6e9a13f00777f9296b7c3b06b")),
           _pkgs(_V510, ("linux-headers-5.10.0-46-amd64", "7b4eeca0a36e33faa7fd2b48f304b2a033d80f72e5952f7746de261d9796b06e"),
                 ("linux-headers-5.10.0-46-common", "3b5bc361e77e67b122455a8cce26495ff5ce59fc147bb089f3cbedf6b4e2ec31")),
           ci=True, robots="Debian 11; the oldest line robots run (JetPack 5's 5.10)"),
    Kernel("6.1", "bookworm", "6.1.0-57-amd64",
           *_pkgs(_V61, ("linux-image-6.1.0-57-amd64-unsigned",
                         "f43a8dbe0b318a5491880233bb20982dc9cc8ef103dd361cd56499eea15c5191")),
           _pkgs(_V61, ("linux-headers-6.1.0-57-amd64", "515e0075e18508f9d048a99b776e155a30bca68da16d3d614323c4384f53905d"),
                 ("linux-headers-6.1.0-57-common", "5d248d9fff260d3750cf1a4223d9477c789e7fe6c8739f4b03f9b31431c2e5da")),
           ci=True, robots="Debian 12; before the socket tracepoints (6.6), as Ubuntu 22.04's 5.15"),
    Kernel("6.1-rt", "bookworm", "6.1.0-57-rt-amd64",
           *_pkgs(_V61, ("linux-image-6.1.0-57-rt-amd64-unsigned",
                         "d1d2bdd62a0b6d33cbdbc318a89479b2d143780c2ab3d5d942eaa03d09410d88")),
           _pkgs(_V61, ("linux-headers-6.1.0-57-rt-amd64", "bc8671478d7e55902530b4f20a8fa74e00fa656bbe0290ba79941a272cdb6f59"),
                 ("linux-headers-6.1.0-57-common-rt", "2a8222eb2a63e4379d8c3add06b1979d5778a7eab1ad8620f088474250d9fa7a")),
           ci=True, robots="Debian 12 PREEMPT_RT"),
    Kernel("6.12", "bookworm", "6.12.118+deb12-amd64",
           *_pkgs(_V612, ("linux-image-6.12.118+deb12-amd64-unsigned",
                          "628257aaa694038ae776ddc9cbc89c096b4df55e6fccd8a51352288af69b4ad9")),
           _pkgs(_V612, ("linux-headers-6.12.118+deb12-amd64", "a19e90266250d37e45448494da6e1bfd76a3b2935d28f99e6db2fbd34a5a7f8e"),
                 ("linux-headers-6.12.118+deb12-common", "ed74603a3ba75ea8dfa271cbf5bf79a9a272f56e898729b7d5d02c60703d74c5")),
           ci=False, robots="Debian 13 (bookworm-backports' build); after the socket tracepoints"),
    Kernel("6.12-rt", "bookworm", "6.12.118+deb12-rt-amd64",
           *_pkgs(_V612, ("linux-image-6.12.118+deb12-rt-amd64-unsigned",
                          "f8332644589632503e3f4644a152412e5965e13b6b8566ea34ee0dd3c5787f1a")),
           _pkgs(_V612, ("linux-headers-6.12.118+deb12-rt-amd64", "42722837e56b81b2949a857ce3d69c8b92ff5d407fc1ce0af162e964614dcac8"),
                 ("linux-headers-6.12.118+deb12-common-rt", "0246c6e2a07f377a9633c733a855ac6fba2e3c931201d6d2256d8d7b41cbad84")),
           ci=False, robots="Debian 13 PREEMPT_RT"),
    Kernel("6.1-arm64", "bookworm", "6.1.0-57-arm64",
           *_pkgs(_V61, ("linux-image-6.1.0-57-arm64-unsigned",
                         "b19fb23a7313b6e345c7ef7aa8d2ce44381d32111403b86040bdada12da8c379"), arch="arm64"),
           _pkgs(_V61, ("linux-headers-6.1.0-57-arm64", "c35a734c09d05cb1bcce0bb7f98c4177c030d2da4f23fa076d352f627116854c"),
                 arch="arm64")
           + _pkgs(_V61, ("linux-headers-6.1.0-57-common", "5d248d9fff260d3750cf1a4223d9477c789e7fe6c8739f4b03f9b31431c2e5da")),
           ci=False, robots="arm64 boards (Jetson, Raspberry Pi): no fentry before 6.0 there", arch="arm64"),
)
