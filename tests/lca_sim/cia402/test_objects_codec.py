"""The object table (lca_sim.cia402.objects), the unit codec (.codec) and the shipped EDS.

The codec laws hold for all inputs (hypothesis): decode(encode(x)) within half a quantum of x
inside the type's range, encode(decode(raw)) == raw for every raw value, saturation / wrap /
raise beyond the range, NaN <-> the undefined marker. The EDS (config/can/lca_drive.eds) is
read with configparser, independently of the table, and compared entry by entry.
"""

from __future__ import annotations

import configparser
import math
from collections.abc import Callable

import canopen
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support import CONFIG

from lca_sim.cia402 import bus_load, codec
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import Codec, CodecError, DriveUnits
from lca_sim.cia402.device import SUPPORTED_DRIVE_MODES_BITS
from lca_sim.cia402.object_entry import (
    Access,
    DataType,
    ObjectEntry,
    Overflow,
    Scaling,
    UnknownObjectError,
)

EDS = CONFIG / "can" / "lca_drive.eds"
SHIPPED = DriveUnits(rated_torque_nm=1.2, rated_current_a=10.0, increments_per_rev=65536)

# A drive's references: rated torque 1 mN m - 1 kN m, current 10 mA - 1 kA, 1 - 2^24 counts/rev.
units_st = st.builds(
    DriveUnits,
    rated_torque_nm=st.floats(1e-3, 1e3),
    rated_current_a=st.floats(1e-2, 1e3),
    increments_per_rev=st.integers(1, 1 << 24).map(float),
)

# Every scaled quantity lca_hil codes, by name: its codec for some drive units.
QUANTITIES: dict[str, Callable[[DriveUnits], Codec]] = {
    "torque (0x6071/0x6077/0x2014/0x2015)": codec.torque,
    "max torque (0x6072)": codec.max_torque,
    "current (0x6078)": codec.current,
    "position (0x6064)": codec.position,
    "velocity (0x606C)": codec.velocity,
    "efficiency (0x2012/0x2013)": lambda _: codec.EFFICIENCY,
    "voltage (0x2016)": lambda _: codec.VOLTAGE,
    "rated current (0x6075)": lambda _: codec.RATED_CURRENT,
    "rated torque (0x6076)": lambda _: codec.RATED_TORQUE,
    "cycle period (0x1006)": lambda _: codec.CYCLE_PERIOD,
    "heartbeat time (0x1017)": lambda _: codec.HEARTBEAT_TIME,
}


# --- the codec: laws for every quantity ---------------------------------------------------------


@pytest.mark.parametrize("name", QUANTITIES)
@given(units=units_st, fraction=st.floats(0.0, 1.0))
def test_decode_of_encode_is_within_half_a_quantum(
    name: str, units: DriveUnits, fraction: float
) -> None:
    """Any SI value inside the type's range comes back within half a quantum."""
    c = QUANTITIES[name](units)
    value = (c.min_raw + fraction * (c.max_raw - c.min_raw)) * c.quantum
    raw = c.encode(value)
    assert c.min_raw <= raw <= c.max_raw
    # half a quantum, plus the float rounding of products as large as 2^32 counts
    assert abs(c.decode(raw) - value) <= 0.5 * c.quantum + 1e-15 * abs(value)


@pytest.mark.parametrize("name", QUANTITIES)
@given(units=units_st, data=st.data())
def test_encode_of_decode_is_exact_for_every_raw_value(
    name: str, units: DriveUnits, data: st.DataObject
) -> None:
    """Every raw value of the type (but the marker) decodes and encodes back to itself."""
    c = QUANTITIES[name](units)
    raw = data.draw(
        st.one_of(st.sampled_from([c.min_raw, c.max_raw, 0, 1]), st.integers(c.min_raw, c.max_raw))
    )
    assert c.encode(c.decode(raw)) == raw


@pytest.mark.parametrize("name", QUANTITIES)
@given(units=units_st, data=st.data())
def test_the_fast_decoder_is_decode(name: str, units: DriveUnits, data: st.DataObject) -> None:
    """`Codec.decoder()` (what the bridge calls per frame) gives decode's value for every raw."""
    c = QUANTITIES[name](units)
    type_ = c.data_type
    raw = data.draw(st.integers(type_.min_raw, type_.max_raw))
    fast, exact = c.decoder()(raw), c.decode(raw)
    assert fast == exact or (math.isnan(fast) and math.isnan(exact))


def _outcome(encode: Callable[[float], int], value: float) -> tuple[object, ...]:
    try:
        return ("raw", encode(value))
    except CodecError as exc:
        return ("refused", str(exc))


