"""The CAN bridge's drives: the bus, the CANopen master and, on `virtual`, the rack (docs/can.md).

`CanDrives` owns what the bridge node's configure opens and its cleanup closes: the python-can
bus, the canopen network, `Cia402Master` (with its `LockstepLoop` in lockstep) and, with
`interface: virtual`, the virtual drive rack on a linked in-process bus. `bridge_params` builds
the master's `BridgeParams` from the node's parameters field by field of `BridgeParams`, so a
field added there cannot be forgotten here; `CycleValues` turns a SYNC cycle into the plant
contract's values.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import fields, replace
from operator import attrgetter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import canopen

from lca_control import contract as pc
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.lockstep import CycleClock, LockstepLoop
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_frames import master_network
from lca_sim.canbus.master_params import BridgeError, BridgeParams
from lca_sim.canbus.master_state import Snapshot
from lca_sim.cia402.device import PowerState
from lca_sim.config.can_bridge_params import CAN_BRIDGE_PARAMETERS, CanBridgeNodeParams
from lca_sim.errors import ConfigError, LcaHilError
from lca_sim.model.params import RobotParams
from lca_sim.ros.contract_cdr import DriveChainRows
from lca_sim.runtime import settle_heap

if TYPE_CHECKING:
    from lca_sim.canbus.virtual_rack import VirtualDriveRack

# How long shutdown and error processing wait for the drives to leave OPERATION ENABLED: a
# disable is one cycle, its statusword the next slow TPDO (50 Hz by default).
TORQUE_FREE_TIMEOUT_S = 0.5
# BridgeParams fields the node has no parameter for: the master's own default holds.
# heartbeat_loss_periods is the master's CiA 301 consumer margin, not a user's choice.
MASTER_DEFAULTS = frozenset({"heartbeat_loss_periods"})
# BridgeParams fields named otherwise among the node's parameters: field -> parameter.
RENAMED = {"bitrate_bit_s": "bitrate"}
# BridgeParams fields that come from the robot config (`robot_values`).
FROM_ROBOT = frozenset({"torque_constants_nm_per_a", "gear_ratios", "drive_state_names"})
# The master's fields a live parameter set changes: the live parameters it has.
LIVE_FIELDS = tuple(
    f.name
    for f in fields(BridgeParams)
    if f.name in CAN_BRIDGE_PARAMETERS and f.name not in CAN_BRIDGE_PARAMETERS.read_only
)


class UnmappedFieldError(LcaHilError):
    """A BridgeParams field that no node parameter, robot value or master default fills."""


def bridge_params(p: CanBridgeNodeParams, robot_values: Mapping[str, Any]) -> BridgeParams:
    """The master's params: each `BridgeParams` field from the node parameter of its name.

    Args:
        p: the node's parameters.
        robot_values: the `FROM_ROBOT` fields (per joint, from the robot config).

    Raises:
        UnmappedFieldError: a field with no source (a new one in `BridgeParams`).
    """
    values: dict[str, Any] = {}
    for f in fields(BridgeParams):
        if f.name in FROM_ROBOT:
            values[f.name] = robot_values[f.name]
        elif f.name in RENAMED:
            values[f.name] = getattr(p, RENAMED[f.name])
        elif hasattr(p, f.name):
            values[f.name] = getattr(p, f.name)
        elif f.name not in MASTER_DEFAULTS:
            raise UnmappedFieldError(
                f"BridgeParams.{f.name} has no source: add a node parameter of that name, or "
                "name it in RENAMED, FROM_ROBOT or MASTER_DEFAULTS (lca_sim.ros.can_drives)"
            )
    values["bitrate_bit_s"] = float(values["bitrate_bit_s"])
    return BridgeParams(**values)


def live_bridge_params(current: BridgeParams, new: CanBridgeNodeParams) -> BridgeParams:
    """The master's params with the live node parameters of `new` (`LIVE_FIELDS`)."""
    return replace(current, **{name: getattr(new, name) for name in LIVE_FIELDS})


def open_bus(interface: str, channel: str, bitrate: int) -> can.BusABC:
    """Open a python-can bus, or raise ConfigError with one clear line (no traceback).

    Only the bus differs between a real drive (`socketcan`, `can0`) and the virtual rack
    (`virtual`): everything above it is the same code.
    """
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        hint = (
            " (is the interface up? `ip link show` lists them; this machine may have no "
            "SocketCAN at all: use interface virtual)"
            if interface == "socketcan"
            else ""
        )
        raise ConfigError(
            "parameters", "interface", f"cannot open {interface} channel {channel!r}: {exc}{hint}"
        ) from exc


# What `CycleValues` reads of each drive, in one C call per drive and cycle.
_MOTION = attrgetter(
    "position", "velocity", "motor_position_rad", "motor_velocity_rad_s", "current_a"
)
_CODES = attrgetter("motion_state", "drive_state")
# The DRIVE_NUMBER_KEYS in order, each the AxisState field of its name, except the motor
# torque: read as the current, times k_t.
_TORQUE_AT = pc.DRIVE_NUMBER_KEYS.index("motor_torque_nm")
_NUMBERS = attrgetter(
    *("current_a" if key == "motor_torque_nm" else key for key in pc.DRIVE_NUMBER_KEYS)
)


