"""The object store of a CANopen slave: object values described by an EDS, accessed as bytes.

Owns :class:`ObjectStore` — a dict-backed object dictionary loaded from an EDS with canopen's
``import_od`` (data type, access, default, limits), byte-level ``read_object`` / ``write_object``
raising :class:`bus.errors.SdoAbort` with CiA 301 abort codes, and per-object read/write hooks
through which the application behind the node (the drive firmware, the plant node) links
objects to its state.  The SDO server (:mod:`bus.cia301.sdo`) and the PDO service
(:mod:`bus.cia301.pdo`) reach the objects only through it.
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Callable
from pathlib import Path

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable, import_od
from canopen.objectdictionary import datatypes as dt

from bus.errors import AbortCode, SdoAbort

_STRUCTS: dict[int, struct.Struct] = {
    dt.BOOLEAN: struct.Struct("<?"),
    dt.INTEGER8: struct.Struct("<b"),
    dt.INTEGER16: struct.Struct("<h"),
    dt.INTEGER32: struct.Struct("<i"),
    dt.INTEGER64: struct.Struct("<q"),
    dt.UNSIGNED8: struct.Struct("<B"),
    dt.UNSIGNED16: struct.Struct("<H"),
    dt.UNSIGNED32: struct.Struct("<I"),
    dt.UNSIGNED64: struct.Struct("<Q"),
    dt.REAL32: struct.Struct("<f"),
    dt.REAL64: struct.Struct("<d"),
}

Value = int | float | bytes | str
Key = tuple[int, int]


@functools.lru_cache(maxsize=64)
def _described(eds_path: str, node_id: int, mtime_ns: int) -> ObjectDictionary:
    """The EDS parsed once per file version and node id (a drive's EDS takes ~15 ms to parse;
    the stores share it: nothing writes to a description, only to the stores' values)."""
    return import_od(eds_path, node_id)


def struct_of(var: ODVariable) -> struct.Struct | None:
    """The packing of a numeric ``var``; None for DOMAIN, strings and a missing data type."""
    return None if var.data_type is None else _STRUCTS.get(var.data_type)


class ObjectStore:
    """Object values of one node, described by an EDS (``canopen.objectdictionary.import_od``).

    Values are Python values (int, float, bytes for DOMAIN/OCTET_STRING, str for strings);
    :meth:`read_object` / :meth:`write_object` convert to and from little-endian bytes and
    enforce access type, exact size of numeric types and the EDS LowLimit/HighLimit.  A read
    hook replaces the stored value; a write hook sees the decoded value before it is stored
    and may refuse with :class:`SdoAbort`.

    :param eds_path: the EDS file.
    :param node_id: node id for ``$NODEID`` expressions.
    """

    def __init__(self, eds_path: str | Path, node_id: int) -> None:
        path = str(eds_path)
        self.od = _described(path, int(node_id), os.stat(path).st_mtime_ns)
        self.vars: dict[Key, ODVariable] = {}
        for obj in self.od.values():
            if obj.index < 0x1000:
                continue  # data type definitions, not objects
            if isinstance(obj, ODVariable):
                self.vars[(obj.index, 0)] = obj
            elif isinstance(obj, (ODRecord, ODArray)):
                for var in obj.values():
                    self.vars[(obj.index, var.subindex)] = var
        self._indices = {k[0] for k in self.vars}
        self.values: dict[Key, Value] = {}
        self.read_hooks: dict[Key, Callable[[], Value]] = {}
        self.write_hooks: dict[Key, Callable[[Value], None]] = {}
        self.reset(0x0000, 0xFFFF)

    @staticmethod
    def default(var: ODVariable) -> Value:
        """The EDS default of ``var`` (0 / b"" / "" if none)."""
        if var.default is not None:
            return var.default
        if var.data_type in (dt.DOMAIN, dt.OCTET_STRING):
            return b""
        if var.data_type in (dt.VISIBLE_STRING, dt.UNICODE_STRING):
            return ""
        return 0

    def reset(self, first: int, last: int) -> None:
        """Set every object with index in [first, last] to its EDS default."""
        for key, var in self.vars.items():
            if first <= key[0] <= last:
                self.values[key] = self.default(var)

    def lookup(self, index: int, sub: int) -> ODVariable:
        """:raises SdoAbort: 0x06020000 no object, 0x06090011 no sub-index."""
        var = self.vars.get((index, sub))
        if var is None:
            if index not in self._indices:
                raise SdoAbort(AbortCode.NO_OBJECT, f"no object 0x{index:04X}")
            raise SdoAbort(AbortCode.NO_SUBINDEX, f"no sub-index {sub} in 0x{index:04X}")
        return var

    def get(self, index: int, sub: int = 0) -> Value:
        """The current value (through the read hook, if any), no access check."""
        hook = self.read_hooks.get((index, sub))
        return hook() if hook is not None else self.values[(index, sub)]

    def get_bytes(self, index: int, sub: int = 0) -> bytes:
        """:meth:`get` of a DOMAIN / OCTET_STRING object.

        :raises TypeError: the object holds a number or a string.
        """
        value = self.get(index, sub)
        if not isinstance(value, bytes):
            raise TypeError(f"0x{index:04X}:{sub} holds {type(value).__name__}, not bytes")
        return value

    def read_object(self, index: int, sub: int) -> bytes:
        """:raises SdoAbort: unknown object/sub-index, write-only."""
        var = self.lookup(index, sub)
        if var.access_type == "wo":
            raise SdoAbort(AbortCode.WRITE_ONLY, f"0x{index:04X}:{sub} is write-only")
        return self.encode(var, self.get(index, sub))

    def write_object(self, index: int, sub: int, data: bytes) -> None:
        """:raises SdoAbort: unknown, read-only, wrong length, out of range, refused by hook."""
        var = self.lookup(index, sub)
        if var.access_type in ("ro", "const"):
            raise SdoAbort(AbortCode.READ_ONLY, f"0x{index:04X}:{sub} is read-only")
        value = self.decode(var, bytes(data))
        key = (index, sub)
        hook = self.write_hooks.get(key)
        if hook is not None:
            hook(value)
        self.values[key] = value

    def writer(self, index: int, sub: int) -> Callable[[bytes], None]:
        """:meth:`write_object` of ``(index, sub)`` with the object looked up now: the same checks,
        hook and store on every call (for a writer called often, e.g. an RPDO's mapped objects;
        the hooks must be installed before it is made).

        :raises SdoAbort: unknown object/sub-index (now); when called, as :meth:`write_object`.
        """
        var = self.lookup(index, sub)
        if var.access_type in ("ro", "const"):
            return functools.partial(self.write_object, index, sub)  # refused at every call
        key = (index, sub)
        hook = self.write_hooks.get(key)
        values = self.values
        decode = self.decode

        def write(data: bytes) -> None:
            value = decode(var, bytes(data))
            if hook is not None:
                hook(value)
            values[key] = value

        return write

    @staticmethod
    def encode(var: ODVariable, value: Value) -> bytes:
        s = struct_of(var)
        if s is not None:
            return s.pack(value)
        if isinstance(value, str):
            return value.encode("ascii")
        if not isinstance(value, bytes):
            raise TypeError(f"0x{var.index:04X}:{var.subindex} (DOMAIN/string) holds {type(value).__name__}, not bytes")
        return bytes(value)

    @staticmethod
    def decode(var: ODVariable, data: bytes) -> Value:
        """:raises SdoAbort: 0x06070010 length, 0x06090031/32 limits, 0x06090030 non-ASCII."""
        s = struct_of(var)
        if s is None:
            if var.data_type in (dt.VISIBLE_STRING, dt.UNICODE_STRING):
                try:
                    return data.decode("ascii")
                except UnicodeDecodeError:
                    raise SdoAbort(AbortCode.VALUE_RANGE, "string is not ASCII") from None
            return data
        if len(data) != s.size:
            raise SdoAbort(AbortCode.LENGTH_MISMATCH, f"0x{var.index:04X}:{var.subindex} needs {s.size} bytes, got {len(data)}")
        (value,) = s.unpack(data)
        if var.max is not None and value > var.max:
            raise SdoAbort(AbortCode.VALUE_TOO_HIGH, f"{value} > {var.max}")
        if var.min is not None and value < var.min:
            raise SdoAbort(AbortCode.VALUE_TOO_LOW, f"{value} < {var.min}")
        return value