@pytest.mark.parametrize("name", QUANTITIES)
@given(units=units_st, data=st.data())
def test_the_fast_encoder_is_encode(name: str, units: DriveUnits, data: st.DataObject) -> None:
    """`Codec.encoder()` (what the rack's TPDOs call per SYNC) gives encode's raw or refusal."""
    c = QUANTITIES[name](units)
    span = (c.max_raw - c.min_raw + 2) * c.quantum
    value = data.draw(
        st.one_of(
            st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0]),
            st.sampled_from([c.min_raw, c.max_raw, c.min_raw - 0.5, c.max_raw + 0.5]).map(
                lambda raw: raw * c.quantum
            ),
            st.floats(-2.0 * span, 2.0 * span),
            st.floats(allow_nan=False),
        )
    )
    assert _outcome(c.encoder(), value) == _outcome(c.encode, value)


@pytest.mark.parametrize(
    ("data_type", "lo", "hi"),
    [
        (DataType.INTEGER8, -128, 127),
        (DataType.INTEGER16, -32768, 32767),
        (DataType.INTEGER32, -(2**31), 2**31 - 1),
        (DataType.UNSIGNED8, 0, 255),
        (DataType.UNSIGNED16, 0, 65535),
        (DataType.UNSIGNED32, 0, 2**32 - 1),
    ],
)
def test_type_limits_and_saturation(data_type: DataType, lo: int, hi: int) -> None:
    """A saturating codec clamps to the CiA 301 type's bounds, infinities included."""
    assert (data_type.min_raw, data_type.max_raw) == (lo, hi)
    c = Codec(data_type, 0.5, Overflow.SATURATE)
    assert c.encode(hi * 0.5) == hi
    assert c.encode(hi * 0.5 + 0.5) == hi  # one count beyond
    assert c.encode(1e300) == hi
    assert c.encode(math.inf) == hi
    assert c.encode(lo * 0.5) == lo
    assert c.encode(lo * 0.5 - 0.5) == lo
    assert c.encode(-math.inf) == lo
    with pytest.raises(CodecError, match="NaN"):
        c.encode(math.nan)


@given(units=units_st, turns=st.integers(-1000, 1000), counts=st.integers(-(2**31), 2**31 - 1))
def test_position_wraps_like_an_encoder_counter(units: DriveUnits, turns: int, counts: int) -> None:
    """0x6064 wraps at the INTEGER32 bounds: 2^32 counts more is the same register value."""
    c = codec.position(units)
    assert c.encode((counts + turns * 2**32) * c.quantum) == counts
    with pytest.raises(CodecError):
        c.encode(math.inf)
    with pytest.raises(CodecError):
        c.encode(math.nan)


def test_configuration_values_raise_beyond_their_type() -> None:
    """0x6075 / 0x6076 (UNSIGNED32, mA / mN m) must fit: a negative or too large value raises."""
    assert codec.RATED_CURRENT.encode(4294967.295) == 2**32 - 1
    for bad in (-0.001, 4294967.296, math.inf, math.nan):
        with pytest.raises(CodecError):
            codec.RATED_CURRENT.encode(bad)
    assert codec.RATED_TORQUE.encode(-0.0004) == 0  # rounds to 0 mN m: inside the range


@given(eta=st.floats(0.0, 65.534))
def test_efficiency_never_encodes_a_finite_value_to_the_marker(eta: float) -> None:
    """Per mille, UNSIGNED16, 0xFFFF reserved: finite values stop at 0xFFFE (65.534)."""
    raw = codec.EFFICIENCY.encode(eta)
    assert raw != od.EFFICIENCY_UNDEFINED
    assert abs(codec.EFFICIENCY.decode(raw) - eta) <= 0.0005 + 1e-12


def test_undefined_efficiency_is_nan_both_ways() -> None:
    """Axis stopped: NaN -> 0xFFFF -> NaN (not 65.535); 1e9 saturates at 0xFFFE; < 0 at 0."""
    assert codec.EFFICIENCY.encode(math.nan) == 0xFFFF
    assert math.isnan(codec.EFFICIENCY.decode(0xFFFF))
    assert codec.EFFICIENCY.encode(1e9) == 0xFFFE
    assert codec.EFFICIENCY.decode(0xFFFE) == pytest.approx(65.534)
    assert codec.EFFICIENCY.encode(-0.2) == 0
    for obj in (od.entry(od.ETA_M), od.entry(od.ETA_L)):
        assert obj.undefined == obj.default == 0xFFFF


