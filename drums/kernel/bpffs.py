"""Pinned BPF objects, read through libbpf without bcc or its compiler.

The loader (drums.kernel.loader) compiles and attaches the probes, then pins their maps and links
under /sys/fs/bpf/drums. The long-running agent only opens those pins and reads the maps in
batches, so it never maps LLVM into its address space.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno
import mmap
import os
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache

from drums.errors import KernelError, ProbeError

BPFFS = "/sys/fs/bpf"
PIN_ROOT = os.path.join(BPFFS, "drums")
PERCPU_TYPES = {5, 6, 10}  # BPF_MAP_TYPE_PERCPU_HASH, PERCPU_ARRAY, LRU_PERCPU_HASH
ARRAY_TYPES = {2, 6}  # BPF_MAP_TYPE_ARRAY, PERCPU_ARRAY
LRU_TYPES = {9, 10}  # BPF_MAP_TYPE_LRU_HASH, LRU_PERCPU_HASH: the kernel evicts entries from them
_BATCH = 4096  # entries of one batch read at most
_BATCH_LEAST = 16  # and at least, whatever the last read found
_BATCH_BYTES = 1 << 18  # and this many bytes of values: a buffer for 4,096 of 8 KiB each would be 32 MiB
# What bpf_map_lookup_batch fails with where the map type or kernel has no batch operations.
_NO_BATCH = {errno.EINVAL, errno.EOPNOTSUPP, 524}  # 524: the kernel's ENOTSUPP


class _MapInfo(ctypes.Structure):
    # The head of struct bpf_map_info (include/uapi/linux/bpf.h); the kernel fills what fits.
    _fields_ = [
        ("type", ctypes.c_uint32),
        ("id", ctypes.c_uint32),
        ("key_size", ctypes.c_uint32),
        ("value_size", ctypes.c_uint32),
        ("max_entries", ctypes.c_uint32),
        ("map_flags", ctypes.c_uint32),
        ("name", ctypes.c_char * 16),
    ]


class _TestRunOpts(ctypes.Structure):
    # struct bpf_test_run_opts of libbpf 1.1, up to what a raw tracepoint program's run uses.
    _fields_ = [
        ("sz", ctypes.c_size_t),
        ("data_in", ctypes.c_void_p),
        ("data_out", ctypes.c_void_p),
        ("data_size_in", ctypes.c_uint32),
        ("data_size_out", ctypes.c_uint32),
        ("ctx_in", ctypes.c_void_p),
        ("ctx_out", ctypes.c_void_p),
        ("ctx_size_in", ctypes.c_uint32),
        ("ctx_size_out", ctypes.c_uint32),
        ("retval", ctypes.c_uint32),
    ]


@lru_cache(maxsize=1)
def libbpf() -> ctypes.CDLL:
    path = ctypes.util.find_library("bpf") or "libbpf.so.1"
    try:
        lib = ctypes.CDLL(path, use_errno=True)
    except OSError:
        raise KernelError("libbpf is not installed (Debian/Ubuntu: apt-get install libbpf1)") from None
    lib.bpf_obj_get.argtypes = [ctypes.c_char_p]
    lib.bpf_obj_pin.argtypes = [ctypes.c_int, ctypes.c_char_p]
    lib.bpf_map_lookup_elem.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    lib.bpf_map_delete_elem.argtypes = [ctypes.c_int, ctypes.c_void_p]
    lib.bpf_map_update_elem.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint64]
    lib.bpf_map_get_next_key.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    for batch in (lib.bpf_map_lookup_batch, lib.bpf_map_lookup_and_delete_batch):
        batch.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                          ctypes.POINTER(ctypes.c_uint32), ctypes.c_void_p]
    lib.bpf_obj_get_info_by_fd.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint32)]
    lib.bpf_prog_test_run_opts.argtypes = [ctypes.c_int, ctypes.POINTER(_TestRunOpts)]
    return lib


class _BatchError(ProbeError):
    def __init__(self, err: int, message: str):
        super().__init__(message)
        self.errno = err


def _check(ret: int, what: str) -> int:
    if ret < 0:
        err = ctypes.get_errno() or -ret
        raise ProbeError(f"{what}: {os.strerror(err)}")
    return ret


def prog_runs_missed(fd: int, offset: int) -> int:
    """How many times the kernel skipped the program because it was running on that CPU already
    (struct bpf_prog_info's recursion_misses, at `offset`: Linux >= 5.12). On a PREEMPT_RT kernel a
    preempted program can be the one running, and its CPU's next event is then not counted."""
    info = ctypes.create_string_buffer(offset + 8)
    size = ctypes.c_uint32(offset + 8)
    _check(libbpf().bpf_obj_get_info_by_fd(fd, info, ctypes.byref(size)), "program info")
    return int.from_bytes(info.raw[offset:offset + 8], "little") if size.value >= offset + 8 else 0


def obj_get(path: str) -> int:
    """An fd of the pinned program, link or map."""
    return _check(libbpf().bpf_obj_get(path.encode()), f"open {path}")


def pin(fd: int, path: str) -> None:
    _check(libbpf().bpf_obj_pin(fd, path.encode()), f"pin {path}")


def run_program(fd: int, *args: int) -> int:
    """Run a raw tracepoint program once, as if its tracepoint had passed it `args`
    (BPF_PROG_TEST_RUN, Linux >= 5.10); what it returned."""
    ctx = (ctypes.c_uint64 * len(args))(*args)
    opts = _TestRunOpts(sz=ctypes.sizeof(_TestRunOpts), ctx_in=ctypes.addressof(ctx), ctx_size_in=ctypes.sizeof(ctx))
    _check(libbpf().bpf_prog_test_run_opts(fd, ctypes.byref(opts)), "run a BPF program")
    return opts.retval


def possible_cpus() -> int:
    """Per-CPU map values hold one slot for every possible CPU, not only the online ones."""
    with open("/sys/devices/system/cpu/possible") as f:
        count = 0
        for part in f.read().strip().split(","):
            lo, _, hi = part.partition("-")
            count += int(hi or lo) - int(lo) + 1
        return count


class PinnedMap:
    """A BPF map opened from its pin; iterated in batches of raw (key, value) bytes."""

    def __init__(self, path: str):
        self._init(obj_get(path), path)

    @classmethod
    def from_fd(cls, fd: int, name: str) -> "PinnedMap":
        """A map held by a bcc object in this process (attach paths that cannot be pinned)."""
        m = cls.__new__(cls)
        m._init(os.dup(fd), name)
        return m

    def _init(self, fd: int, path: str) -> None:
        self.path = path
        self.fd = fd
        info = _MapInfo()
        size = ctypes.c_uint32(ctypes.sizeof(info))
        _check(libbpf().bpf_obj_get_info_by_fd(self.fd, ctypes.byref(info), ctypes.byref(size)), "map info")
        self.type = info.type
        self.key_size = info.key_size
        self.declared_value_size = info.value_size
        self.max_entries = info.max_entries
        self.ncpus = possible_cpus() if info.type in PERCPU_TYPES else 1
        # The kernel rounds each per-CPU value up to 8 bytes.
        self.value_size = (info.value_size + 7) // 8 * 8 if self.ncpus > 1 else info.value_size
        self.value_stride = self.value_size * self.ncpus
        self._batch_ok = True
        self._last_count = self.max_entries  # entries the last batch read found

    def memory(self) -> int:
        """The kernel memory the map holds now, as the kernel says of its descriptor (0 if it does
        not): a hash map made without preallocation grows with its entries."""
        try:
            with open(f"/proc/self/fdinfo/{self.fd}", "rb") as f:
                for line in f:
                    if line.startswith(b"memlock:"):
                        return int(line.split()[1])
        except (OSError, ValueError, IndexError):
            pass
        return 0

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    @contextmanager
    def mapped(self) -> Iterator[mmap.mmap]:
        """The values of an array map made with BPF_F_MMAPABLE, in place and read-only, for the
        length of a `with` (no view of it may outlive it): what the programs write shows there, with
        no copy. Mapped anew each time: the pages are the kernel's, held with the map whether or not
        it is mapped (drums_probe_map_memory_bytes), and a mapping kept between reads would count
        them as the agent's own memory too (the threads' slots: 1.6 MB of its USS). Mapping them
        costs 0.2 ms."""
        size = self.max_entries * ((self.value_size + 7) // 8 * 8)
        try:
            mapping = mmap.mmap(self.fd, -(-size // mmap.PAGESIZE) * mmap.PAGESIZE, mmap.MAP_SHARED, mmap.PROT_READ)
        except OSError as e:
            raise KernelError(f"cannot map {self.path} into memory: {e.strerror}") from None
        try:
            yield mapping
        finally:
            mapping.close()

    def read(self, delete: bool = False) -> tuple[bytes, bytes, int]:
        """All entries as (keys, values, count): contiguous buffers, as the kernel returned them.
        `delete`: each entry is deleted as it is read (a hash map's)."""
        if self._batch_ok:
            try:
                return self._read_batch(delete)
            except _BatchError as e:
                # Array maps before kernel 5.6 and some map types have no batch operations; any
                # other failure (no memory, say) is this read's only.
                self._batch_ok = e.errno not in _NO_BATCH
        keys, values, count = self._read_each()
        for i in range(count if delete else 0):
            self.delete(keys[i * self.key_size:(i + 1) * self.key_size])
        return keys, values, count

    def lookup(self, key: bytes) -> bytes | None:
        """The entry's value; None if there is none."""
        value = ctypes.create_string_buffer(self.value_stride)
        return value.raw if libbpf().bpf_map_lookup_elem(self.fd, key, value) == 0 else None

    def _read_batch(self, delete: bool = False) -> tuple[bytes, bytes, int]:
        lib = libbpf()
        batch_op = lib.bpf_map_lookup_and_delete_batch if delete else lib.bpf_map_lookup_batch
        keys, values, total = [], [], 0
        # Buffers for the entries the last read found, and a few more, doubled while batches come
        # back full: a map read at every collect holds about as many as the time before, often few,
        # and buffers for the most a batch may take (256 KiB) would be mapped, zeroed and faulted
        # in anew at each read.
        most = max(1, min(_BATCH, _BATCH_BYTES // self.value_stride))
        batch = min(most, max(_BATCH_LEAST, self._last_count + self._last_count // 4))

        def buffers(entries: int) -> tuple:
            return ctypes.create_string_buffer(self.key_size * entries), ctypes.create_string_buffer(
                self.value_stride * entries)
        kbuf, vbuf = buffers(batch)
        token = ctypes.create_string_buffer(max(self.key_size, 8))
        token_next = ctypes.create_string_buffer(max(self.key_size, 8))
        first = True
        while True:
            count = ctypes.c_uint32(batch)
            ret = batch_op(self.fd, None if first else token, token_next, kbuf, vbuf, ctypes.byref(count), None)
            err = ctypes.get_errno() if ret < 0 else 0
            if err == errno.ENOSPC and batch < _BATCH:  # a hash bucket holds more than a batch: read it whole
                batch *= 2
                kbuf, vbuf = buffers(batch)
                continue
            if ret < 0 and err != errno.ENOENT:
                raise _BatchError(err, f"batch read of {self.path}: {os.strerror(err)}")
            n = count.value
            if n:  # only what the kernel wrote
                keys.append(ctypes.string_at(kbuf, n * self.key_size))
                values.append(ctypes.string_at(vbuf, n * self.value_stride))
                total += n
            if ret < 0:  # ENOENT: that was the last batch
                break
            ctypes.memmove(token, token_next, len(token))
            first = False
            if n == batch < most:
                batch = min(most, 2 * batch)
                kbuf, vbuf = buffers(batch)
        self._last_count = total
        return b"".join(keys), b"".join(values), total

    def _read_each(self) -> tuple[bytes, bytes, int]:
        """Entry by entry. When the key last read is deleted meanwhile, the kernel starts again
        from the first key: an entry is kept once (its latest value), and the walk ends after as
        many steps as the map can hold entries, twice, so churn can neither repeat nor prolong it."""
        lib = libbpf()
        entries: dict[bytes, bytes] = {}
        prev = None
        key = ctypes.create_string_buffer(self.key_size)
        value = ctypes.create_string_buffer(self.value_stride)
        for _ in range(2 * self.max_entries):
            if lib.bpf_map_get_next_key(self.fd, prev, key) != 0:
                break
            if lib.bpf_map_lookup_elem(self.fd, key, value) == 0:
                entries[key.raw] = value.raw
            prev = ctypes.create_string_buffer(key.raw, self.key_size)
        return b"".join(entries), b"".join(entries.values()), len(entries)

    def update(self, key: bytes, value: bytes) -> None:
        _check(libbpf().bpf_map_update_elem(self.fd, key, value, 0), f"update {self.path}")

    def delete(self, key: bytes) -> None:
        """Delete the entry if it is there."""
        libbpf().bpf_map_delete_elem(self.fd, key)

    def delete_unchanged(self, entries: list[tuple[bytes, bytes]]) -> list[bool]:
        """Delete entries that still hold the value read; one that changed since (its key now
        names a new socket) or is gone already stays as it is. Whether each was deleted."""
        lib = libbpf()
        current = ctypes.create_string_buffer(self.value_stride)
        return [lib.bpf_map_lookup_elem(self.fd, key, current) == 0 and current.raw == value
                and lib.bpf_map_delete_elem(self.fd, key) == 0 for key, value in entries]


def sum_percpu(values: bytes, fmt: str, ncpus: int) -> list[tuple]:
    """Fold per-CPU values into one tuple per entry by summing each field across CPUs."""
    size = struct.calcsize(fmt)
    stride = (size + 7) // 8 * 8
    rows = []
    for base in range(0, len(values), stride * ncpus):
        acc = None
        for cpu in range(ncpus):
            fields = struct.unpack_from(fmt, values, base + cpu * stride)
            acc = list(fields) if acc is None else [a + b for a, b in zip(acc, fields)]
        rows.append(tuple(acc))
    return rows
