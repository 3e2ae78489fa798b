#!/usr/bin/env bash
# Prepares a Debian/Ubuntu host (as root) for the Drums agent and its tests: system packages,
# kernel headers for bcc, tracefs and bpffs, and a virtual environment. Idempotent: a second run
# installs nothing and takes a second.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
HEADERS_DIR=${DRUMS_HEADERS_DIR:-/var/cache/drums/kernel-headers}
APT_PACKAGES=(python3-bpfcc python3-venv libbpf1 bpftool iproute2)
# For the tests: Prometheus and VictoriaMetrics run the mixin, Graphviz draws the graph, Chromium
# loads the agent's page, tmux runs `drums top` in a terminal, gcc builds a clock a process preloads.
[ "${DRUMS_SETUP_TEST:-0}" = 1 ] && APT_PACKAGES+=(prometheus victoria-metrics iperf3 tcpdump graphviz chromium tmux gcc libc6-dev)
# For make test-kernels: qemu boots the matrix's kernels (virtme-ng, pinned in the test lock, drives
# it and wants a static busybox for the guest's first steps), kmod indexes their modules; the arm64
# kernel boots over an arm64 root made by debootstrap, whose programs qemu-user-static runs here.
[ "${DRUMS_SETUP_KERNELS:-0}" = 1 ] && APT_PACKAGES+=(qemu-system-x86 busybox-static kmod qemu-system-arm qemu-user-static debootstrap)
# For the benchmarks: node_exporter is a peer (its service is disabled again: the benchmark runs it).
[ "${DRUMS_SETUP_BENCH:-0}" = 1 ] && APT_PACKAGES+=(prometheus-node-exporter)

log() { echo "setup: $*" >&2; }

need_apt=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || need_apt+=("$p")
done
# Kernel headers: the running kernel's own package where the distribution has one.
release=$(uname -r)
if [ ! -e "/lib/modules/$release/build/include" ] && [ ! -e "$HEADERS_DIR/include" ]; then
  need_headers=1
else
  need_headers=0
fi
if [ ${#need_apt[@]} -gt 0 ] || [ $need_headers = 1 ]; then
  export DEBIAN_FRONTEND=noninteractive
  log "apt-get install ${need_apt[*]:-} (kernel headers: $([ $need_headers = 1 ] && echo needed || echo present))"
  apt-get update -qq
  [ ${#need_apt[@]} -gt 0 ] && apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
  if [[ " ${need_apt[*]} " == *" prometheus-node-exporter "* ]]; then
    systemctl disable --now prometheus-node-exporter >/dev/null 2>&1 || true
  fi
  if [ $need_headers = 1 ]; then
    if apt-get install -y -qq --no-install-recommends "linux-headers-$release" >/dev/null 2>&1; then
      log "installed linux-headers-$release"
    else
      # No package for this kernel (custom build): bcc only needs headers for tracepoint argument
      # layouts, which it reads from tracefs anyway; kernel struct offsets come from BTF at run time.
      log "no linux-headers-$release package; using the distribution's generic headers"
      arch=$(dpkg --print-architecture)
      apt-get install -y -qq --no-install-recommends "linux-headers-$arch" >/dev/null
      common=$(ls -d /usr/src/linux-headers-*-common 2>/dev/null | sort -V | tail -n1)
      flavour=$(ls -d /usr/src/linux-headers-*-"$arch" 2>/dev/null | sort -V | tail -n1)
      rm -rf "$HEADERS_DIR.tmp" && mkdir -p "$HEADERS_DIR.tmp"
      cp -rs "$common/." "$HEADERS_DIR.tmp/"
      cp -rsf "$flavour/." "$HEADERS_DIR.tmp/"
      rm -rf "$HEADERS_DIR" && mv "$HEADERS_DIR.tmp" "$HEADERS_DIR"
      log "merged $common and $flavour into $HEADERS_DIR"
    fi
  fi
fi

# bcc attaches tracepoints through tracefs; the agent pins programs and maps in bpffs.
mountpoint -q /sys/kernel/tracing || mount -t tracefs tracefs /sys/kernel/tracing || log "cannot mount tracefs"
mountpoint -q /sys/fs/bpf || mount -t bpf bpf /sys/fs/bpf || log "cannot mount bpffs"

# bcc's Python module lives in Debian's dist-packages: the venv must come from that interpreter.
if [ ! -x "$VENV/bin/python" ]; then
  /usr/bin/python3 -m venv --system-site-packages "$VENV"
fi
# Exactly the versions in the lock file (`make lock` writes it), checked against its hashes; then
# Drums itself, with the setuptools the venv came with, so nothing unpinned is fetched to build it.
lock=requirements.lock
[ "${DRUMS_SETUP_TEST:-0}" = 1 ] && lock=requirements-test.lock
stamp="$VENV/.installed-$(sha256sum "$lock" pyproject.toml | sha256sum | cut -c1-16)"
if [ ! -e "$stamp" ]; then
  "$VENV/bin/pip" install -q --disable-pip-version-check --require-hashes -r "$lock"
  "$VENV/bin/pip" install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
  rm -f "$VENV"/.installed*
  touch "$stamp"
fi
# An editable install leaves Drums' own modules uncompiled, and a host that writes no bytecode
# (PYTHONDONTWRITEBYTECODE) compiled all fifty at every start: a third of a warm start's 0.7 s.
# Only what changed is compiled again; Python checks each file's time, so none goes stale.
"$VENV/bin/python" -m compileall -q drums