@pytest.mark.parametrize(
    "name", ["voltage (0x2016)", "torque (0x6071/0x6077/0x2014/0x2015)", "current (0x6078)"]
)
def test_quantities_without_a_marker_refuse_nan(name: str) -> None:
    """Only 0x2012 / 0x2013 have an undefined marker; elsewhere NaN is an error, not a value."""
    with pytest.raises(CodecError, match="NaN"):
        QUANTITIES[name](SHIPPED).encode(math.nan)


def test_hand_worked_numbers() -> None:
    """The shipped drive (1.2 N m, 10 A, 65536 counts/rev), worked by hand."""
    assert codec.torque(SHIPPED).encode(0.3) == 250
    assert codec.torque(SHIPPED).decode(500) == pytest.approx(0.6)
    assert codec.current(SHIPPED).decode(250) == pytest.approx(2.5)
    assert codec.current(SHIPPED).encode(-1.234) == -123
    assert codec.current(SHIPPED).encode(1000.0) == 32767  # saturated INTEGER16
    assert codec.max_torque(SHIPPED).encode(-1.0) == 0  # UNSIGNED16
    position = codec.position(SHIPPED)
    assert position.encode(math.pi) == 32768
    assert position.encode(-2.0 * math.pi) == -65536
    assert position.decode(16384) == pytest.approx(math.pi / 2.0)
    # pivot at 35 deg behind a 600:1 gear: 0.6109 * 600 / (2 pi) * 65536 increments
    assert position.encode(0.6109 * 600.0) == 3823151
    assert position.encode(2**31 * position.quantum) == -(2**31)  # the counter wraps
    velocity = codec.velocity(DriveUnits(1.2, 10.0, 4096))
    assert velocity.encode(2.0 * math.pi) == 4096
    assert velocity.encode(1e12) == 2**31 - 1  # saturates, does not wrap
    assert codec.EFFICIENCY.encode(0.55) == 550
    assert codec.VOLTAGE.encode(-12.345) == -1234  # 10 mV, half to even
    assert codec.VOLTAGE.encode(300.0) == 30000  # the pivot's 300 V amplifier fits
    assert codec.VOLTAGE.encode(400.0) == 32767  # +-327.67 V
    assert codec.RATED_TORQUE.encode(0.12 * 10.0) == 1200  # k_t x rated current, mN m
    assert codec.CYCLE_PERIOD.encode(1.0 / 250.0) == 4000  # us
    assert DriveUnits.from_raw(1200, 10000, 65536, 1) == SHIPPED
    assert DriveUnits.from_raw(1200, 10000, 4096, 2).increments_per_rev == 2048.0


@pytest.mark.parametrize(
    ("gear_ratio", "per_unit"),
    [(800.0, 8344303), (600.0, 6258227), (700.0, 7301265), (6283.2, 65536153)],
)
def test_increments_per_joint_unit(gear_ratio: float, per_unit: int) -> None:
    """The docs/can-modes.md table: l_arm, pivot, c_arc per rad, the lift per metre."""
    assert round(codec.increments_per_joint_unit(SHIPPED, gear_ratio)) == per_unit
    with pytest.raises(CodecError, match="gear_ratio"):
        codec.increments_per_joint_unit(SHIPPED, 0.0)


def test_codec_refusals() -> None:
    """A code has no SI value; a relative scaling needs the drive's units; bad units refused."""
    with pytest.raises(CodecError, match="not a scaled quantity"):
        codec.codec_for(od.entry(od.STATUSWORD))
    with pytest.raises(CodecError, match="per mille of 0x6076"):
        codec.codec_for(od.entry(od.TARGET_TORQUE))
    with pytest.raises(CodecError, match="rated_torque_nm"):
        DriveUnits.from_raw(0, 10000, 65536, 1)
    with pytest.raises(CodecError, match="motor revolutions"):
        DriveUnits.from_raw(1200, 10000, 65536, 0)
    with pytest.raises(CodecError, match="edge"):
        Codec(DataType.UNSIGNED16, 1.0, undefined=7)
    with pytest.raises(CodecError, match="wrapping"):
        Codec(DataType.INTEGER32, 1.0, Overflow.WRAP, undefined=-(2**31))


# --- the object table ---------------------------------------------------------------------------


def test_table_is_consistent() -> None:
    """One entry per key; every scaled entry has a codec and a unit; markers at type edges."""
    assert len(od.BY_KEY) == len(od.OBJECTS)
    for obj in od.OBJECTS:
        assert od.entry(obj.index, obj.subindex) is obj
        if obj.scaling is Scaling.RAW:
            assert obj.unit == ""
            continue
        c = codec.codec_for(obj, SHIPPED)
        assert c.data_type is obj.data_type
        assert obj.unit or obj.scaling is Scaling.PERMILLE, obj  # efficiency is unitless
        if obj.undefined is not None:
            assert obj.undefined in (obj.data_type.min_raw, obj.data_type.max_raw)


