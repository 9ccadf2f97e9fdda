"""One encode/decode pair for every scaled CANopen quantity (pure: no bus, no file, no clock).

Each scaled object of `lca_sim.cia402.objects` is linear in its raw integer, SI value = raw x
quantum, the quantum fixed or taken from the drive (`DriveUnits`: 0x6075, 0x6076, 0x608F). A
`Codec` holds the quantum, the CiA 301 data type, what happens beyond the type's range
(saturate, wrap, or `CodecError`) and the "undefined" marker that decodes to NaN; the rack
(encoding its TPDOs) and the bridge (decoding them) share it. docs/can.md, "Object dictionary
(the EDS)", gives the rules and each object's scaling.

    units = DriveUnits(rated_torque_nm=1.2, rated_current_a=10.0, increments_per_rev=65536)
    torque(units).encode(0.3)        # 250 (per mille of 1.2 N m)
    EFFICIENCY.decode(0xFFFF)        # nan
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

from lca_sim.cia402 import objects as od
from lca_sim.cia402.object_entry import DataType, ObjectEntry, Overflow, Scaling
from lca_sim.errors import LcaHilError

TWO_PI = 2.0 * math.pi


class CodecError(LcaHilError, ValueError):
    """A value that cannot be encoded (NaN without a marker, beyond a strict type's range)."""


@dataclass(frozen=True, slots=True)
class DriveUnits:
    """The references a drive scales its objects by.

    Attributes:
        rated_torque_nm: motor rated torque (0x6076, mN m on the bus).
        rated_current_a: motor rated current (0x6075, mA on the bus).
        increments_per_rev: encoder increments per motor revolution (0x608F sub 1 / sub 2).
    """

    rated_torque_nm: float
    rated_current_a: float
    increments_per_rev: float

    def __post_init__(self) -> None:
        for name in ("rated_torque_nm", "rated_current_a", "increments_per_rev"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise CodecError(f"{name} must be finite and > 0, got {value!r}")

    @classmethod
    def from_raw(
        cls, rated_torque_mnm: int, rated_current_ma: int, increments: int, revolutions: int
    ) -> DriveUnits:
        """From the raw 0x6076, 0x6075, 0x608F sub 1 and sub 2 (as read over SDO).

        Raises:
            CodecError: a zero reference (the drive would scale nothing by it).
        """
        if revolutions <= 0:
            raise CodecError(f"0x608F sub 2 (motor revolutions) must be > 0, got {revolutions}")
        return cls(
            rated_torque_nm=RATED_TORQUE.decode(rated_torque_mnm),
            rated_current_a=RATED_CURRENT.decode(rated_current_ma),
            increments_per_rev=increments / revolutions,
        )


@dataclass(frozen=True, slots=True)
class Codec:
    """SI value <-> raw integer of one object: SI = raw x `quantum`.

    Attributes:
        data_type: the object's CiA 301 type (its range bounds the raw value).
        quantum: SI units per count, > 0.
        overflow: beyond the range: saturate, wrap or raise.
        undefined: the raw marker for "no value" (NaN), at the type's min or max, or None.
        min_raw, max_raw: what a finite value encodes to at most (the type's range, less the
            marker).
    """

    data_type: DataType
    quantum: float
    overflow: Overflow = Overflow.SATURATE
    undefined: int | None = None
    min_raw: int = field(init=False)
    max_raw: int = field(init=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.quantum) and self.quantum > 0.0):
            raise CodecError(f"a codec's quantum must be finite and > 0, got {self.quantum!r}")
        lo, hi = self.data_type.min_raw, self.data_type.max_raw
        if self.undefined is not None:
            if self.overflow is Overflow.WRAP:
                raise CodecError("a wrapping codec cannot reserve an undefined marker")
            if self.undefined == hi:
                hi -= 1
            elif self.undefined == lo:
                lo += 1
            else:
                raise CodecError(f"undefined marker {self.undefined} is not at the type's edge")
        object.__setattr__(self, "min_raw", lo)
        object.__setattr__(self, "max_raw", hi)

    def encode(self, value: float) -> int:
        """SI value -> raw integer (see the module docstring for the limits).

        Raises:
            CodecError: NaN without an undefined marker; with `Overflow.RAISE` a value beyond
                the range; with `Overflow.WRAP` an infinite one.
        """
        if math.isnan(value):
            if self.undefined is None:
                raise CodecError(f"NaN cannot be encoded as {self.data_type.name}")
            return self.undefined
        counts = value / self.quantum
        overflow = self.overflow
        if overflow is Overflow.SATURATE:
            if counts >= self.max_raw:
                return self.max_raw
            if counts <= self.min_raw:
                return self.min_raw
            return round(counts)
        if not math.isfinite(counts):
            raise CodecError(f"{value!r} cannot be encoded as {self.data_type.name}")
        raw = round(counts)
        if overflow is Overflow.WRAP:
            span = 1 << self.data_type.bits
            return (raw - self.min_raw) % span + self.min_raw
        if not self.min_raw <= raw <= self.max_raw:
            raise CodecError(
                f"{value!r} is {raw} counts of {self.quantum!r}, outside {self.data_type.name} "
                f"[{self.min_raw}, {self.max_raw}]"
            )
        return raw

    def encoder(self) -> Callable[[float], int]:
        """`encode` as the cheapest callable for a per-SYNC loop: the same raw for every value.

        A saturating or wrapping codec gets a closure with its limits bound; NaN (and, wrapping,
        infinity) goes to `encode`, which returns the undefined marker or raises.
        `Overflow.RAISE` is `encode` itself.
        """
        quantum, lo, hi = self.quantum, self.min_raw, self.max_raw
        if self.overflow is Overflow.SATURATE:
            undefined, refuse_nan, isnan = self.undefined, self.encode, math.isnan

            def saturate(value: float) -> int:
                if isnan(value):  # the undefined marker, or CodecError
                    return refuse_nan(value) if undefined is None else undefined
                counts = value / quantum
                if counts >= hi:
                    return hi
                if counts <= lo:
                    return lo
                return round(counts)

            return saturate
        if self.overflow is Overflow.WRAP:
            refuse, isfinite, span = self.encode, math.isfinite, 1 << self.data_type.bits

            def wrap(value: float) -> int:
                counts = value / quantum
                if not isfinite(counts):  # NaN or infinite: CodecError
                    return refuse(value)
                return (round(counts) - lo) % span + lo

            return wrap
        return self.encode

    def decode(self, raw: int) -> float:
        """Raw integer (as unpacked for the data type) -> SI value; the marker -> NaN."""
        if raw == self.undefined:
            return math.nan
        return raw * self.quantum

    def decoder(self) -> Callable[[int], float]:
        """`decode` as the cheapest callable for a per-frame loop: the same value for every raw.

        Without an undefined marker decoding is one multiplication, bound here to the quantum
        in C (`operator.mul`), which saves a Python call per field; with a marker it is
        `decode`.
        """
        if self.undefined is None:
            return partial(operator.mul, self.quantum)
        return self.decode


def codec_for(obj: ObjectEntry, units: DriveUnits | None = None) -> Codec:
    """The codec of a scaled object of the table.

    Args:
        obj: the object (`objects.entry(...)`).
        units: the drive's references; needed for the relative scalings only.

    Raises:
        CodecError: a raw object (a code or bit field has no SI value), or a relative scaling
            without `units`.
    """
    scaling = obj.scaling
    quantum = scaling.fixed_quantum
    if quantum is None:
        if scaling is Scaling.RAW:
            raise CodecError(f"0x{obj.index:04X} ({obj.name}) is not a scaled quantity")
        if units is None:
            raise CodecError(
                f"0x{obj.index:04X} ({obj.name}) is {scaling.value}: the drive's units are needed"
            )
        if scaling is Scaling.PERMILLE_RATED_TORQUE:
            quantum = units.rated_torque_nm / 1000.0
        elif scaling is Scaling.PERMILLE_RATED_CURRENT:
            quantum = units.rated_current_a / 1000.0
        else:  # INCREMENTS, INCREMENTS_PER_S: one revolution is 2 pi rad
            quantum = TWO_PI / units.increments_per_rev
    return Codec(obj.data_type, quantum, obj.overflow, obj.undefined)


# --- the quantities ------------------------------------------------------------------------------


def torque(units: DriveUnits) -> Codec:
    """Motor torque, N m <-> per mille of 0x6076 (INTEGER16: 0x6071, 0x6077, 0x2014, 0x2015)."""
    return codec_for(od.entry(od.TARGET_TORQUE), units)


def max_torque(units: DriveUnits) -> Codec:
    """Max torque 0x6072, N m <-> per mille of 0x6076 (UNSIGNED16)."""
    return codec_for(od.entry(od.MAX_TORQUE), units)


def current(units: DriveUnits) -> Codec:
    """Motor current, A <-> per mille of 0x6075 (0x6078, INTEGER16)."""
    return codec_for(od.entry(od.CURRENT_ACTUAL), units)


def position(units: DriveUnits) -> Codec:
    """Motor shaft angle, rad <-> encoder increments (0x6064, INTEGER32, wraps)."""
    return codec_for(od.entry(od.POSITION_ACTUAL), units)


def velocity(units: DriveUnits) -> Codec:
    """Motor speed, rad/s <-> increments per second (0x606C, INTEGER32, saturates)."""
    return codec_for(od.entry(od.VELOCITY_ACTUAL), units)


def increments_per_joint_unit(units: DriveUnits, gear_ratio: float) -> float:
    """Increments per joint rad (per m for a prismatic joint): gear_ratio x 0x608F / 2 pi.

    `gear_ratio` is the robot config's motor rad per joint rad (or per m). Every position and
    velocity object of docs/can-modes.md is motor increments; this is their joint scale.

    Raises:
        CodecError: a gear ratio that is not finite and > 0.
    """
    if not (math.isfinite(gear_ratio) and gear_ratio > 0.0):
        raise CodecError(f"gear_ratio must be finite and > 0, got {gear_ratio!r}")
    return gear_ratio * units.increments_per_rev / TWO_PI


# Efficiency (0x2012 / 0x2013): per mille, UNSIGNED16, 0xFFFF = undefined (axis stopped).
EFFICIENCY = codec_for(od.entry(od.ETA_M))
# Amplifier voltage (0x2016): 10 mV, INTEGER16 (+-327.67 V: the pivot's 300 V amplifier fits).
VOLTAGE = codec_for(od.entry(od.VOLTAGE))
# Rated values (0x6075 mA, 0x6076 mN m, UNSIGNED32): configuration, so out of range raises.
RATED_CURRENT = codec_for(od.entry(od.MOTOR_RATED_CURRENT))
RATED_TORQUE = codec_for(od.entry(od.MOTOR_RATED_TORQUE))
# Timing (0x1006 us, 0x1017 ms).
CYCLE_PERIOD = codec_for(od.entry(od.CYCLE_PERIOD))
HEARTBEAT_TIME = codec_for(od.entry(od.HEARTBEAT_PRODUCER))
