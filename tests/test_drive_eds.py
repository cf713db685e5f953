"""bus/drive.eds is true: every entry is checked against the live object dictionary of a freshly
booted drive (NMT PRE-OPERATIONAL).

* every entry is present and reads its EDS default (a write-only entry answers 0x06010001);
* the access type: ``ro``/``const`` writes are refused with 0x06010002, an ``rw`` entry takes its
  own value back (the few that need more -- a signature, a table length first, the CiA 301 PDO
  mapping procedure -- answer with the abort code named in :data:`WRITE_BACK`);
* the limits: one below LowLimit is refused with 0x06090032, one above HighLimit with 0x06090031,
  the limits themselves are accepted (except where a rule of the object refuses them:
  :data:`LIMIT_REFUSED`);
* PDOMapping: a mappable entry can be mapped (an RPDO if writable, a TPDO if readable), a
  non-mappable one is refused with 0x06040041;
* the header: the object lists name exactly the objects described, the mapping granularity is 8
  (whole objects of 8, 16, 32 bits), 4 PDOs each way, vendor, product and revision as 0x1018;
* 0x6502 says exactly the modes 0x6060 accepts.
"""

from __future__ import annotations

import configparser
import struct

import pytest
from canopen.objectdictionary import ODVariable, import_od
from canopen.objectdictionary import datatypes as dt

from bus.cia301.object_store import ObjectStore
from bus.errors import AbortCode, SdoAbort
from bus.objects import DRIVE_EDS_PATH, PRODUCT_CODE, REVISION_NUMBER, SUPPORTED_DRIVE_MODES_VALUE, VENDOR_ID, Obj
from firmware_model.drive import Drive

NODE = 3
OD = import_od(str(DRIVE_EDS_PATH), NODE)
ENTRIES: list[ODVariable] = sorted(
    (var for obj in OD.values() if obj.index >= 0x1000 for var in (obj.values() if hasattr(obj, "values") else [obj])),
    key=lambda v: (v.index, v.subindex),
)
_RANGES = {
    dt.INTEGER8: (-(1 << 7), (1 << 7) - 1),
    dt.INTEGER16: (-(1 << 15), (1 << 15) - 1),
    dt.INTEGER32: (-(1 << 31), (1 << 31) - 1),
    dt.UNSIGNED8: (0, 0xFF),
    dt.UNSIGNED16: (0, 0xFFFF),
    dt.UNSIGNED32: (0, 0xFFFF_FFFF),
}
_MAPPINGS = {0x1600 + k for k in range(4)} | {0x1A00 + k for k in range(4)}
#: rw entries whose own value written back is refused, and why (the abort code)
WRITE_BACK: dict[tuple[int, int], int] = {
    **{(Obj.STORE_PARAMETERS, s): AbortCode.CANNOT_STORE for s in (1, 2, 3)},  # needs the signature "save"
    **{(Obj.RESTORE_DEFAULTS, s): AbortCode.CANNOT_STORE for s in (1, 2, 3)},  # needs the signature "load"
    **{(index, 0): AbortCode.DEVICE_STATE for index in (Obj.REF_POSITION_TABLE, Obj.REF_VELOCITY_TABLE, Obj.FEEDFORWARD_TABLE)},
    **{(0x1600, s): AbortCode.UNSUPPORTED_ACCESS for s in range(1, 9)},  # RPDO1 maps 1 object: entries need sub 0 = 0
    **{(0x1A00, s): AbortCode.UNSUPPORTED_ACCESS for s in range(1, 9)},  # TPDO1 likewise
}
#: limit values an object's own rule refuses although the EDS limits allow them
LIMIT_REFUSED: dict[tuple[int, int, int], int] = {
    (Obj.INTERPOLATION_PERIOD, 1, 255): AbortCode.VALUE_RANGE,  # 255 ms: beyond 0x2300's 100 ms
    (Obj.INTERPOLATION_PERIOD, 2, -6): AbortCode.VALUE_RANGE,  # 1 µs: below 0x2300's 100 µs
    (Obj.TRIAL, 1, 1): AbortCode.DEVICE_STATE,  # arming needs the tables
    **{(index, 0, 8): AbortCode.NO_OBJECT for index in _MAPPINGS},  # 8 entries, all empty
}


def pack(var: ODVariable, value: int) -> bytes:
    return ObjectStore.encode(var, value)


def name(var: ODVariable) -> str:
    return f"0x{var.index:04X}:{var.subindex} {var.name}"


def code_of(fn, *args) -> int | None:  # type: ignore[no-untyped-def]
    try:
        fn(*args)
    except SdoAbort as err:
        return err.code
    return None


def test_every_entry_is_present_and_reads_its_default_at_boot() -> None:
    d = Drive(NODE)
    for var in ENTRIES:
        if var.access_type == "wo":
            assert code_of(d.read_object, var.index, var.subindex) == AbortCode.WRITE_ONLY, name(var)
            continue
        raw = d.read_object(var.index, var.subindex)
        if var.default is None:
            assert var.data_type == dt.DOMAIN and raw == b"", name(var)  # tables and recorder: empty
            continue
        value = raw.decode("ascii") if var.data_type == dt.VISIBLE_STRING else var.decode_raw(raw)
        assert value == var.default, name(var)