class CycleValues:
    """One SYNC cycle of the drives as the plant contract's values (`publish_values`).

    effort = k_t * i * N (joint side), motor torque = k_t * i (motor side, k_t from the robot
    config). A field the drives' TPDOs do not fill (`decoded`: `Cia402Master.decoded_fields`)
    is unknown: the efficiencies, torques and voltage stay NaN (`AxisState`'s default), the drive
    state code becomes NaN, and the motion state is NaN unless it is mapped and has been
    reported (the drive-state code is -1 until the first drive-chain TPDO, and the motion code,
    0 by default, would read as `stop` before it).

    Plain floats, no arrays: built on the master's cycle thread every SYNC, where a snapshot's
    arrays cost about a third of what publishing them does (docs/can-transport.md). The
    drive-chain values are worked out only when asked for (someone subscribes to them).

    Args:
        snap: the cycle's states from the master.
        torque_constants_nm_per_a, gear_ratios: per joint, as Python floats.
        state_names: the robot's drive-state names.
        decoded: the AxisState fields every drive's TPDOs fill.
    """

    __slots__ = ("_axes", "_decoded", "_k_t", "_state_names", "joint", "motor", "stamp_s")

    def __init__(
        self,
        snap: Snapshot,
        torque_constants_nm_per_a: tuple[float, ...],
        gear_ratios: tuple[float, ...],
        state_names: tuple[str, ...],
        decoded: frozenset[str],
    ) -> None:
        position, velocity, motor_position, motor_velocity, current = zip(
            *map(_MOTION, snap.axes), strict=True
        )
        torque = [i * k for i, k in zip(current, torque_constants_nm_per_a, strict=True)]
        self.stamp_s = snap.sync_wall_s
        self.joint = (position, velocity, [t * n for t, n in zip(torque, gear_ratios, strict=True)])
        self.motor = (motor_position, motor_velocity, current)
        self._axes = snap.axes
        self._k_t = torque_constants_nm_per_a
        self._state_names = state_names
        self._decoded = decoded

    def drive_chain(self) -> DriveChainRows:
        """The cycle's drive_chain_states values (the NaN rules of the class docstring)."""
        decoded = self._decoded
        codes = list(map(_CODES, self._axes))
        drive: list[float] = (
            [float(d) for _, d in codes] if "drive_state" in decoded else [math.nan] * len(codes)
        )
        if "motion_state" not in decoded:
            motion = [math.nan] * len(codes)
        elif "drive_state" in decoded:
            motion = [float(m) if d >= 0 else math.nan for m, d in codes]
        else:
            motion = [float(m) for m, _ in codes]
        numbers = []
        for row, k_t in zip(map(_NUMBERS, self._axes), self._k_t, strict=True):
            values = list(row)
            values[_TORQUE_AT] *= k_t
            numbers.append(values)
        return DriveChainRows(motion, drive, numbers, self._state_names)


def drives_in_process(p: CanBridgeNodeParams) -> bool:
    """`interface: virtual`: the bridge opens a linked bus and runs the rack on it, here.

    A stall of this process then stalls the drives too, so it trips no deadline of theirs.
    """
    return p.interface == "virtual"


