"""The types of lca_hil's object table: a variable's entry, data type, access, scaling.

`ObjectEntry` is one variable of the object dictionary with its CiA 301 data type, EDS access,
PDO mapping, SI scaling and overflow rule; `lca_sim.cia402.objects` declares the table with
them (and re-exports them).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

from lca_sim.errors import InvalidValueError, LcaHilError

MANUFACTURER_AREA = range(0x2000, 0x6000)  # CiA 301: manufacturer-specific profile area


class UnknownObjectError(LcaHilError, KeyError):
    """An index / sub-index pair that is not in lca_hil's object table."""

    def __init__(self, index: int, subindex: int) -> None:
        self.index = index
        self.subindex = subindex
        super().__init__(
            f"object 0x{index:04X} sub {subindex} is not in lca_hil's object table "
            "(lca_sim.cia402.objects.OBJECTS)"
        )

    def __str__(self) -> str:
        return str(self.args[0])


class DataType(enum.IntEnum):
    """CiA 301 basic data types, by their index in the data type area (0x0002-0x0007)."""

    INTEGER8 = 0x0002
    INTEGER16 = 0x0003
    INTEGER32 = 0x0004
    UNSIGNED8 = 0x0005
    UNSIGNED16 = 0x0006
    UNSIGNED32 = 0x0007

    @property
    def bits(self) -> int:
        """Length on the bus (and in a PDO mapping entry), bits."""
        return _TYPE_LAYOUT[self][1]

    @property
    def signed(self) -> bool:
        """Two's complement (INTEGERn) rather than UNSIGNEDn."""
        return _TYPE_LAYOUT[self][2]

    @property
    def min_raw(self) -> int:
        """The smallest value of the type."""
        return -(1 << (self.bits - 1)) if self.signed else 0

    @property
    def max_raw(self) -> int:
        """The largest value of the type."""
        return (1 << (self.bits - 1)) - 1 if self.signed else (1 << self.bits) - 1

    @property
    def struct_format(self) -> str:
        """Its `struct` code (CANopen is little-endian: prefix "<" for a whole frame)."""
        return _TYPE_LAYOUT[self][0]


_TYPE_LAYOUT: Mapping[DataType, tuple[str, int, bool]] = {
    DataType.INTEGER8: ("b", 8, True),
    DataType.INTEGER16: ("h", 16, True),
    DataType.INTEGER32: ("i", 32, True),
    DataType.UNSIGNED8: ("B", 8, False),
    DataType.UNSIGNED16: ("H", 16, False),
    DataType.UNSIGNED32: ("I", 32, False),
}


class Access(enum.Enum):
    """EDS access type (CiA 306): what SDO may do, and which PDO direction may map it."""

    RO = "ro"  # read only; a TPDO may map it
    RW = "rw"  # read and write by SDO
    RWW = "rww"  # read and write; an RPDO may map it (process data written by the master)
    CONST = "const"

    @property
    def writable(self) -> bool:
        """SDO (or an RPDO) may write it."""
        return self in (Access.RW, Access.RWW)


class Scaling(enum.Enum):
    """How an object's raw integer relates to its SI value (`lca_sim.cia402.codec`).

    Relative scalings take their reference from the drive: 0x6076, 0x6075 or 0x608F
    (`codec.DriveUnits`); fixed ones have a constant quantum.
    """

    RAW = "raw"  # a code, bit field, count or COB-ID: no SI value
    PERMILLE_RATED_TORQUE = "per mille of 0x6076"  # CiA 402-2 0x6071 / 0x6077
    PERMILLE_RATED_CURRENT = "per mille of 0x6075"  # CiA 402-2 0x6078
    INCREMENTS = "increments (0x608F)"  # CiA 402-2 0x6064: motor encoder counts
    INCREMENTS_PER_S = "increments/s (0x608F)"  # CiA 402-2 0x606C
    INCREMENTS_PER_S2 = "increments/s^2 (0x608F)"  # CiA 402-2 0x6083
    PERMILLE = "per mille"
    MILLI = "1e-3"  # mA, mN m, ms
    MICRO = "1e-6"  # us
    HUNDRED_MICRO = "1e-4"  # 100 us (inhibit time)
    CENTI = "1e-2"  # 10 mV

    @property
    def fixed_quantum(self) -> float | None:
        """SI units per count of a fixed scaling; None for RAW and the relative ones."""
        return _FIXED_QUANTUM.get(self)


