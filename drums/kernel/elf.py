"""File offsets of the dynamic symbols of an ELF shared library, where uprobes go (librcl's
functions, the dynamic linker's _dl_debug_state).

The ELF header, the section headers, .dynsym with its string table, and the loadable segments:
all the agent needs, read from a memory map. A general ELF library (pyelftools) cost the agent
with the ROS 2 graph 1.1 MB of memory (USS, idle) for as long as it ran, for a look at a file now
and then.
"""
from __future__ import annotations

import mmap
import struct

from drums.errors import ProbeError

_SHT_DYNSYM = 11
_PT_LOAD = 1
_SHN_UNDEF = 0
# Per ELF class (1: 32-bit, 2: 64-bit): the header after e_ident (e_type .. e_shstrndx), a section
# header, a program header, a symbol; and where in each tuple the fields used here are.
_LAYOUT = {
    1: ("HHIIIIIHHHHHH", "IIIIIIIIII", "IIIIIIII", "IIIBBH"),
    2: ("HHIQQQIHHHHHH", "IIQQQQIIQQ", "IIQQQQQQ", "IBBHQQ"),
}
_PHDR = {1: {"type": 0, "offset": 1, "vaddr": 2, "memsz": 5}, 2: {"type": 0, "offset": 2, "vaddr": 3, "memsz": 6}}
_SYM = {1: {"name": 0, "value": 1, "shndx": 5}, 2: {"name": 0, "value": 4, "shndx": 3}}


def symbol_offsets(path: str, names) -> dict[str, int]:
    """File offsets of those of the named dynamic symbols the library defines."""
    try:
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, prot=mmap.PROT_READ) as data:
            return _offsets(data, set(names))
    except (OSError, ValueError, struct.error, IndexError) as e:
        raise ProbeError(f"{path}: cannot read its symbols ({e or 'not ELF'})") from None


def _offsets(data, names: set[str]) -> dict[str, int]:
    if data[:4] != b"\x7fELF" or data[4] not in _LAYOUT or data[5] not in (1, 2):
        raise ValueError("not an ELF file")
    cls, order = data[4], "<" if data[5] == 1 else ">"
    header, section, program, symbol = (struct.Struct(order + f) for f in _LAYOUT[cls])
    fields = header.unpack_from(data, 16)
    phoff, shoff, phnum, shnum = fields[4], fields[5], fields[9], fields[11]
    sections = [section.unpack_from(data, shoff + i * section.size) for i in range(shnum)]
    dynsym = next((s for s in sections if s[1] == _SHT_DYNSYM), None)
    if dynsym is None:
        return {}
    strings = sections[dynsym[6]]  # sh_link: its string table
    strtab = data[strings[4]:strings[4] + strings[5]]  # sh_offset, sh_size
    table = data[dynsym[4]:dynsym[4] + dynsym[5]]
    # Where each wanted name lies in the string table (a symbol's name may be the tail of another's).
    wanted: dict[int, str] = {}
    for name in names:
        needle, at = name.encode() + b"\0", -1
        while (at := strtab.find(needle, at + 1)) >= 0:
            wanted[at] = name
    ph, sy = _PHDR[cls], _SYM[cls]
    loads = [(p[ph["vaddr"]], p[ph["memsz"]], p[ph["offset"]])
             for p in (program.unpack_from(data, phoff + i * program.size) for i in range(phnum))
             if p[ph["type"]] == _PT_LOAD]
    out = {}
    for sym in symbol.iter_unpack(table[:len(table) - len(table) % symbol.size]):
        name = wanted.get(sym[sy["name"]])
        if name is None or sym[sy["shndx"]] == _SHN_UNDEF:
            continue
        value = sym[sy["value"]]
        for vaddr, memsz, offset in loads:
            if vaddr <= value < vaddr + memsz:
                out[name] = value - vaddr + offset
    return out
