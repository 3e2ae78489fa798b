"""Struct layouts and tracepoint signatures read from the running kernel's BTF.

Headers installed for bcc may belong to another kernel version, so every kernel struct offset a
probe uses is looked up here and handed to the BPF C code as a -D flag (see STYLE.md, practice 6).
Only the parts of the BTF format that this needs are decoded: structs, unions, typedefs,
modifiers, pointers and function prototypes.
"""
from __future__ import annotations

import array
import struct
from dataclasses import dataclass

from drums.errors import KernelError

VMLINUX_BTF = "/sys/kernel/btf/vmlinux"
_MAGIC = 0xEB9F

# BTF kinds (include/uapi/linux/btf.h) and the size of the data that follows each type record.
_INT, _PTR, _ARRAY, _STRUCT, _UNION, _ENUM, _FWD, _TYPEDEF = 1, 2, 3, 4, 5, 6, 7, 8
_VOLATILE, _CONST, _RESTRICT, _FUNC, _FUNC_PROTO, _VAR, _DATASEC = 9, 10, 11, 12, 13, 14, 15
_FLOAT, _DECL_TAG, _TYPE_TAG, _ENUM64 = 16, 17, 18, 19
_MODIFIERS = (_TYPEDEF, _VOLATILE, _CONST, _RESTRICT, _TYPE_TAG)
_FIXED_EXTRA = {_INT: 4, _ARRAY: 12, _VAR: 4, _DECL_TAG: 4}
_PER_MEMBER_EXTRA = {_STRUCT: 12, _UNION: 12, _ENUM: 8, _FUNC_PROTO: 8, _DATASEC: 12, _ENUM64: 12}


@dataclass(frozen=True)
class Field:
    """Where a (possibly nested) struct member lives: byte offset from the struct start and size."""

    offset: int
    size: int


def _read(path: str) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise KernelError(f"cannot read kernel BTF at {path}: {e.strerror}") from None


def _sections(data: bytes) -> tuple[int, int, bytes]:
    """Where a BTF blob's type records start and end, and its string section."""
    if len(data) < 24:
        raise KernelError("BTF blob is truncated")
    magic, _version, _flags, hdr_len, type_off, type_len, str_off, str_len = struct.unpack_from("<HBBIIIII", data, 0)
    if magic != _MAGIC:
        raise KernelError("not a BTF blob (bad magic)")
    return hdr_len + type_off, hdr_len + type_off + type_len, data[hdr_len + str_off : hdr_len + str_off + str_len]


def names(path: str = VMLINUX_BTF) -> bytes:
    """The string section of a BTF file: every type, member and function name, each ended by a
    NUL. A name's presence answers some questions (whether the kernel has a struct at all) without
    indexing 130,000 types as Btf does (0.15 s)."""
    return _sections(_read(path))[2]