_FIXED_QUANTUM: Mapping[Scaling, float] = {
    Scaling.PERMILLE: 1e-3,
    Scaling.MILLI: 1e-3,
    Scaling.MICRO: 1e-6,
    Scaling.HUNDRED_MICRO: 1e-4,
    Scaling.CENTI: 1e-2,
}


class Overflow(enum.Enum):
    """What encoding does with a value beyond the data type's range (`codec.Codec.encode`)."""

    SATURATE = "saturate"  # clamp to the nearest limit, as a drive's register saturates
    WRAP = "wrap"  # two's complement wrap, as an encoder counter overflows
    RAISE = "raise"  # a configuration value: out of range is an error (codec.CodecError)


@dataclass(frozen=True, slots=True)
class ObjectEntry:
    """One variable of the object dictionary.

    Attributes:
        index, subindex: where it lives.
        name: its EDS ParameterName.
        data_type: its CiA 301 data type.
        access: its EDS access type.
        pdo_mappable: whether a PDO may map it (TPDO if readable, RPDO if `rww`).
        reference: the standard object it is ("CiA 301 0x1017", "CiA 402-2 0x6077") or
            "lca_hil" for the manufacturer-specific ones.
        unit: the SI unit of the decoded value ("" for unitless quantities and raw codes).
        scaling: how raw relates to SI.
        overflow: what encoding does beyond the type's range.
        default: the value after boot-up (the EDS DefaultValue), if the table fixes one.
        default_plus_node_id: the EDS default is "$NODEID+default".
        undefined: the raw value that means "no value" (decodes to NaN), if any.
        signal: the lca_sim signal (`lca_sim.model.simulator.SIGNAL_NAMES`) behind a
            virtual-drive object, which is also the drive-chain key and `AxisState` field
            the bridge decodes it into.
    """

    index: int
    subindex: int
    name: str
    data_type: DataType
    access: Access
    pdo_mappable: bool
    reference: str
    unit: str = ""
    scaling: Scaling = Scaling.RAW
    overflow: Overflow = Overflow.RAISE
    default: int | None = None
    default_plus_node_id: bool = False
    undefined: int | None = None
    signal: str = ""

    def __post_init__(self) -> None:
        where = f"0x{self.index:04X} sub {self.subindex}"
        if not (0 <= self.index <= 0xFFFF and 0 <= self.subindex <= 0xFF):
            raise InvalidValueError(f"{where}: index or sub-index out of range")
        lo, hi = self.data_type.min_raw, self.data_type.max_raw
        for what, value in (("default", self.default), ("undefined", self.undefined)):
            if value is not None and not lo <= value <= hi:
                raise InvalidValueError(f"{where}: {what} {value} outside {self.data_type.name}")
        if self.undefined is not None and self.undefined not in (lo, hi):
            raise InvalidValueError(f"{where}: an undefined marker must be the type's min or max")

    @property
    def key(self) -> tuple[int, int]:
        """(index, sub-index)."""
        return self.index, self.subindex

    @property
    def mapping_entry(self) -> int:
        """The u32 a PDO mapping object holds to map this object (CiA 301 0x1600 / 0x1A00)."""
        return (self.index << 16) | (self.subindex << 8) | self.data_type.bits

    @property
    def manufacturer_specific(self) -> bool:
        """In 0x2000-0x5FFF: lca_hil's own, reported by the virtual drive only."""
        return self.index in MANUFACTURER_AREA

    def default_for(self, node_id: int) -> int | None:
        """The default on the node `node_id` ("$NODEID+" defaults add the node id)."""
        if self.default is None:
            return None
        return self.default + node_id if self.default_plus_node_id else self.default
