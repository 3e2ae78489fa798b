"""drums.kernel.elf: the file offsets where uprobes go, against the dynamic linker's own addresses
in this process, and against ELF files of each class and byte order built here (which readelf,
from binutils, reads back as we meant them)."""
from __future__ import annotations

import ctypes
import ctypes.util
import struct
import subprocess

import pytest

from drums.errors import ProbeError
from drums.kernel.elf import symbol_offsets

SHT_DYNSYM, SHT_STRTAB, PT_LOAD = 11, 3, 1


def _mapped_path(name: str) -> str:
    with open("/proc/self/maps") as f:
        return next(line.split()[5] for line in f if len(line.split()) > 5 and name in line.split()[5].rsplit("/", 1)[-1])


def _file_offset(address: int, path: str) -> int:
    """Where in `path` the byte this process has mapped at `address` comes from."""
    with open("/proc/self/maps") as f:
        for line in f:
            fields = line.split()
            if len(fields) > 5 and fields[5] == path:
                start, end = (int(x, 16) for x in fields[0].split("-"))
                if start <= address < end:
                    return address - start + int(fields[2], 16)
    raise AssertionError(f"{address:#x} is not in {path}")


def test_offsets_are_where_the_dynamic_linker_mapped_the_functions():
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    path = _mapped_path("libc.so")
    names = ["getpid", "malloc", "qsort", "fork"]  # no IFUNCs: dlsym gives their own address
    truth = {n: _file_offset(ctypes.cast(getattr(libc, n), ctypes.c_void_p).value, path) for n in names}
    assert symbol_offsets(path, names + ["no_such_function"]) == truth


def _elf(cls: int, order: str) -> tuple[bytes, dict[str, int]]:
    """A shared library of the class (1: 32-bit, 2: 64-bit) and byte order ("<", ">") with two
    loadable segments and three dynamic symbols: rcl_publish and rcl_take defined (rcl_take's name
    the tail of another string), malloc undefined; and the file offsets of the defined ones."""
    o = order
    ehdr, phdr, shdr, sym = ((52, 32, 40, 16) if cls == 1 else (64, 56, 64, 24))
    dynstr = b"\0rcl_publish\0xrcl_take\0malloc\0"
    names = {"rcl_publish": 1, "rcl_take": 14, "malloc": 23}
    segments = [(0, 0x10000, 0x1000), (0x1000, 0x21000, 0x1000)]  # (offset, vaddr, size)
    values = {"rcl_publish": 0x10100, "rcl_take": 0x21010, "malloc": 0}
    phoff = ehdr
    symoff = 0x200
    symbols = b"\0" * sym
    for name in ("rcl_publish", "rcl_take", "malloc"):
        shndx = 0 if name == "malloc" else 1
        if cls == 1:
            symbols += struct.pack(o + "IIIBBH", names[name], values[name], 16, 0x12, 0, shndx)
        else:
            symbols += struct.pack(o + "IBBHQQ", names[name], 0x12, 0, shndx, values[name], 16)
    stroff = symoff + len(symbols)
    shoff = 0x400
    body = bytearray(0x2000)
    ident = b"\x7fELF" + bytes([cls, 1 if o == "<" else 2, 1]) + b"\0" * 9
    addr = "I" if cls == 1 else "Q"
    body[:ehdr] = ident + struct.pack(o + f"HHI{addr}{addr}{addr}IHHHHHH", 3, 0x3E if cls == 2 else 3, 1, 0, phoff,
                                      shoff, 0, ehdr, phdr, len(segments), shdr, 4, 3)
    for i, (off, vaddr, size) in enumerate(segments):
        fields = ((PT_LOAD, off, vaddr, vaddr, size, size, 5, 0x1000) if cls == 1 else
                  (PT_LOAD, 5, off, vaddr, vaddr, size, size, 0x1000))
        body[phoff + i * phdr: phoff + (i + 1) * phdr] = struct.pack(o + ("8I" if cls == 1 else "IIQQQQQQ"), *fields)
    body[symoff:symoff + len(symbols)] = symbols
    body[stroff:stroff + len(dynstr)] = dynstr
    # The sections' names (readelf 2.44 prints a symbol's section by name where it can)
    shstrtab, shstroff = b"\0.dynsym\0.dynstr\0.shstrtab\0", stroff + len(dynstr)
    body[shstroff:shstroff + len(shstrtab)] = shstrtab
    sections = [(0,) * 10, (1, SHT_DYNSYM, 2, 0, symoff, len(symbols), 2, 1, 8, sym),
                (9, SHT_STRTAB, 2, 0, stroff, len(dynstr), 0, 0, 1, 0),
                (17, SHT_STRTAB, 0, 0, shstroff, len(shstrtab), 0, 0, 1, 0)]
    for i, fields in enumerate(sections):
        body[shoff + i * shdr: shoff + (i + 1) * shdr] = struct.pack(o + ("10I" if cls == 1 else "IIQQQQIIQQ"), *fields)
    return bytes(body), {"rcl_publish": 0x100, "rcl_take": 0x1010}


@pytest.mark.parametrize("cls", [1, 2])
@pytest.mark.parametrize("order", ["<", ">"])
def test_both_classes_and_byte_orders(tmp_path, cls, order):
    data, offsets = _elf(cls, order)
    path = tmp_path / "librcl.so"
    path.write_bytes(data)
    listed = subprocess.run(["readelf", "-W", "--dyn-syms", str(path)], capture_output=True, text=True, check=True).stdout
    assert [(line.split()[1].lstrip("0"), line.split()[6], line.split()[7]) for line in listed.splitlines()
            if line.split()[-1:] in (["rcl_publish"], ["rcl_take"], ["malloc"])] == \
        [("10100", "1", "rcl_publish"), ("21010", "1", "rcl_take"), ("", "UND", "malloc")]
    assert symbol_offsets(str(path), ["rcl_publish", "rcl_take", "malloc", "rcl"]) == offsets


@pytest.mark.parametrize("data", [b"", b"#!/bin/sh\n", b"\x7fELF\x02\x01\x01" + b"\0" * 20])
def test_a_file_that_is_not_a_whole_elf_file_is_one_probe_error(tmp_path, data):
    path = tmp_path / "lib.so"
    path.write_bytes(data)
    with pytest.raises(ProbeError, match=f"^{path}: cannot read its symbols"):
        symbol_offsets(str(path), ["rcl_publish"])
    with pytest.raises(ProbeError, match="cannot read its symbols"):
        symbol_offsets(str(tmp_path / "missing.so"), ["rcl_publish"])