class CanDrives:
    """The bus, network, master and rack of one configured bridge; None/empty while closed.

    Args:
        robot: the robot config (k_t, gear ratios, drive-state names).
        joints: the bridge's joints (read-only), in command order.
        eds: the drives' EDS.
        on_state: called with each complete SYNC cycle (in the notifier thread).
        before_cycle: real time: called by the cycle thread before each SYNC's RPDOs
            (`Cia402Master`'s `before_cycle`); lockstep runs on commands and ignores it.
    """

    def __init__(
        self,
        robot: RobotParams,
        joints: tuple[str, ...],
        eds: Path,
        on_state: Callable[[Snapshot], None],
        before_cycle: Callable[[], None] | None = None,
    ) -> None:
        axes = {a.name: a for a in robot.axes}
        self.joints = joints
        # Python floats: the contract's numbers are their repr (a NumPy scalar's differs).
        self.torque_constants = tuple(float(axes[j].motor.torque_constant_nm_per_a) for j in joints)
        self.gear_ratios = tuple(float(axes[j].gear_ratio) for j in joints)
        self.state_names = robot.state_machine.state_names
        self._eds = eds
        self._on_state = on_state
        self._before_cycle = before_cycle
        self.master: Cia402Master | None = None
        self.network: canopen.Network | None = None
        self.rack: VirtualDriveRack | None = None
        # Lockstep: the loop that sends one SYNC per command; kept after a close, replaced by
        # the next open.
        self.loop: LockstepLoop | None = None
        self.configured = False  # the last init() succeeded
        self.init_error = ""  # why the last init() failed
        self._bus: can.BusABC | None = None
        self._rack_bus: can.BusABC | None = None
        self._lockstep = False
        self._init_lock = threading.Lock()

    def robot_values(self) -> dict[str, Any]:
        """The `FROM_ROBOT` fields of `BridgeParams`."""
        return {
            "torque_constants_nm_per_a": self.torque_constants,
            "gear_ratios": self.gear_ratios,
            "drive_state_names": self.state_names,
        }

    def cycle_values(self, snap: Snapshot, decoded: frozenset[str]) -> CycleValues:
        """A SYNC cycle as the contract's values (`CycleValues`)."""
        return CycleValues(snap, self.torque_constants, self.gear_ratios, self.state_names, decoded)

    def open(self, p: CanBridgeNodeParams) -> None:
        """Open the bus (and start the rack on `virtual`), then the network and the master."""
        virtual = drives_in_process(p)
        self._lockstep = p.timing_mode == "lockstep"
        bus = (
            LinkedVirtualBus(channel=p.channel)
            if virtual
            else open_bus(p.interface, p.channel, p.bitrate)
        )
        self._bus = bus
        if virtual:
            self._start_rack(p)
        self.network = master_network(bus)
        params = bridge_params(p, self.robot_values())
        if not self._lockstep:
            self.master = Cia402Master(
                self.network,
                params,
                self._eds,
                on_state=self._on_state,
                before_cycle=self._before_cycle,
                drives_in_process=virtual,
            )
            return
        clock = CycleClock(1.0 / p.cycle_hz)
        master = Cia402Master(
            self.network,
            params,
            self._eds,
            on_state=self._on_state,
            clock=clock.now,
            stamp_clock=clock.now,
            drives_in_process=virtual,
        )
        self.master = master
        self.loop = LockstepLoop(clock, master.cycle, p.lockstep_resend_s)

    def _start_rack(self, p: CanBridgeNodeParams) -> None:
        from lca_sim.canbus.virtual_rack import VirtualDriveRack  # noqa: PLC0415
        from lca_sim.config.rack import load_rack_config  # noqa: PLC0415

        config = load_rack_config(Path(p.rack_config) if p.rack_config else None)
        config = replace(config, timing_mode=p.timing_mode)  # one clock for the whole loop
        self._rack_bus = LinkedVirtualBus(channel=p.channel)
        self.rack = VirtualDriveRack(self._rack_bus, config)
        self.rack.start()

    def init(self) -> str:
        """Configure and start the drives, then the cycle; '' or the error."""
        master = self.master
        if master is None:
            raise RuntimeError("the CANopen master is not running (node unconfigured)")
        with self._init_lock:
            master.stop()
            try:
                master.init()
            except BridgeError as exc:
                self.configured, self.init_error = False, str(exc)
                return str(exc)
            settle_heap()  # before the cycle runs: a full collection would stall it
            if not self._lockstep:
                master.start()  # lockstep: the loop sends the SYNCs (the node's tick)
            self.configured, self.init_error = True, ""
            return ""

    def torque_free(self) -> list[str]:
        """Disable every drive and wait, bounded, until none is in OPERATION ENABLED.

        CiA 402-2 transition 5 (disable operation, controlword 0x0007), then 6 (shutdown): no
        torque. Returns the joints still enabled after TORQUE_FREE_TIMEOUT_S: a drive that does
        not answer is left to its own watchdogs (heartbeat consumer, RPDO deadline: its 0x6007
        reaction once the cycle stops).
        """
        master = self.master
        if master is None or not self.configured:
            return []
        master.enable(False)
        # Judged on statuswords sent after the disable: the slow TPDO that carries them goes
        # every `slow_tpdo_every`-th SYNC, so a state read before that may predate it.
        fresh_from = master.counters.cycles + master.params.slow_tpdo_every + 2
        deadline = time.monotonic() + TORQUE_FREE_TIMEOUT_S
        while True:
            enabled = [
                j
                for j in self.joints
                if master.axis_state(j).power_state is PowerState.OPERATION_ENABLED
            ]
            fresh = master.counters.cycles >= fresh_from
            if (fresh and not enabled) or time.monotonic() > deadline:
                return enabled
            if self.loop is not None and self.loop.started:
                self.loop.sync_now()  # lockstep: no cycle runs unless sent
            time.sleep(0.005)

    def close(self) -> None:
        """Stop the cycle (the drives' watchdogs then react), close the bus, stop the rack."""
        self.configured = False
        master, self.master = self.master, None
        network, self.network = self.network, None
        bus, self._bus = self._bus, None
        rack, self.rack = self.rack, None
        rack_bus, self._rack_bus = self._rack_bus, None
        try:
            if master is not None:
                master.stop()
            if network is not None and network.bus is not None:
                network.disconnect()  # its notifier, then the bus
            elif bus is not None:
                _close_bus(bus)
        finally:
            if rack is not None:
                rack.stop()
            if rack_bus is not None:
                _close_bus(rack_bus)


def _close_bus(bus: can.BusABC) -> None:
    with contextlib.suppress(can.CanError):
        bus.shutdown()