def test_standard_objects_cite_their_profile() -> None:
    """0x1000-0x1FFF cite CiA 301, 0x6000- CiA 402-2, 0x2000-0x5FFF are lca_hil's."""
    for obj in od.OBJECTS:
        if obj.index < 0x2000:
            assert obj.reference == f"CiA 301 0x{obj.index:04X}"
        elif obj.manufacturer_specific:
            assert obj.reference == "lca_hil"
        else:
            assert obj.reference == f"CiA 402-2 0x{obj.index:04X}"


def test_unknown_object_names_itself() -> None:
    """An object the table does not declare: one line naming index and sub-index."""
    with pytest.raises(UnknownObjectError) as error:
        od.entry(0x6079)
    assert str(error.value).startswith("object 0x6079 sub 0 is not in lca_hil's object table")
    with pytest.raises(ValueError, match="outside INTEGER16"):
        ObjectEntry(0x2FFF, 0, "x", DataType.INTEGER16, Access.RO, True, "lca_hil", default=1 << 15)


def test_default_pdo_mappings_come_from_the_table() -> None:
    """Each default PDO's mapping objects hold the table's entries; none exceeds 64 bits."""
    for pdo in od.DEFAULT_PDOS:
        base = od.RPDO_MAPPING if pdo.receive else od.TPDO_MAPPING
        mapping = base + pdo.number - 1
        assert od.entry(mapping, 0).default == len(pdo.objects)
        entries = [od.entry(mapping, k).default for k in range(1, len(pdo.objects) + 1)]
        assert entries == [od.entry(i).mapping_entry for i in pdo.objects]
        assert sum(od.entry(i).data_type.bits for i in pdo.objects) <= 64
        for index in pdo.objects:
            obj = od.entry(index)
            assert obj.pdo_mappable
            assert obj.access is (Access.RWW if pdo.receive else obj.access)
    assert od.entry(od.TPDO_MAPPING + 3, 1).default == 0x20140010
    assert od.entry(od.TPDO_COMMUNICATION + 3, 2).default == od.EXTRAS_TRANSMISSION_TYPE == 10
    assert od.entry(od.SUPPORTED_DRIVE_MODES).default == SUPPORTED_DRIVE_MODES_BITS


def test_mode_objects_map_as_the_modes_use_them() -> None:
    """Cyclic set-points are rww and mappable, demand values ro and mappable; the rest rw.

    The modes' configuration (windows, ramps, homing) is SDO-only. docs/can-modes.md.
    """
    for index in (od.TARGET_POSITION, od.VELOCITY_OFFSET, od.TORQUE_OFFSET):
        assert (od.entry(index).access, od.entry(index).pdo_mappable) == (Access.RWW, True)
    for index in (od.POSITION_DEMAND, od.FOLLOWING_ERROR_ACTUAL):
        assert (od.entry(index).access, od.entry(index).pdo_mappable) == (Access.RO, True)
    configuration = [
        *((index, 0) for index in (
            od.HALT_OPTION, od.FOLLOWING_ERROR_WINDOW, od.FOLLOWING_ERROR_TIME,
            od.POSITION_WINDOW, od.POSITION_WINDOW_TIME, od.VELOCITY_WINDOW,
            od.VELOCITY_WINDOW_TIME, od.VELOCITY_THRESHOLD, od.VELOCITY_THRESHOLD_TIME,
            od.HOME_OFFSET, od.MAX_PROFILE_VELOCITY, od.PROFILE_VELOCITY,
            od.PROFILE_ACCELERATION, od.PROFILE_DECELERATION, od.QUICK_STOP_DECELERATION,
            od.MOTION_PROFILE_TYPE, od.HOMING_METHOD, od.HOMING_ACCELERATION, od.MAX_SLIPPAGE,
            od.HOMING_STOP_CURRENT, od.HOMING_STOP_TIME,
        )),
        (od.SOFTWARE_POSITION_LIMIT, 1), (od.SOFTWARE_POSITION_LIMIT, 2),
        (od.HOMING_SPEEDS, 1), (od.HOMING_SPEEDS, 2),
    ]  # fmt: skip
    for key in configuration:
        assert (od.BY_KEY[key].access, od.BY_KEY[key].pdo_mappable) == (Access.RW, False), key


