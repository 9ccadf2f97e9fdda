"""What the rack keeps per drive: its PDOs, its injected faults, its objects; and its counters.

Plain values that the rack's parts share; the behaviour is in the parts (docs/can.md, "The
virtual drive rack").
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from operator import call
from typing import TYPE_CHECKING

import canopen
from canopen import SdoAbortedError
from canopen.objectdictionary import ObjectDictionary, ODVariable

from lca_sim.cia402 import cia301, codec
from lca_sim.cia402.codec import Codec, DriveUnits
from lca_sim.cia402.device import Cia402AxisState
from lca_sim.config.rack import AxisConfig

if TYPE_CHECKING:  # rack_modes reads a Drive: only the type goes this way
    from lca_sim.canbus.rack_modes import AxisModes

# canopen's names of the NMT states (`NmtSlave.state`).
NMT_OPERATIONAL = "OPERATIONAL"
NMT_PRE_OPERATIONAL = "PRE-OPERATIONAL"
NMT_STOPPED = "STOPPED"


@dataclass
class RackCounters:
    """What the rack received, sent, refused and detected (for diagnostics and tests)."""

    syncs: int = 0
    syncs_too_fast: int = 0  # SYNCs beyond 0x1006's rate: not advancing the plant (EMCY 0x8100)
    rpdos_received: int = 0
    rpdos_applied: int = 0
    pdos_ignored_not_operational: int = 0
    sdo_ignored_stopped: int = 0  # SDO requests to a node in NMT STOPPED (not answered)
    rpdo_values_rejected: int = 0
    tpdos_sent: int = 0
    bad_frames: int = 0
    extended_frames: int = 0  # 29-bit identifiers: not for these 11-bit nodes, ignored
    fd_frames: int = 0  # CAN FD frames: ignored likewise
    remote_frames: int = 0  # RTR frames: no object of these nodes answers one
    error_frames: int = 0
    emcy_sent: int = 0
    heartbeat_losses: int = 0
    rpdo_timeouts: int = 0
    sync_losses: int = 0
    send_errors: int = 0
    bus_errors: int = 0  # exceptions of the bus layer's receive (python-can Notifier)
    handler_errors: int = 0
    process_freezes: int = 0  # stalls of this process (also 0x2020), each discounted ...
    stalls_beyond_discount: int = 0  # ... up to max_stall_discount_s; these longer (EMCY 0xFF02)
    tpdos_lost: int = 0  # TPDOs not sent: fault injection 0x2030 sub 1
    frames_dropped_bus_off: int = 0  # frames a node in (injected) bus-off did not send

    def as_dict(self) -> dict[str, int]:
        """The counters by name."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


@dataclass
class Pdo:
    """One PDO of one node: its communication and mapping parameters, and its traffic state."""

    number: int  # 1-based
    receive: bool
    cob_id: int
    valid: bool
    transmission_type: int
    inhibit_100us: int
    event_timer_ms: int
    slots: list[int]  # the raw mapping entries, sub 1..8
    count: int  # mapping sub 0
    objects: list[ODVariable] = field(default_factory=list)
    frame: struct.Struct = field(default_factory=lambda: struct.Struct("<"))  # the whole frame
    # TPDO: the current raw value of each mapped object, read when the frame is sent.
    getters: list[Callable[[], int]] = field(default_factory=list)
    encode: Callable[[], bytes] = field(default=bytes)  # the TPDO's frame now (`map`)
    latched: bytes | None = None  # a synchronous RPDO waiting for the next SYNC
    last_rx_s: float | None = None  # arms the RPDO deadline
    last_data: bytes | None = None  # the TPDO last sent
    last_sent_s: float = -math.inf
    sync_count: int = 0
    length_error: int = 0  # RPDO: the EMCY code of the current run of wrong-length frames

    def map(self, objects: list[ODVariable], getters: list[Callable[[], int]]) -> None:
        """Map `objects`, and pack and unpack the frame in one step from now on."""
        self.objects = objects
        self.frame = frame_codec(objects)
        self.getters = getters
        self.encode = frame_encoder(self.frame, getters)


def frame_encoder(
    frame: struct.Struct, getters: Sequence[Callable[[], int]]
) -> Callable[[], bytes]:
    """A TPDO's frame of its objects' current values, built once per mapping.

    A TPDO is encoded when it is due, an event one at every SYNC outside its inhibit time (to
    see a change): the getters are called from C (`operator.call`) into the mapping's struct.
    """
    pack, calls = frame.pack, tuple(getters)

    def encode() -> bytes:
        return pack(*map(call, calls))

    return encode


