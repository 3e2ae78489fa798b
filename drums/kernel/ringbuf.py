"""A BPF ring buffer (BPF_MAP_TYPE_RINGBUF, Linux >= 5.8) read from its pin, without bcc.

The kernel maps the consumer position read-write at offset 0, then the producer position and
the data, twice in a row so that a record that wraps reads as one piece (kernel/bpf/ringbuf.c).
The map's fd is readable with epoll while records wait: a reader sleeps until there is work.
"""
from __future__ import annotations

import mmap
import os
import select
import struct

from drums.errors import ProbeError
from drums.kernel import bpffs

_BUSY = 1 << 31  # the producer has reserved the record and not committed it yet
_DISCARD = 1 << 30  # the producer gave the record up
_HEADER = 8  # u32 length and flags, u32 page offset
_U64 = struct.Struct("<Q")


class RingBuffer:
    def __init__(self, path: str):
        self.fd = bpffs.obj_get(path)
        try:
            size = bpffs.PinnedMap.from_fd(self.fd, path)
            self.size = size.max_entries
            size.close()
            page = mmap.PAGESIZE
            self._consumer = mmap.mmap(self.fd, page, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
            self._data = mmap.mmap(self.fd, page + 2 * self.size, mmap.MAP_SHARED, mmap.PROT_READ, offset=page)
        except (OSError, ProbeError) as e:
            os.close(self.fd)
            raise ProbeError(f"ring buffer {path}: {e}") from None
        self._page = page
        self._epoll = select.epoll()
        self._epoll.register(self.fd, select.EPOLLIN)

    def wait(self, timeout: float) -> None:
        """Sleep until a record is there or `timeout` seconds passed."""
        self._epoll.poll(timeout)

    def drain(self) -> list[bytes]:
        """Every committed record, oldest first; their space goes back to the producers."""
        out = []
        consumer = _U64.unpack_from(self._consumer, 0)[0]
        producer = _U64.unpack_from(self._data, 0)[0]
        mask = self.size - 1
        while consumer < producer:
            at = self._page + (consumer & mask)
            header = struct.unpack_from("<I", self._data, at)[0]
            if header & _BUSY:
                break
            length = header & ~(_BUSY | _DISCARD)
            if not header & _DISCARD:
                out.append(self._data[at + _HEADER:at + _HEADER + length])
            consumer += (length + _HEADER + 7) & ~7
            _U64.pack_into(self._consumer, 0, consumer)
        return out

    def close(self) -> None:
        if self.fd >= 0:
            self._epoll.close()
            self._consumer.close()
            self._data.close()
            os.close(self.fd)
            self.fd = -1
