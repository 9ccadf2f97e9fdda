"""The CANopen object dictionary of lca_hil, declared once (pure: no bus, no file, no clock).

One `ObjectEntry` per variable the virtual drive holds (config/can/lca_drive.eds) and the
bridge reads or writes: index, sub-index, name, CiA 301 data type, access, PDO mapping, SI unit
and scaling, default and "undefined" marker; standard objects cite CiA 301 or CiA 402-2,
0x2010-0x2041 are lca_hil's (docs/can.md, "Object dictionary (the EDS)"; the objects of the
profile and position modes: docs/can-modes.md). The rack, the bridge and the EDS test read this
table instead of repeating it; the entry types are in `object_entry`.

    from lca_sim.cia402 import objects as od

    od.entry(od.TARGET_TORQUE).data_type      # DataType.INTEGER16
    od.entry(od.ETA_M).undefined              # 0xFFFF: decodes to NaN
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from lca_sim.cia402.object_entry import (
    Access,
    DataType,
    ObjectEntry,
    Overflow,
    Scaling,
    UnknownObjectError,
)

# --- object indices ----------------------------------------------------------------------------
# CiA 301 communication profile area
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
COB_ID_SYNC = 0x1005
CYCLE_PERIOD = 0x1006  # us
COB_ID_EMCY = 0x1014
HEARTBEAT_CONSUMER = 0x1016
HEARTBEAT_PRODUCER = 0x1017  # ms
IDENTITY = 0x1018
ERROR_BEHAVIOUR = 0x1029  # sub 1: communication error -> NMT state (ERROR_BEHAVIOUR_*)
RPDO_COMMUNICATION = 0x1400  # + PDO number - 1
RPDO_MAPPING = 0x1600
TPDO_COMMUNICATION = 0x1800
TPDO_MAPPING = 0x1A00
# lca_hil manufacturer-specific area: the drive chain of the lca_sim plant (virtual drive only)
DRIVE_STATE = 0x2010  # gear functional state index
MOTION_STATE = 0x2011  # -1, 0, +1
ETA_M = 0x2012  # per mille, 0xFFFF undefined
ETA_L = 0x2013
LOAD_TORQUE = 0x2014  # motor side, per mille of 0x6076
FRICTION_TORQUE = 0x2015  # motor side, per mille of 0x6076
VOLTAGE = 0x2016  # amplifier output voltage, 10 mV
PROCESS_STALLS = 0x2020  # how often the virtual drive's process stood still (count)
LONGEST_STALL = 0x2021  # the longest such stall, ms
HOMING_STOP_CURRENT = 0x2040  # homing on a mechanical stop: |current| pressing it, per mille
HOMING_STOP_TIME = 0x2041  # ... for this long, ms
# lca_hil fault injection (virtual drive only): a RECORD, SDO-writable, one sub per fault kind
FAULT_INJECTION = 0x2030
FAULT_LOST_TPDOS = 1  # UNSIGNED8: bit n - 1 set = TPDO n is not sent
FAULT_HEARTBEAT_OFF = 2  # UNSIGNED8: 1 = the heartbeat producer is silent
FAULT_RAISE_EMCY = 3  # UNSIGNED16: writing a code sends that EMCY; 0 clears it
FAULT_DRIVE_FAULT = 4  # UNSIGNED16: a drive fault with this code (CiA 402 FAULT); 0 clears
FAULT_BUS_OFF = 5  # UNSIGNED16: off the bus for this many ms of the rack's time; 0 = on
# CiA 402-2 drive profile area
ABORT_CONNECTION_OPTION = 0x6007
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
HALT_OPTION = 0x605D
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_DEMAND = 0x6062  # increments
POSITION_ACTUAL = 0x6064  # increments
FOLLOWING_ERROR_WINDOW = 0x6065  # increments
FOLLOWING_ERROR_TIME = 0x6066  # ms
POSITION_WINDOW = 0x6067  # increments
POSITION_WINDOW_TIME = 0x6068  # ms
VELOCITY_ACTUAL = 0x606C  # increments/s
VELOCITY_WINDOW = 0x606D  # increments/s
VELOCITY_WINDOW_TIME = 0x606E  # ms
VELOCITY_THRESHOLD = 0x606F  # increments/s
VELOCITY_THRESHOLD_TIME = 0x6070  # ms
TARGET_POSITION = 0x607A  # increments (PP, CSP)
HOME_OFFSET = 0x607C  # increments
SOFTWARE_POSITION_LIMIT = 0x607D  # sub 1 min, sub 2 max, increments
MAX_PROFILE_VELOCITY = 0x607F  # increments/s
PROFILE_VELOCITY = 0x6081  # increments/s
PROFILE_ACCELERATION = 0x6083  # increments/s^2
PROFILE_DECELERATION = 0x6084  # increments/s^2
QUICK_STOP_DECELERATION = 0x6085  # increments/s^2
MOTION_PROFILE_TYPE = 0x6086
HOMING_METHOD = 0x6098
HOMING_SPEEDS = 0x6099  # sub 1 search for switch, sub 2 search for zero, increments/s
HOMING_ACCELERATION = 0x609A  # increments/s^2
VELOCITY_OFFSET = 0x60B1  # increments/s (CSP)
TORQUE_OFFSET = 0x60B2  # per mille of rated torque (CSP)
FOLLOWING_ERROR_ACTUAL = 0x60F4  # increments
MAX_SLIPPAGE = 0x60F8  # increments/s (PV)
TARGET_TORQUE = 0x6071  # per mille of rated torque
TARGET_VELOCITY = 0x60FF  # increments/s (CSV, mode 9)
MAX_TORQUE = 0x6072
MOTOR_RATED_CURRENT = 0x6075  # mA
MOTOR_RATED_TORQUE = 0x6076  # mN m
TORQUE_ACTUAL = 0x6077  # per mille of rated torque
CURRENT_ACTUAL = 0x6078  # per mille of rated current
POSITION_ENCODER_RESOLUTION = 0x608F
SUPPORTED_DRIVE_MODES = 0x6502

# CiA 301 0x1029 sub 1 (7.5.2.32): what a communication error does to the NMT state.
ERROR_BEHAVIOUR_PRE_OPERATIONAL = 0  # CiA 301's default and ours: to PRE-OPERATIONAL, if OP
ERROR_BEHAVIOUR_NO_CHANGE = 1
ERROR_BEHAVIOUR_STOPPED = 2
ERROR_BEHAVIOURS = frozenset(
    {ERROR_BEHAVIOUR_PRE_OPERATIONAL, ERROR_BEHAVIOUR_NO_CHANGE, ERROR_BEHAVIOUR_STOPPED}
)


# CiA 301 7.5.2.2 (0x1001 error register): bit 0 generic (set for any error), 1 current,
# 2 voltage, 3 temperature, 4 communication, 5 device profile specific, 7 manufacturer specific.
ERROR_REGISTER_GENERIC_BIT = 1 << 0
_ERROR_REGISTER_BY_CLASS: tuple[tuple[int, int, int], ...] = (
    # (mask, value, bit) over the EMCY code, CiA 301 table 21 (emergency error code classes)
    (0xF000, 0x2000, 1 << 1),  # current
    (0xF000, 0x3000, 1 << 2),  # voltage
    (0xF000, 0x4000, 1 << 3),  # temperature
    (0xFF00, 0x8100, 1 << 4),  # communication
    (0xFF00, 0x8200, 1 << 4),  # protocol error (PDO, SYNC length): communication too
    (0xFF00, 0xFF00, 1 << 7),  # device specific: manufacturer-specific bit
)


def error_register_for(code: int) -> int:
    """The 0x1001 bits an error with EMCY code `code` sets (CiA 301 7.5.2.2); 0 for no error.

    Generic (bit 0) for every error, plus the bit of the code's class where 0x1001 has one
    (0x2xxx current, 0x3xxx voltage, 0x4xxx temperature, 0x81xx / 0x82xx communication,
    0xFFxx manufacturer specific). Codes 0x0000-0x00FF are "error reset or no error".
    """
    if code & 0xFF00 == 0:
        return 0
    bits = ERROR_REGISTER_GENERIC_BIT
    for mask, value, bit in _ERROR_REGISTER_BY_CLASS:
        if code & mask == value:
            bits |= bit
    return bits


EFFICIENCY_UNDEFINED = 0xFFFF  # 0x2012 / 0x2013 while the axis is stopped (eq. 10 idle)
# TPDO4 (the drive-chain extras 0x2014-0x2016) goes every this many SYNCs (CiA 301 0x1803
# sub 2, types 1-240): the extras change slowly next to position and velocity, and one 6-byte
# frame per axis every 10th SYNC costs 2.3 % of a 1 Mbit/s bus at 500 Hz instead of 23 %.
EXTRAS_TRANSMISSION_TYPE = 10


_U8, _U16, _U32 = DataType.UNSIGNED8, DataType.UNSIGNED16, DataType.UNSIGNED32
_I8, _I16, _I32 = DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32
_RO, _RW, _RWW = Access.RO, Access.RW, Access.RWW
_SAT = Overflow.SATURATE


def _cia301(index: int) -> str:
    return f"CiA 301 0x{index:04X}"


def _cia402(index: int) -> str:
    return f"CiA 402-2 0x{index:04X}"


# --- the default PDOs ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class PdoDefault:
    """A PDO as the drive boots (its communication and mapping objects' defaults).

    Attributes:
        number: 1-based PDO number.
        receive: RPDO (master -> drive) rather than TPDO.
        cob_id: the COB-ID without the node id (CiA 301 pre-defined connection set).
        valid: COB-ID bit 31 clear.
        transmission_type: 0-240 synchronous (every n-th SYNC for a TPDO), 254/255 event.
        event_timer_ms: TPDO: at least this often (0: never); RPDO: the deadline (0: off).
        objects: the mapped objects, in frame order (sub-index 0 of each).
    """

    number: int
    receive: bool
    cob_id: int
    valid: bool
    transmission_type: int
    event_timer_ms: int
    objects: tuple[int, ...]


DEFAULT_PDOS: tuple[PdoDefault, ...] = (
    PdoDefault(1, True, 0x200, True, 1, 0, (CONTROLWORD, TARGET_TORQUE)),
    PdoDefault(2, True, 0x300, False, 1, 0, (CONTROLWORD, MODES_OF_OPERATION)),
    PdoDefault(1, False, 0x180, True, 1, 0, (STATUSWORD, POSITION_ACTUAL)),
    PdoDefault(2, False, 0x280, True, 1, 0, (VELOCITY_ACTUAL, CURRENT_ACTUAL)),
    PdoDefault(3, False, 0x380, True, 254, 100, (DRIVE_STATE, MOTION_STATE, ETA_M, ETA_L)),
    PdoDefault(
        4,
        False,
        0x480,
        True,
        EXTRAS_TRANSMISSION_TYPE,
        0,
        (LOAD_TORQUE, FRICTION_TORQUE, VOLTAGE),
    ),
)

PDO_MAPPING_SLOTS = 8  # sub 1-8 of each mapping object
PDO_COB_ID_INVALID = 1 << 31  # CiA 301 PDO communication sub 1: the PDO does not exist
PDO_COB_ID_NO_RTR = 1 << 30  # CiA 301 TPDO communication sub 1: no RTR allowed


_INC, _INC_S, _INC_S2 = Scaling.INCREMENTS, Scaling.INCREMENTS_PER_S, Scaling.INCREMENTS_PER_S2
_REV = 65536  # increments per motor revolution of the shipped 0x608F: the defaults below

# CiA 402-2 objects of the profile and cyclic position modes (PP 1, PV 3, HM 6, CSP 8), motor
# side, factor group off (position units = increments). docs/can-modes.md gives each default
# in joint units; the rack stores them until the modes are wired in.
_MODE_OBJECTS: tuple[ObjectEntry, ...] = (
    ObjectEntry(HALT_OPTION, 0, "Halt option code", _I16, _RW, False, _cia402(HALT_OPTION),
                default=1),  # 1 slow-down ramp 0x6084, 2 quick-stop ramp 0x6085
    ObjectEntry(POSITION_DEMAND, 0, "Position demand value", _I32, _RO, True,
                _cia402(POSITION_DEMAND), "rad", _INC, Overflow.WRAP, default=0),
    ObjectEntry(FOLLOWING_ERROR_WINDOW, 0, "Following error window", _U32, _RW, False,
                _cia402(FOLLOWING_ERROR_WINDOW), "rad", _INC, _SAT, default=10 * _REV),
    ObjectEntry(FOLLOWING_ERROR_TIME, 0, "Following error time out", _U16, _RW, False,
                _cia402(FOLLOWING_ERROR_TIME), "s", Scaling.MILLI, default=10),
    ObjectEntry(POSITION_WINDOW, 0, "Position window", _U32, _RW, False,
                _cia402(POSITION_WINDOW), "rad", _INC, _SAT, default=_REV // 8),
    ObjectEntry(POSITION_WINDOW_TIME, 0, "Position window time", _U16, _RW, False,
                _cia402(POSITION_WINDOW_TIME), "s", Scaling.MILLI, default=10),
    ObjectEntry(VELOCITY_WINDOW, 0, "Velocity window", _U16, _RW, False,
                _cia402(VELOCITY_WINDOW), "rad/s", _INC_S, _SAT, default=_REV // 8),
    ObjectEntry(VELOCITY_WINDOW_TIME, 0, "Velocity window time", _U16, _RW, False,
                _cia402(VELOCITY_WINDOW_TIME), "s", Scaling.MILLI, default=10),
    ObjectEntry(VELOCITY_THRESHOLD, 0, "Velocity threshold", _U16, _RW, False,
                _cia402(VELOCITY_THRESHOLD), "rad/s", _INC_S, _SAT, default=_REV // 8),
    ObjectEntry(VELOCITY_THRESHOLD_TIME, 0, "Velocity threshold time", _U16, _RW, False,
                _cia402(VELOCITY_THRESHOLD_TIME), "s", Scaling.MILLI, default=10),
    ObjectEntry(TARGET_POSITION, 0, "Target position", _I32, _RWW, True,
                _cia402(TARGET_POSITION), "rad", _INC, _SAT, default=0),
    ObjectEntry(HOME_OFFSET, 0, "Home offset", _I32, _RW, False, _cia402(HOME_OFFSET), "rad",
                _INC, _SAT, default=0),
    ObjectEntry(SOFTWARE_POSITION_LIMIT, 0, "Highest sub-index supported", _U8, _RO, False,
                _cia402(SOFTWARE_POSITION_LIMIT), default=2),
    ObjectEntry(SOFTWARE_POSITION_LIMIT, 1, "Min position limit", _I32, _RW, False,
                _cia402(SOFTWARE_POSITION_LIMIT), "rad", _INC, _SAT, default=-(2**31)),
    ObjectEntry(SOFTWARE_POSITION_LIMIT, 2, "Max position limit", _I32, _RW, False,
                _cia402(SOFTWARE_POSITION_LIMIT), "rad", _INC, _SAT, default=2**31 - 1),
    ObjectEntry(MAX_PROFILE_VELOCITY, 0, "Max profile velocity", _U32, _RW, False,
                _cia402(MAX_PROFILE_VELOCITY), "rad/s", _INC_S, _SAT, default=100 * _REV),
    ObjectEntry(PROFILE_VELOCITY, 0, "Profile velocity", _U32, _RW, False,
                _cia402(PROFILE_VELOCITY), "rad/s", _INC_S, _SAT, default=10 * _REV),
    ObjectEntry(PROFILE_ACCELERATION, 0, "Profile acceleration", _U32, _RW, False,
                _cia402(PROFILE_ACCELERATION), "rad/s^2", _INC_S2, _SAT, default=10 * _REV),
    ObjectEntry(PROFILE_DECELERATION, 0, "Profile deceleration", _U32, _RW, False,
                _cia402(PROFILE_DECELERATION), "rad/s^2", _INC_S2, _SAT, default=10 * _REV),
    ObjectEntry(QUICK_STOP_DECELERATION, 0, "Quick stop deceleration", _U32, _RW, False,
                _cia402(QUICK_STOP_DECELERATION), "rad/s^2", _INC_S2, _SAT, default=50 * _REV),
    ObjectEntry(MOTION_PROFILE_TYPE, 0, "Motion profile type", _I16, _RW, False,
                _cia402(MOTION_PROFILE_TYPE), default=0),  # linear ramp (trapezoidal)
    ObjectEntry(HOMING_METHOD, 0, "Homing method", _I8, _RW, False, _cia402(HOMING_METHOD),
                default=37),  # the present position is home
    ObjectEntry(HOMING_SPEEDS, 0, "Highest sub-index supported", _U8, _RO, False,
                _cia402(HOMING_SPEEDS), default=2),
    ObjectEntry(HOMING_SPEEDS, 1, "Speed during search for switch", _U32, _RW, False,
                _cia402(HOMING_SPEEDS), "rad/s", _INC_S, _SAT, default=5 * _REV),
    ObjectEntry(HOMING_SPEEDS, 2, "Speed during search for zero", _U32, _RW, False,
                _cia402(HOMING_SPEEDS), "rad/s", _INC_S, _SAT, default=_REV),
    ObjectEntry(HOMING_ACCELERATION, 0, "Homing acceleration", _U32, _RW, False,
                _cia402(HOMING_ACCELERATION), "rad/s^2", _INC_S2, _SAT, default=10 * _REV),
    ObjectEntry(VELOCITY_OFFSET, 0, "Velocity offset", _I32, _RWW, True,
                _cia402(VELOCITY_OFFSET), "rad/s", _INC_S, _SAT, default=0),
    ObjectEntry(TORQUE_OFFSET, 0, "Torque offset", _I16, _RWW, True, _cia402(TORQUE_OFFSET),
                "N m", Scaling.PERMILLE_RATED_TORQUE, _SAT, default=0),
    ObjectEntry(FOLLOWING_ERROR_ACTUAL, 0, "Following error actual value", _I32, _RO, True,
                _cia402(FOLLOWING_ERROR_ACTUAL), "rad", _INC, _SAT, default=0),
    ObjectEntry(MAX_SLIPPAGE, 0, "Max slippage", _I32, _RW, False, _cia402(MAX_SLIPPAGE),
                "rad/s", _INC_S, _SAT, default=2**31 - 1),  # the largest: off
)  # fmt: skip


# --- the variables ------------------------------------------------------------------------------

_PROCESS_OBJECTS: tuple[ObjectEntry, ...] = (
    # CiA 301 communication profile
    ObjectEntry(DEVICE_TYPE, 0, "Device type", _U32, _RO, False, _cia301(DEVICE_TYPE),
                default=0x00020192),  # CiA 402 (0x0192), servo drive (type 0x0002)
    ObjectEntry(ERROR_REGISTER, 0, "Error register", _U8, _RO, True, _cia301(ERROR_REGISTER),
                default=0x00),
    ObjectEntry(COB_ID_SYNC, 0, "COB-ID SYNC", _U32, _RO, False, _cia301(COB_ID_SYNC),
                default=0x80),
    ObjectEntry(CYCLE_PERIOD, 0, "Communication cycle period", _U32, _RW, False,
                _cia301(CYCLE_PERIOD), "s", Scaling.MICRO, default=0),
    ObjectEntry(COB_ID_EMCY, 0, "COB-ID EMCY", _U32, _RO, False, _cia301(COB_ID_EMCY),
                default=0x80, default_plus_node_id=True),
    ObjectEntry(HEARTBEAT_CONSUMER, 0, "Highest sub-index supported", _U8, _RO, False,
                _cia301(HEARTBEAT_CONSUMER), default=1),
    # bits 16-22 producer node id (127: the master), bits 0-15 time in ms (250)
    ObjectEntry(HEARTBEAT_CONSUMER, 1, "Consumer heartbeat time 1", _U32, _RW, False,
                _cia301(HEARTBEAT_CONSUMER), default=0x007F00FA),
    ObjectEntry(HEARTBEAT_PRODUCER, 0, "Producer heartbeat time", _U16, _RW, False,
                _cia301(HEARTBEAT_PRODUCER), "s", Scaling.MILLI, default=100),
    ObjectEntry(IDENTITY, 0, "Highest sub-index supported", _U8, _RO, False, _cia301(IDENTITY),
                default=4),
    ObjectEntry(IDENTITY, 1, "Vendor-ID", _U32, _RO, False, _cia301(IDENTITY), default=0),
    ObjectEntry(IDENTITY, 2, "Product code", _U32, _RO, False, _cia301(IDENTITY),
                default=0x4C434144),  # "LCAD"
    ObjectEntry(IDENTITY, 3, "Revision number", _U32, _RO, False, _cia301(IDENTITY),
                default=0x00010000),
    ObjectEntry(IDENTITY, 4, "Serial number", _U32, _RO, False, _cia301(IDENTITY), default=0),
    ObjectEntry(ERROR_BEHAVIOUR, 0, "Highest sub-index supported", _U8, _RO, False,
                _cia301(ERROR_BEHAVIOUR), default=1),
    # 0 = to PRE-OPERATIONAL, CiA 301's default: the bridge's ~/recover starts the node again
    # with the fault reset (docs/can.md, "Watchdogs and safety").
    ObjectEntry(ERROR_BEHAVIOUR, 1, "Communication error", _U8, _RW, False,
                _cia301(ERROR_BEHAVIOUR), default=ERROR_BEHAVIOUR_PRE_OPERATIONAL),
    # lca_hil: the drive chain of the lca_sim plant (the paper's state machine, eq. 8-10)
    ObjectEntry(DRIVE_STATE, 0, "Gear functional state", _U8, _RO, True, "lca_hil",
                default=0),  # index into the robot's drive-state names
    ObjectEntry(MOTION_STATE, 0, "Motion state", _I8, _RO, True, "lca_hil",
                default=0),  # -1 reverse, 0 stop, +1 direct
    ObjectEntry(ETA_M, 0, "Motor-side efficiency eta_m", _U16, _RO, True, "lca_hil", "",
                Scaling.PERMILLE, _SAT, default=EFFICIENCY_UNDEFINED,
                undefined=EFFICIENCY_UNDEFINED, signal="eta_m"),
    ObjectEntry(ETA_L, 0, "Load-side efficiency eta_l", _U16, _RO, True, "lca_hil", "",
                Scaling.PERMILLE, _SAT, default=EFFICIENCY_UNDEFINED,
                undefined=EFFICIENCY_UNDEFINED, signal="eta_l"),
    ObjectEntry(LOAD_TORQUE, 0, "Motor-side load torque", _I16, _RO, True, "lca_hil", "N m",
                Scaling.PERMILLE_RATED_TORQUE, _SAT, default=0, signal="load_torque_nm"),
    ObjectEntry(FRICTION_TORQUE, 0, "Motor-side friction torque", _I16, _RO, True, "lca_hil",
                "N m", Scaling.PERMILLE_RATED_TORQUE, _SAT, default=0,
                signal="friction_torque_nm"),
    ObjectEntry(VOLTAGE, 0, "Amplifier voltage", _I16, _RO, True, "lca_hil", "V",
                Scaling.CENTI, _SAT, default=0, signal="voltage_v"),
    # lca_hil: the virtual drive's own health. Its watchdogs do not count time its process
    # stood still (a monitor tick later than lca_sim.runtime.FREEZE_THRESHOLD_S) against the
    # master; these say how often that happened and the longest stall, so a master can know.
    ObjectEntry(PROCESS_STALLS, 0, "Process stalls", _U32, _RO, True, "lca_hil", default=0),
    ObjectEntry(LONGEST_STALL, 0, "Longest process stall", _U16, _RO, True, "lca_hil", "s",
                Scaling.MILLI, _SAT, default=0),
    # lca_hil: homing methods -1 / -2 (the mechanical stop, docs/can-modes.md "Homing"): home
    # is where |current| has stayed >= 0x2040 with the speed within 0x606F for 0x2041.
    ObjectEntry(HOMING_STOP_CURRENT, 0, "Homing stop current", _U16, _RW, False, "lca_hil",
                "A", Scaling.PERMILLE_RATED_CURRENT, default=800),
    ObjectEntry(HOMING_STOP_TIME, 0, "Homing stop time", _U16, _RW, False, "lca_hil", "s",
                Scaling.MILLI, default=100),
    # lca_hil: fault injection (docs/can.md "Fault injection"). Written by SDO (or by the rack's
    # `faults:` schedule); reads give what is active. Not PDO-mappable: a test harness sets it.
    ObjectEntry(FAULT_INJECTION, 0, "Highest sub-index supported", _U8, _RO, False, "lca_hil",
                default=FAULT_BUS_OFF),
    ObjectEntry(FAULT_INJECTION, FAULT_LOST_TPDOS, "Lost TPDOs", _U8, _RW, False, "lca_hil",
                default=0),  # bit n - 1: TPDO n
    ObjectEntry(FAULT_INJECTION, FAULT_HEARTBEAT_OFF, "Heartbeat off", _U8, _RW, False,
                "lca_hil", default=0),
    ObjectEntry(FAULT_INJECTION, FAULT_RAISE_EMCY, "Raise EMCY", _U16, _RW, False, "lca_hil",
                default=0),
    ObjectEntry(FAULT_INJECTION, FAULT_DRIVE_FAULT, "Drive fault", _U16, _RW, False, "lca_hil",
                default=0),
    ObjectEntry(FAULT_INJECTION, FAULT_BUS_OFF, "Bus-off", _U16, _RW, False, "lca_hil", "s",
                Scaling.MILLI, Overflow.RAISE, default=0),
    # CiA 402-2 drive profile
    ObjectEntry(ABORT_CONNECTION_OPTION, 0, "Abort connection option code", _I16, _RW, False,
                _cia402(ABORT_CONNECTION_OPTION), default=1),
    ObjectEntry(ERROR_CODE, 0, "Error code", _U16, _RO, True, _cia402(ERROR_CODE), default=0),
    ObjectEntry(CONTROLWORD, 0, "Controlword", _U16, _RWW, True, _cia402(CONTROLWORD),
                default=0),
    ObjectEntry(STATUSWORD, 0, "Statusword", _U16, _RO, True, _cia402(STATUSWORD), default=0),
    ObjectEntry(QUICK_STOP_OPTION, 0, "Quick stop option code", _I16, _RW, False,
                _cia402(QUICK_STOP_OPTION), default=2),
    ObjectEntry(MODES_OF_OPERATION, 0, "Modes of operation", _I8, _RWW, True,
                _cia402(MODES_OF_OPERATION), default=10),
    ObjectEntry(MODES_OF_OPERATION_DISPLAY, 0, "Modes of operation display", _I8, _RO, True,
                _cia402(MODES_OF_OPERATION_DISPLAY), default=10),
    ObjectEntry(POSITION_ACTUAL, 0, "Position actual value", _I32, _RO, True,
                _cia402(POSITION_ACTUAL), "rad", Scaling.INCREMENTS, Overflow.WRAP, default=0),
    ObjectEntry(VELOCITY_ACTUAL, 0, "Velocity actual value", _I32, _RO, True,
                _cia402(VELOCITY_ACTUAL), "rad/s", Scaling.INCREMENTS_PER_S, _SAT, default=0),
    ObjectEntry(TARGET_TORQUE, 0, "Target torque", _I16, _RWW, True, _cia402(TARGET_TORQUE),
                "N m", Scaling.PERMILLE_RATED_TORQUE, _SAT, default=0),
    ObjectEntry(TARGET_VELOCITY, 0, "Target velocity", _I32, _RWW, True,
                _cia402(TARGET_VELOCITY), "rad/s", Scaling.INCREMENTS_PER_S, _SAT, default=0),
    ObjectEntry(MAX_TORQUE, 0, "Max torque", _U16, _RWW, True, _cia402(MAX_TORQUE), "N m",
                Scaling.PERMILLE_RATED_TORQUE, _SAT, default=2000),
    ObjectEntry(MOTOR_RATED_CURRENT, 0, "Motor rated current", _U32, _RO, False,
                _cia402(MOTOR_RATED_CURRENT), "A", Scaling.MILLI, default=10000),
    ObjectEntry(MOTOR_RATED_TORQUE, 0, "Motor rated torque", _U32, _RO, False,
                _cia402(MOTOR_RATED_TORQUE), "N m", Scaling.MILLI, default=1200),
    ObjectEntry(TORQUE_ACTUAL, 0, "Torque actual value", _I16, _RO, True,
                _cia402(TORQUE_ACTUAL), "N m", Scaling.PERMILLE_RATED_TORQUE, _SAT, default=0),
    ObjectEntry(CURRENT_ACTUAL, 0, "Current actual value", _I16, _RO, True,
                _cia402(CURRENT_ACTUAL), "A", Scaling.PERMILLE_RATED_CURRENT, _SAT, default=0),
    ObjectEntry(POSITION_ENCODER_RESOLUTION, 0, "Highest sub-index supported", _U8, _RO, False,
                _cia402(POSITION_ENCODER_RESOLUTION), default=2),
    ObjectEntry(POSITION_ENCODER_RESOLUTION, 1, "Encoder increments", _U32, _RO, False,
                _cia402(POSITION_ENCODER_RESOLUTION), default=65536),
    ObjectEntry(POSITION_ENCODER_RESOLUTION, 2, "Motor revolutions", _U32, _RO, False,
                _cia402(POSITION_ENCODER_RESOLUTION), default=1),
    # 0x000003A5: bits 0, 2, 5, 7, 8, 9 = PP, PV, HM, CSP, CSV, CST (bit n - 1 for mode n);
    # the tests hold this, the EDS and device.SUPPORTED_MODES together.
    ObjectEntry(SUPPORTED_DRIVE_MODES, 0, "Supported drive modes", _U32, _RO, False,
                _cia402(SUPPORTED_DRIVE_MODES), default=0x000003A5),
    *_MODE_OBJECTS,
)  # fmt: skip


def _pdo_objects(pdo: PdoDefault) -> tuple[ObjectEntry, ...]:
    """The communication and mapping variables of one PDO (CiA 301 0x1400-0x1BFF)."""
    kind = "RPDO" if pdo.receive else "TPDO"
    com = (RPDO_COMMUNICATION if pdo.receive else TPDO_COMMUNICATION) + pdo.number - 1
    mapping = (RPDO_MAPPING if pdo.receive else TPDO_MAPPING) + pdo.number - 1
    com_ref, map_ref = _cia301(com), _cia301(mapping)
    invalid = 0 if pdo.valid else PDO_COB_ID_INVALID
    # CiA 301 0x1800-0x19FF sub 1 bit 30: 1 = no RTR allowed on this PDO. These drives do not
    # answer remote frames, so every TPDO says so (bit 30 is reserved in an RPDO's COB-ID).
    no_rtr = 0 if pdo.receive else PDO_COB_ID_NO_RTR
    # Sub 3 (inhibit time) is a TPDO's only; sub 5 is the TPDO event timer or RPDO deadline.
    subs = (0, 1, 2, 5) if pdo.receive else (0, 1, 2, 3, 5)
    entries = [
        ObjectEntry(com, 0, "Highest sub-index supported", _U8, _RO, False, com_ref,
                    default=5),
        ObjectEntry(com, 1, f"COB-ID used by {kind}", _U32, _RW, False, com_ref,
                    default=invalid | no_rtr | pdo.cob_id, default_plus_node_id=True),
        ObjectEntry(com, 2, "Transmission type", _U8, _RW, False, com_ref,
                    default=pdo.transmission_type),
    ]  # fmt: skip
    if 3 in subs:
        entries.append(
            ObjectEntry(com, 3, "Inhibit time", _U16, _RW, False, com_ref, "s",
                        Scaling.HUNDRED_MICRO, default=0)
        )  # fmt: skip
    entries.append(
        ObjectEntry(com, 5, "Event timer", _U16, _RW, False, com_ref, "s", Scaling.MILLI,
                    default=pdo.event_timer_ms)
    )  # fmt: skip
    mapped = [_VARIABLES[(index, 0)].mapping_entry for index in pdo.objects]
    mapped += [0] * (PDO_MAPPING_SLOTS - len(mapped))
    entries.append(
        ObjectEntry(mapping, 0, "Number of mapped objects", _U8, _RW, False, map_ref,
                    default=len(pdo.objects))
    )  # fmt: skip
    entries += [
        ObjectEntry(mapping, k, f"Mapping entry {k}", _U32, _RW, False, map_ref, default=value)
        for k, value in enumerate(mapped, start=1)
    ]
    return tuple(entries)


_VARIABLES: Mapping[tuple[int, int], ObjectEntry] = {e.key: e for e in _PROCESS_OBJECTS}

# Every variable, in index order: the one declaration the EDS is checked against.
OBJECTS: tuple[ObjectEntry, ...] = tuple(
    sorted(
        (*_PROCESS_OBJECTS, *(e for pdo in DEFAULT_PDOS for e in _pdo_objects(pdo))),
        key=lambda e: e.key,
    )
)
BY_KEY: Mapping[tuple[int, int], ObjectEntry] = MappingProxyType({e.key: e for e in OBJECTS})
if len(BY_KEY) != len(OBJECTS):  # pragma: no cover - a table edit that repeats a key
    raise RuntimeError("lca_sim.cia402.objects declares an object twice")

# The objects backed by an lca_sim signal, by signal name (the virtual drive's drive chain).
SIGNAL_OBJECTS: Mapping[str, ObjectEntry] = MappingProxyType(
    {e.signal: e for e in OBJECTS if e.signal}
)


def entry(index: int, subindex: int = 0) -> ObjectEntry:
    """The declaration of one variable.

    Raises:
        UnknownObjectError: the table has no such variable.
    """
    try:
        return BY_KEY[(index, subindex)]
    except KeyError:
        raise UnknownObjectError(index, subindex) from None