class Btf:
    """A parsed BTF blob; lookups are by C names as they appear in the kernel source."""

    def __init__(self, data: bytes):
        self._data = data
        types_start, types_end, self._strings = _sections(data)
        # type id -> offset of its record (id 0 is void): 130,000 of them, in one block rather than
        # as as many Python ints (4 MB, which left the heap fragmented once the BTF was dropped)
        self._records = array.array("I", [0])
        self._by_name: dict[str, list[int]] = {}
        self._index(types_start, types_end)

    @classmethod
    def load(cls, path: str = VMLINUX_BTF) -> "Btf":
        return cls(_read(path))

    def _index(self, pos: int, end: int) -> None:
        unpack = struct.unpack_from
        data = self._data
        while pos < end:
            name_off, info = unpack("<II", data, pos)
            kind = (info >> 24) & 0x1F
            vlen = info & 0xFFFF
            type_id = len(self._records)
            self._records.append(pos)
            if name_off and kind in (_STRUCT, _UNION, _TYPEDEF):
                self._by_name.setdefault(self._name(name_off), []).append(type_id)
            pos += 12 + _FIXED_EXTRA.get(kind, 0) + vlen * _PER_MEMBER_EXTRA.get(kind, 0)

    def _name(self, off: int) -> str:
        end = self._strings.index(b"\0", off)
        return self._strings[off:end].decode()

    def _header(self, type_id: int) -> tuple[int, int, int, int, int]:
        """(name_off, kind, vlen, kind_flag, size_or_type) of a type."""
        pos = self._records[type_id]
        name_off, info, size_or_type = struct.unpack_from("<III", self._data, pos)
        return name_off, (info >> 24) & 0x1F, info & 0xFFFF, info >> 31, size_or_type

    def _resolve(self, type_id: int) -> int:
        """Follow typedefs and qualifiers to the underlying type."""
        while type_id:
            _, kind, _, _, target = self._header(type_id)
            if kind not in _MODIFIERS:
                return type_id
            type_id = target
        return 0

    def _size(self, type_id: int) -> int:
        type_id = self._resolve(type_id)
        _, kind, _, _, size = self._header(type_id)
        if kind == _PTR:
            return 8
        if kind == _ARRAY:
            elem, _index_type, nelems = struct.unpack_from("<III", self._data, self._records[type_id] + 12)
            return self._size(elem) * nelems
        return size

    def _members(self, type_id: int):
        """Yield (name, type id, bit offset, bitfield size) of a struct or union."""
        _, _, vlen, kind_flag, _ = self._header(type_id)
        pos = self._records[type_id] + 12
        for i in range(vlen):
            name_off, mtype, offset = struct.unpack_from("<III", self._data, pos + 12 * i)
            if kind_flag:
                yield self._name(name_off), mtype, offset & 0xFFFFFF, offset >> 24
            else:
                yield self._name(name_off), mtype, offset, 0

    def _find_member(self, type_id: int, name: str) -> tuple[int, int, int] | None:
        """(bit offset, type id, bitfield size) of a member, looking inside anonymous members."""
        for mname, mtype, bit_off, bits in self._members(type_id):
            if mname == name:
                return bit_off, mtype, bits
            if not mname:
                inner = self._resolve(mtype)
                if self._header(inner)[1] in (_STRUCT, _UNION):
                    found = self._find_member(inner, name)
                    if found:
                        return bit_off + found[0], found[1], found[2]
        return None

    def _struct(self, name: str) -> int:
        for type_id in self._by_name.get(name, ()):
            if self._header(type_id)[1] in (_STRUCT, _UNION):
                return type_id
        raise KernelError(f"kernel BTF has no struct {name}")

    def field(self, struct_name: str, path: str) -> Field:
        """Offset and size of `path` (dotted, e.g. '__sk_common.skc_family') in `struct_name`."""
        type_id = self._struct(struct_name)
        bit_total = 0
        mtype = type_id
        for part in path.split("."):
            found = self._find_member(self._resolve(mtype), part)
            if found is None:
                raise KernelError(f"kernel struct {struct_name} has no member {path}")
            bit_off, mtype, bits = found
            if bits or bit_off % 8:
                raise KernelError(f"{struct_name}.{path} is a bitfield; no byte offset")
            bit_total += bit_off
        return Field(bit_total // 8, self._size(mtype))

    def has_field(self, struct_name: str, path: str) -> bool:
        try:
            self.field(struct_name, path)
        except KernelError:
            return False
        return True

    def has_function(self, name: str) -> bool:
        """Whether the kernel has a function of that name (one a trampoline or kprobe can take).
        Functions are not indexed (70,000 names, asked for twice): their records are searched for
        the name's one string (BTF strings are deduplicated) and the kind, with any linkage."""
        at = self._strings.find(b"\0" + name.encode() + b"\0")
        return at >= 0 and any(struct.pack("<II", at + 1, _FUNC << 24 | linkage) in self._data for linkage in (0, 1, 2))

    def tracepoint_args(self, event: str) -> list[str] | None:
        """Names of the raw tracepoint's argument types, or None if the kernel has no such event.

        Every tracepoint has a `btf_trace_<event>` typedef: a pointer to a function whose first
        parameter is the tracepoint's private data and the rest are the TP_PROTO arguments.
        """
        for type_id in self._by_name.get(f"btf_trace_{event}", ()):
            ptr = self._resolve(type_id)
            _, kind, _, _, proto = self._header(ptr)
            if kind != _PTR:
                continue
            _, kind, vlen, _, _ = self._header(proto)
            if kind != _FUNC_PROTO:
                continue
            pos = self._records[proto] + 12
            params = [struct.unpack_from("<II", self._data, pos + 8 * i)[1] for i in range(vlen)]
            return [self._type_name(p) for p in params[1:]]
        return None

    def _type_name(self, type_id: int) -> str:
        name_off, kind, _, _, target = self._header(type_id)
        if kind == _PTR:
            return self._type_name(target) + " *"
        if kind in (_CONST, _VOLATILE, _RESTRICT, _TYPE_TAG):
            return self._type_name(target)
        prefix = {_STRUCT: "struct ", _UNION: "union ", _ENUM: "enum ", _ENUM64: "enum "}.get(kind, "")
        return prefix + (self._name(name_off) if name_off else "void")