def frame_codec(objects: Sequence[ODVariable]) -> struct.Struct:
    """One little-endian struct for a PDO's mapped objects (mappable objects are numbers).

    Packing a whole frame at once instead of object by object (`ODVariable.encode_raw`) is
    most of what keeps the rack's SYNC handling inside a 2 ms cycle (bench/can_cycle.py).
    """
    return struct.Struct("<" + "".join(number_format(obj) for obj in objects))


def number_format(obj: ODVariable) -> str:
    """The struct format of a number object; a string or domain cannot be mapped.

    Neither can a 24-, 40-, 48- or 56-bit number: canopen packs those with the next wider
    format, which would code the whole frame at the wrong length.
    """
    packer = None if obj.data_type is None else ODVariable.STRUCT_TYPES.get(obj.data_type)
    if packer is None or packer.size != struct.calcsize(packer.format):
        raise SdoAbortedError(cia301.ABORT_NOT_MAPPABLE)
    return packer.format.lstrip("<")


@dataclass
class DriveFaults:
    """The faults injected into one drive (object 0x2030; docs/can.md "Fault injection")."""

    lost_tpdos: int = 0  # bit n - 1: TPDO n is not sent
    heartbeat_off: bool = False
    emcy_code: int = 0  # the EMCY raised last (0: none)
    drive_fault: int = 0  # a drive fault's code while its cause lasts (0: none)
    bus_off: bool = False
    bus_off_ms: int = 0  # 0x2030 sub 5 as written (0 while the schedule or the API set it)
    bus_off_until_step: int | None = None  # plant step at which a timed bus-off ends

    def active(self) -> dict[str, int]:
        """The faults that are on, by kind (`FAULT_KINDS`), with their values."""
        values = {
            "lost_tpdo": self.lost_tpdos,
            "heartbeat_off": int(self.heartbeat_off),
            "emcy": self.emcy_code,
            "drive_fault": self.drive_fault,
            "bus_off": int(self.bus_off),
        }
        return {kind: value for kind, value in values.items() if value}


@dataclass(frozen=True, slots=True)
class FaultEvent:
    """A fault going on (value != 0) or off (0) in one drive, at the rack's plant time."""

    time_s: float
    joint: str
    kind: str
    value: int
    source: str  # "schedule", "sdo" or "api"


@dataclass
class Drive:
    """One drive: its node, its object values and its CiA 402 state."""

    config: AxisConfig
    plant_index: int  # column in the simulator's arrays
    joint_index: int  # position in the CommandedPlant command array
    gear_ratio: float
    torque_constant_nm_per_a: float
    node: canopen.LocalNode
    od: ObjectDictionary
    units: DriveUnits  # what 0x6075, 0x6076 and 0x608F say (read-only objects)
    defaults: dict[tuple[int, int], int]
    values: dict[tuple[int, int], int] = field(default_factory=dict)
    # Objects whose value is computed when read, from the CiA 402 state or the plant.
    live: dict[tuple[int, int], Callable[[], int]] = field(default_factory=dict)
    drive: Cia402AxisState = field(default_factory=Cia402AxisState)
    nmt: str = NMT_PRE_OPERATIONAL
    rpdos: list[Pdo] = field(default_factory=list)
    tpdos: list[Pdo] = field(default_factory=list)
    # The valid TPDOs a SYNC sends (types 0-240) and the valid event-driven ones (254, 255),
    # in number order; kept by `PdoEngine` at each change of a TPDO's COB-ID or type, so the
    # SYNC and the monitor walk only these, not every TPDO of the drive.
    sync_tpdos: list[Pdo] = field(default_factory=list)
    event_tpdos: list[Pdo] = field(default_factory=list)
    heartbeat_last_rx_s: float | None = None
    sync_armed_s: float = -math.inf
    sync_loss_reported: bool = False
    torque: Codec = field(init=False)  # N m <-> per mille of 0x6076 (0x6071, 0x6077)
    current: Codec = field(init=False)  # A <-> per mille of 0x6075 (0x6078)
    velocity: Codec = field(init=False)  # motor rad/s <-> increments/s (0x606C, 0x60FF)
    # The drive's loops and loop modes (CSV, PP, PV, HM, CSP), set when the drive is built.
    modes: AxisModes = field(init=False)
    faults: DriveFaults = field(default_factory=DriveFaults)

    def __post_init__(self) -> None:
        self.torque = codec.torque(self.units)
        self.current = codec.current(self.units)
        self.velocity = codec.velocity(self.units)

    def value(self, index: int, subindex: int = 0) -> int:
        """A stored (non-dynamic) object value."""
        return self.values[(index, subindex)]

    def getter(self, index: int, subindex: int) -> Callable[[], int]:
        """A callable returning the object's current value (live, or stored; 0 if unset)."""
        live = self.live.get((index, subindex))
        if live is not None:
            return live
        values, key = self.values, (index, subindex)

        def stored() -> int:
            return values.get(key, 0)

        return stored