@pytest.mark.parametrize("var", [v for v in ENTRIES if v.access_type in ("ro", "const")], ids=name)
def test_read_only_entries_refuse_writes(var: ODVariable) -> None:
    d = Drive(NODE)
    data = d.read_object(var.index, var.subindex) or b"\x00"
    assert code_of(d.write_object, var.index, var.subindex, data) == AbortCode.READ_ONLY


@pytest.mark.parametrize("var", [v for v in ENTRIES if v.access_type in ("rw", "wo")], ids=name)
def test_writable_entries_take_their_value_back(var: ODVariable) -> None:
    d = Drive(NODE)
    data = pack(var, 0) if var.access_type == "wo" else d.read_object(var.index, var.subindex)
    assert code_of(d.write_object, var.index, var.subindex, data) == WRITE_BACK.get((var.index, var.subindex)), name(var)


LIMITED = [v for v in ENTRIES if v.min is not None or v.max is not None]


@pytest.mark.parametrize("var", LIMITED, ids=name)
def test_writes_outside_the_limits_are_refused(var: ODVariable) -> None:
    lo, hi = _RANGES[var.data_type]
    key = (var.index, var.subindex)
    if var.min is not None:
        if var.min > lo:
            assert code_of(Drive(NODE).write_object, *key, pack(var, var.min - 1)) == AbortCode.VALUE_TOO_LOW, name(var)
        assert code_of(Drive(NODE).write_object, *key, pack(var, var.min)) == LIMIT_REFUSED.get((*key, var.min)), name(var)
    if var.max is not None:
        if var.max < hi:
            assert code_of(Drive(NODE).write_object, *key, pack(var, var.max + 1)) == AbortCode.VALUE_TOO_HIGH, name(var)
        assert code_of(Drive(NODE).write_object, *key, pack(var, var.max)) == LIMIT_REFUSED.get((*key, var.max)), name(var)


def test_pdo_mapping_flags_are_what_the_drive_maps() -> None:
    d = Drive(NODE)
    for rx_map, comm in ((0x1601, 0x1401), (0x1A01, 0x1801)):
        assert d.read_object(comm, 1)[3] & 0x80  # not valid: its mapping may change
        d.write_object(rx_map, 0, b"\x00")
    for var in ENTRIES:
        entry = struct.pack("<I", var.index << 16 | var.subindex << 8 | 8 * max(len(var) // 8, 1))
        readable, writable = var.access_type != "wo", var.access_type in ("rw", "wo")
        for mapping, allowed in ((0x1601, writable), (0x1A01, readable)):
            got = code_of(d.write_object, mapping, 1, entry)
            expected = None if var.pdo_mappable and allowed and var.data_type in _RANGES else AbortCode.NOT_MAPPABLE
            assert got == expected, (name(var), hex(mapping))


def test_header_says_what_the_drive_is() -> None:
    eds = configparser.ConfigParser()
    eds.optionxform = str  # type: ignore[assignment,method-assign]
    eds.read(DRIVE_EDS_PATH)
    info = eds["DeviceInfo"]
    assert int(info["Granularity"]) == 8  # whole objects of 8, 16, 32 bits map: e.g. the I8 0x6061
    assert int(info["NrOfRXPDO"]) == len([i for i in OD if 0x1400 <= i <= 0x15FF]) == 4
    assert int(info["NrOfTXPDO"]) == len([i for i in OD if 0x1800 <= i <= 0x19FF]) == 4
    assert int(info["VendorNumber"], 16) == OD[0x1018][1].default == VENDOR_ID
    assert int(info["ProductNumber"], 16) == OD[0x1018][2].default == PRODUCT_CODE
    assert int(info["RevisionNumber"], 16) == OD[0x1018][3].default == REVISION_NUMBER
    listed: dict[str, set[int]] = {}
    for section in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        n = int(eds[section]["SupportedObjects"])
        listed[section] = {int(eds[section][str(k)], 16) for k in range(1, n + 1)}
        assert len(listed[section]) == n
    described = {i for i in OD if i >= 0x1000}
    assert set().union(*listed.values()) == described
    assert listed["MandatoryObjects"] == {0x1000, 0x1001, 0x1018}
    assert listed["ManufacturerObjects"] == {i for i in described if 0x2000 <= i <= 0x5FFF}


def test_supported_drive_modes_are_exactly_the_modes_0x6060_takes() -> None:
    d = Drive(NODE)
    taken = set()
    for code in range(-128, 128):
        if code_of(d.write_object, Obj.MODES_OF_OPERATION, 0, struct.pack("<b", code)) is None:
            taken.add(code)
    bits = {-1: 16, 1: 0, 6: 5, 8: 7, 9: 8, 10: 9}
    assert taken == set(bits)
    assert OD[0x6502].default == SUPPORTED_DRIVE_MODES_VALUE == sum(1 << b for b in bits.values())
