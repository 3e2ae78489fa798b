#!/usr/bin/env bash
# `make test-chroot SUITE=trixie`: the whole `make test` in a fresh clone of this checkout inside a
# Debian root file system of another release (its Python, bcc and packages; this machine's kernel),
# made once with debootstrap under /var/cache/drums/rootfs-SUITE. Debian 13 (trixie) is Python 3.13.
set -euo pipefail
cd "$(dirname "$0")/.."

SUITE=${SUITE:-trixie}
ROOT=/var/cache/drums/rootfs-$SUITE
log() { echo "test-in-chroot: $*" >&2; }

mirror=$(grep -hoE '^(URIs:|deb)[^#]*https?://[^ ]*/debian/?( |$)' /etc/apt/sources.list /etc/apt/sources.list.d/* 2>/dev/null \
         | grep -oE 'https?://[^ ]*/debian' | head -n1 || true)
[ -n "$mirror" ] || { log "no Debian archive among apt's sources"; exit 2; }
if [ ! -x "$ROOT/usr/bin/python3" ]; then
  command -v debootstrap >/dev/null || apt-get install -y -qq --no-install-recommends debootstrap >/dev/null
  log "debootstrap $SUITE into $ROOT (from $mirror)"
  rm -rf "$ROOT"
  debootstrap --variant=minbase --include=python3,python3-venv,make,git,ca-certificates,iproute2 \
    "$SUITE" "$ROOT" "$mirror" >/dev/null
fi
# What reaches the package registries from here reaches them from there: this host's CA bundle and
# pip settings. No service starts inside.
cp /etc/ssl/certs/ca-certificates.crt "$ROOT/etc/ssl/certs/ca-certificates.crt"
cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
cp /etc/hosts "$ROOT/etc/hosts"  # this host's own name resolves there as here
[ -e /etc/pip.conf ] && cp /etc/pip.conf "$ROOT/etc/pip.conf"
[ -d /etc/xdg/pip ] && mkdir -p "$ROOT/etc/xdg" && cp -r /etc/xdg/pip "$ROOT/etc/xdg/"
printf '#!/bin/sh\nexit 101\n' > "$ROOT/usr/sbin/policy-rc.d" && chmod +x "$ROOT/usr/sbin/policy-rc.d"

# A fresh clone of what is committed, as CI tests it.
rm -rf "$ROOT/work/drums"
mkdir -p "$ROOT/work"
git clone -q "$PWD" "$ROOT/work/drums"

mounted=()
bind() {  # bind(source, options): the host's source at the same path inside
  mkdir -p "$ROOT$1"
  mount $2 "$1" "$ROOT$1"
  mounted=("$ROOT$1" "${mounted[@]}")
}
cleanup() { for m in "${mounted[@]}"; do umount -R "$m" 2>/dev/null || umount -lR "$m"; done; }
trap cleanup EXIT
# The root a mount of its own, as a system's is: `ip netns exec` remounts / (--make-rslave).
mount --bind "$ROOT" "$ROOT" && mounted=("$ROOT" "${mounted[@]}")
mkdir -p "$ROOT/proc" "$ROOT/tmp"
mount -t proc proc "$ROOT/proc" && mounted=("$ROOT/proc" "${mounted[@]}")
# /tmp emptied, on disk as a host's: the disk I/O tests write there (on a tmpfs they were skipped).
find "$ROOT/tmp" -mindepth 1 -delete && chmod 1777 "$ROOT/tmp"
bind /sys --rbind    # bpffs and tracefs with it
bind /dev --rbind
bind /run --rbind    # network namespaces (ip netns) live in /run/netns
# Kernel headers for bcc: the running kernel's own, or setup's merged tree (links into /usr/src).
for d in /lib/modules /usr/src /var/cache/drums/kernel-headers; do
  [ -d "$d" ] && bind "$d" --bind
done

log "make test in $SUITE ($(chroot "$ROOT" python3 --version))"
chroot "$ROOT" make -C /work/drums test