def test_bus_load_of_the_default_mapping() -> None:
    """Four axes at 500 Hz on 1 Mbit/s: SYNC, RPDO1, TPDO1, TPDO2 each cycle, TPDO4 every 10th.

    1355 bits per cycle before the extras (67.75 %); TPDO4 adds 4 x 115 bits every 10th
    SYNC: 70.05 %. Sent every SYNC it would add 23 % (90.75 %).
    """

    def frame_bits(pdo: od.PdoDefault) -> int:
        return bus_load.frame_bits(sum(od.entry(i).data_type.bits for i in pdo.objects) // 8)

    synchronous = [p for p in od.DEFAULT_PDOS if p.valid and p.transmission_type <= 240]
    per_cycle = bus_load.frame_bits(0) + 4 * sum(
        frame_bits(p) / p.transmission_type for p in synchronous
    )
    assert per_cycle == pytest.approx(1401.0)
    assert bus_load.bus_load_pct(per_cycle * 500, 1e6) == pytest.approx(70.05)
    extras = next(p for p in od.DEFAULT_PDOS if p.objects[0] == od.LOAD_TORQUE)
    assert bus_load.bus_load_pct((per_cycle + 4 * frame_bits(extras) * 0.9) * 500, 1e6) == (
        pytest.approx(90.75)
    )


# --- the shipped EDS against the table ----------------------------------------------------------


def _eds() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(inline_comment_prefixes=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # keep the key case
    parser.read(EDS, encoding="utf-8")
    return parser


def _variable_sections(eds: configparser.ConfigParser) -> dict[tuple[int, int], str]:
    """Every VAR of the EDS: (index, sub-index) -> its section name."""
    found = {}
    for name in eds.sections():
        head, _, sub = name.partition("sub")
        try:
            index = int(head, 16)
        except ValueError:
            continue  # [FileInfo], [DeviceInfo], ...
        if int(eds[name]["ObjectType"], 0) == 0x7:
            found[(index, int(sub, 16) if sub else 0)] = name
    return found


def _default(text: str) -> tuple[int, bool]:
    """An EDS DefaultValue: (value, whether it is "$NODEID+" relative)."""
    relative = text.upper().startswith("$NODEID+")
    return int(text[len("$NODEID+") :] if relative else text, 0), relative


def test_eds_agrees_with_the_table_entry_by_entry() -> None:
    """Name, data type, access, PDO mapping, default of every variable; none extra or missing."""
    eds = _eds()
    sections = _variable_sections(eds)
    assert set(sections) == set(od.BY_KEY), "the EDS and the table declare different variables"
    for key, section in sections.items():
        obj, fields = od.BY_KEY[key], eds[section]
        where = f"[{section}]"
        assert fields["ParameterName"] == obj.name, where
        assert int(fields["DataType"], 0) == obj.data_type, where
        assert fields["AccessType"] == obj.access.value, where
        assert bool(int(fields["PDOMapping"])) == obj.pdo_mappable, where
        if obj.default is not None:
            assert _default(fields["DefaultValue"]) == (obj.default, obj.default_plus_node_id), (
                where
            )


def test_eds_object_lists_and_pdo_counts_match_the_table() -> None:
    """[Mandatory/Optional/ManufacturerObjects] list exactly the table's indices; PDO counts."""
    eds = _eds()
    listed = []
    for section in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        fields = eds[section]
        count = int(fields["SupportedObjects"])
        listed += [int(fields[str(k)], 0) for k in range(1, count + 1)]
        assert len(fields) == count + 1, section
    assert sorted(listed) == sorted({obj.index for obj in od.OBJECTS})
    manufacturer = [int(v, 0) for k, v in eds["ManufacturerObjects"].items() if k.isdigit()]
    assert manufacturer == sorted({o.index for o in od.OBJECTS if o.manufacturer_specific})
    info = eds["DeviceInfo"]
    assert int(info["NrOfRXPDO"]) == sum(p.receive for p in od.DEFAULT_PDOS) == 2
    assert int(info["NrOfTXPDO"]) == sum(not p.receive for p in od.DEFAULT_PDOS) == 4


@pytest.mark.parametrize("node_id", [1, 4, 127])
def test_canopen_reads_the_eds_as_the_table_says(node_id: int) -> None:
    """What the rack and bridge load (canopen's EDS import) has the table's types and defaults."""
    dictionary = canopen.objectdictionary.import_od(str(EDS), node_id)
    for obj in od.OBJECTS:
        var = dictionary[obj.index]
        if not isinstance(var, canopen.objectdictionary.ODVariable):
            var = var[obj.subindex]
        assert (var.data_type, var.default, var.pdo_mappable) == (
            obj.data_type,
            obj.default_for(node_id),
            obj.pdo_mappable,
        ), hex(obj.index)
