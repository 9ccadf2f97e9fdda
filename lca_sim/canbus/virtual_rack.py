"""The virtual drive rack: one CiA 402 CANopen node per axis over one coupled lca_sim plant (shell).

Four `canopen.LocalNode`s (SDO server, NMT slave, EMCY producer) on one python-can bus, all
backed by ONE `CommandedPlant(interface="current")` of one `Simulator`, so the axes stay coupled
through the gantry model. The drive logic is `lca_sim.cia402.device`, the objects
`lca_sim.cia402.objects`, their scaling `lca_sim.cia402.codec`. docs/can.md, "The virtual drive
rack", is the contract a master relies on (boot, PDO timing on SYNC, modes 0x6060 = 10, 9 and
0, watchdogs, fault injection, remapping).

    rack = VirtualDriveRack(bus, load_rack_config(None))   # lca_sim.config.rack
    with rack: rack.power_state("pivot")                     # start() ... stop()

Its parts: `rack_state` (per-drive values), `rack_network` (the bus side), `rack_pdo` (PDOs),
`rack_watchdog` (deadlines, SYNC rate, freeze discount), `rack_faults` (fault injection). The
console script `lca-virtual-drive` is `lca_sim.cli.virtual_drive`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from types import TracebackType
from typing import Any, cast

import can
import canopen
from can.interfaces.virtual import VirtualBus
from canopen import SdoAbortedError
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from lca_control.pi import PIController, PIParams
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.rack_faults import RackFaults
from lca_sim.canbus.rack_network import RackListener, RackNetwork
from lca_sim.canbus.rack_pdo import PdoEngine
from lca_sim.canbus.rack_state import (
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_STOPPED,
    Drive,
    FaultEvent,
    Pdo,
    RackCounters,
)
from lca_sim.canbus.rack_watchdog import RackWatchdogs
from lca_sim.canbus.remote import batched_sends
from lca_sim.cia402 import cia301, codec, sync_rate
from lca_sim.cia402 import device as cia402
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import CodecError, DriveUnits
from lca_sim.cia402.device import Cia402AxisState, PowerState
from lca_sim.config.loader import load_robot
from lca_sim.config.rack import (
    FAULT_KINDS,
    FAULT_VALUE_RANGE,
    LOCKSTEP,
    AxisConfig,
    RackConfig,
    eds_path,
)
from lca_sim.errors import ConfigError, UnknownNameError
from lca_sim.model.commanded_plant import CURRENT, CommandedPlant
from lca_sim.model.params import RobotParams
from lca_sim.model.simulator import SIGNAL_NAMES, InputError, PlantState, Simulator
from lca_sim.runtime import (
    settle_heap,
    yield_gil,
)

logger = logging.getLogger(__name__)

MONITOR_PERIOD_S = 0.005  # watchdogs and event-driven TPDOs are checked this often
MAX_WALL_ADVANCE_S = 0.05  # 0x1006 = 0: the plant follows the wall time, at most this per SYNC
NOTIFIER_TIMEOUT_S = 0.05  # the receive thread's poll: bounds how long stop() waits for it
# Option codes: the values a write may set (others are refused with ABORT_VALUE_RANGE).
_OPTION_VALUES: dict[tuple[int, int], frozenset[int]] = {
    (od.ABORT_CONNECTION_OPTION, 0): cia402.ABORT_OPTIONS,
    (od.QUICK_STOP_OPTION, 0): cia402.QUICK_STOP_OPTIONS,
    (od.ERROR_BEHAVIOUR, 1): od.ERROR_BEHAVIOURS,
}


class VirtualDriveRack:
    """Virtual CiA 402 drives, one CANopen node per configured axis, over one plant.

    Args:
        bus: the python-can bus to serve (not shut down by `stop`).
        config: the validated rack config.
        robot: the robot's parameters; loaded from `config.robot` when None.

    Raises:
        ConfigError: an axis the robot does not have, or an initial position outside its end
            stops.
    """

    def __init__(
        self, bus: can.BusABC, config: RackConfig, robot: RobotParams | None = None
    ) -> None:
        self.config = config
        robot = load_robot(config.robot) if robot is None else robot
        self._sim = Simulator(
            robot, dt_s=config.dt_s, rigid_body_update_steps=config.rigid_body_update_steps
        )
        for axis_config in config.axes:
            if axis_config.name not in self._sim.axis_names:
                raise ConfigError(
                    config.source,
                    f"axes.{axis_config.name}",
                    f"the robot has no such axis (axes: {', '.join(self._sim.axis_names)})",
                )
        try:
            self._sim.reset({a.name: a.initial_position for a in config.axes})
        except InputError as exc:
            raise ConfigError(config.source, "axes", f"expected a valid pose ({exc})") from exc
        k_t = {
            a.name: robot.axes[self._sim.axis_names.index(a.name)].motor.torque_constant_nm_per_a
            for a in config.axes
        }
        units = {a.name: self._units(a, k_t[a.name]) for a in config.axes}
        # Rated torque is k_t x rated current, so 0x6072 (per mille of 0x6076) is the same per
        # mille of 0x6075: the most current a drive may set (the codec's 0x6078 scaling).
        peak_current_a = max(
            codec.current(units[a.name]).decode(a.max_torque_permille) for a in config.axes
        )
        self._plant = CommandedPlant(
            sim=self._sim,
            joints=config.axis_names,
            interface=CURRENT,
            current_pi=PIParams(config.current_kp_v_per_a, config.current_ti_s, -1.0, 1.0),
            max_abs_command=2.0 * peak_current_a,
            current_limit_a=peak_current_a,
        )
        # Read-only views, taken once: the simulator updates its arrays in place.
        self._state = self._sim.state_array
        self._modes = self._sim.mode_array
        self._signals = self._sim.signal_array
        self._lock = threading.RLock()
        self._counters = RackCounters()
        self._network = RackNetwork(bus)
        self._network.NOTIFIER_CYCLE = NOTIFIER_TIMEOUT_S
        # Lockstep: the rack's time is its plant's (0x1006 per SYNC), and every deadline,
        # heartbeat and event timer runs on it; realtime: the wall clock.
        self._lockstep = config.timing_mode == LOCKSTEP
        self._network.lockstep = self._lockstep
        self._lockstep_time_s = 0.0
        self._yield_after_tpdos = False  # a master may read on a thread of this process
        self._clock: Callable[[], float] = (
            (lambda: self._lockstep_time_s) if self._lockstep else time.monotonic
        )
        # canopen types its listener list narrowly; any can.Listener works there.
        cast("list[can.Listener]", self._network.listeners)[:] = [
            RackListener(self._on_message, self._on_bus_error)
        ]
        self._axes: list[Drive] = []
        self._by_name: dict[str, Drive] = {}
        self._pdos = PdoEngine(self._axes, self._counters, self._send)
        self._sdo_servers: dict[int, Drive] = {}  # SDO request COB-ID (0x600 + id) -> its node
        self._last_sync_rx_s: float | None = None
        self._sync_length_error = False  # in a run of SYNCs of the wrong length (EMCY sent)
        self._watchdogs = RackWatchdogs(
            self._axes,
            self._counters,
            config.sync_loss_periods,
            config.max_stall_discount_s,
            on_expired=self._communication_error,
            emcy=self._emcy,
            warn_once=self._warn_once,
        )
        self._step_budget_s = 0.0
        self._warned: set[str] = set()
        self._steps_done = 0  # plant steps run since start: the rack's time, SYNCs advance it
        self._started = False
        self._faults = RackFaults(
            self._axes,
            self._network,
            self._counters,
            config.faults,
            self._sim.dt_s,
            steps=lambda: self._steps_done,
            started=lambda: self._started,
            lock=self._lock,
            clock=self._clock,
            emcy=self._emcy,
            communication_error=self._communication_error,
            set_drive=self._set_drive,
        )
        eds = config.eds_path or str(eds_path())
        for joint_index, axis_config in enumerate(config.axes):
            plant_index = self._sim.axis_names.index(axis_config.name)
            dictionary = canopen.objectdictionary.import_od(eds, axis_config.node_id)
            node = canopen.LocalNode(axis_config.node_id, dictionary)
            # canopen 2.4's SDO server starts with no multiplexer (None), and its abort cannot be
            # packed then: a segment request before any transfer raised instead of being
            # answered with an abort (CiA 301 7.2.4.3.17), found by tests/.../test_rack_fuzz.py.
            node.sdo._index, node.sdo._subindex = 0, 0
            axis = Drive(
                config=axis_config,
                plant_index=plant_index,
                joint_index=joint_index,
                gear_ratio=robot.axes[plant_index].gear_ratio,
                torque_constant_nm_per_a=k_t[axis_config.name],
                node=node,
                od=dictionary,
                units=units[axis_config.name],
                defaults={},
            )
            axis.defaults = self._defaults(axis)
            axis.live = self._live_objects(axis)
            limit_a = axis.current.decode(axis_config.max_torque_permille)
            axis.velocity_loop = PIController(
                PIParams(config.velocity_kp_a_per_rad_s, config.velocity_ti_s, -limit_a, limit_a)
            )
            # canopen leaves these two unannotated.
            node.add_read_callback(self._read_callback(axis))  # type: ignore[no-untyped-call]
            node.add_write_callback(self._write_callback(axis))  # type: ignore[no-untyped-call]
            self._network.add_node(node)
            self._axes.append(axis)
            self._by_name[axis_config.name] = axis
            self._sdo_servers[cia301.SDO_REQUEST_COB_BASE + axis_config.node_id] = axis
        self._stop_event = threading.Event()
        self._monitor_thread: threading.Thread | None = None
        self._stopped = False

    # --- lifecycle -------------------------------------------------------------------------

    def start(self, *, settle: bool = True) -> None:
        """Listen on the bus, boot every node (boot-up message, PRE-OPERATIONAL, heartbeat).

        Args:
            settle: first settle the heap (`lca_sim.runtime.settle_heap`: collect, then
                gc.freeze) as the console script does, so that a full collection of the
                start-up objects (Pinocchio, numba, canopen: 70-120 ms with the GIL held) does
                not stall the rack's cycle later. An embedding process that settles its heap
                itself once everything is built may pass False.
        """
        if self._started:
            return
        self._started = True
        if settle:
            settle_heap()  # before the rack's threads run: a full collection would stall them
        self._network.connect()
        bus, notifier = self._network.bus, self._network.notifier
        if isinstance(bus, LinkedVirtualBus) and notifier is not None:
            bus.attach(notifier.listeners)  # a linked master's frames come in its thread
        else:
            self._yield_after_tpdos = isinstance(bus, VirtualBus)
        with self._lock:
            now = self._clock()
            for axis in self._axes:
                self._reset(axis, communication_only=False, now=now)
                self._boot(axis)
                self._faults.reassert(axis, now)
        if self._lockstep:
            return  # the SYNCs run the watchdogs and timers (`_on_sync`)
        self._monitor_thread = threading.Thread(
            target=self._monitor, name="virtual-drive-monitor", daemon=True
        )
        self._monitor_thread.start()

    def stop(self) -> None:
        """Stop the heartbeats, the monitor and the receive thread; the bus stays open."""
        if not self._started or self._stopped:
            return
        self._stopped = True
        if isinstance(self._network.bus, LinkedVirtualBus):
            self._network.bus.detach()  # a master sending on: its frames queue, unread
        self._stop_event.set()
        if self._monitor_thread is not None:
            self._monitor_thread.join()
        if self._network.notifier is not None:  # first: an NMT reset would restart a heartbeat
            self._network.notifier.stop(self._network.NOTIFIER_SHUTDOWN_TIMEOUT)
        for axis in self._axes:
            axis.node.nmt.stop_heartbeat()  # type: ignore[no-untyped-call]

    def __enter__(self) -> VirtualDriveRack:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

    # --- inspection ------------------------------------------------------------------------

    @property
    def simulator(self) -> Simulator:
        """The plant's simulator (read it under `plant_state` from other threads)."""
        return self._sim

    @property
    def plant(self) -> CommandedPlant:
        """The one CommandedPlant behind every node."""
        return self._plant

    @property
    def axis_names(self) -> tuple[str, ...]:
        """The axes of the rack, in order."""
        return self.config.axis_names

    def node(self, axis_name: str) -> canopen.LocalNode:
        """The CANopen node of an axis."""
        return self._axis(axis_name).node

    def power_state(self, axis_name: str) -> PowerState:
        """The CiA 402 power state of an axis."""
        with self._lock:
            return self._axis(axis_name).drive.power

    def nmt_state(self, axis_name: str) -> str:
        """The NMT state of an axis's node (`OPERATIONAL`, `PRE-OPERATIONAL`, `STOPPED`)."""
        with self._lock:
            return self._axis(axis_name).nmt

    @property
    def faults(self) -> dict[str, int]:
        """The active error code (0x603F) per axis; 0 = none."""
        with self._lock:
            return {a.config.name: a.value(od.ERROR_CODE) for a in self._axes}

    @property
    def counters(self) -> RackCounters:
        """A copy of the traffic and error counters."""
        with self._lock:
            return replace(self._counters)

    def plant_state(self) -> PlantState:
        """A consistent snapshot of the plant (taken between SYNC steps)."""
        with self._lock:
            return self._sim.state

    @property
    def time_s(self) -> float:
        """The rack's time: plant steps run since start x dt_s (SYNCs advance it)."""
        with self._lock:
            return self._steps_done * self._sim.dt_s

    @property
    def active_faults(self) -> dict[str, dict[str, int]]:
        """The injected faults that are on, per axis: {kind: value} (`FAULT_KINDS`)."""
        with self._lock:
            return {a.config.name: a.faults.active() for a in self._axes}

    @property
    def fault_log(self) -> tuple[FaultEvent, ...]:
        """Every injected fault going on (value != 0) or off (0), in order."""
        with self._lock:
            return tuple(self._faults.log)

    def set_fault(self, axis_name: str, kind: str, value: int) -> None:
        """Switch a fault on (value != 0) or off (0) at once, as a write of 0x2030 would.

        Args:
            axis_name: the drive.
            kind: one of `FAULT_KINDS`.
            value: the TPDO mask (lost_tpdo), the code (emcy, drive_fault), 1 (heartbeat_off,
                bus_off); 0 switches it off.

        Raises:
            UnknownNameError: an unknown axis or kind.
            ValueError: a value out of the kind's range.
        """
        axis = self._axis(axis_name)
        if kind not in FAULT_KINDS:
            raise UnknownNameError("fault kind", kind, tuple(FAULT_KINDS))
        high = FAULT_VALUE_RANGE[kind][1]
        if isinstance(value, bool) or not 0 <= value <= high:
            raise ValueError(f"{kind}: expected a value in [0, {high}], got {value!r}")
        with self._lock:
            self._faults.set(axis, kind, value, "api", self._clock())

    def _axis(self, name: str) -> Drive:
        try:
            return self._by_name[name]
        except KeyError:
            raise UnknownNameError("axis", name, self.axis_names) from None

    # --- object values ---------------------------------------------------------------------

    def _units(self, axis_config: AxisConfig, torque_constant_nm_per_a: float) -> DriveUnits:
        """The axis's 0x6076 (k_t x rated current), 0x6075 and 0x608F, as a master reads them."""
        try:
            return DriveUnits.from_raw(
                codec.RATED_TORQUE.encode(torque_constant_nm_per_a * axis_config.rated_current_a),
                codec.RATED_CURRENT.encode(axis_config.rated_current_a),
                self.config.encoder_increments_per_rev,
                1,
            )
        except CodecError as exc:
            raise ConfigError(
                self.config.source, f"axes.{axis_config.name}.rated_current_a", str(exc)
            ) from exc

    def _defaults(self, axis: Drive) -> dict[tuple[int, int], int]:
        values: dict[tuple[int, int], int] = {}
        for index in axis.od:
            entry = axis.od[index]
            members = (
                [entry[sub] for sub in entry] if isinstance(entry, ODRecord | ODArray) else [entry]
            )
            for var in members:
                if isinstance(var.default, int):
                    values[(var.index, var.subindex)] = var.default
        cfg = axis.config
        units = axis.units
        values[(od.HEARTBEAT_PRODUCER, 0)] = self.config.heartbeat_producer_ms
        values[(od.MOTOR_RATED_CURRENT, 0)] = codec.RATED_CURRENT.encode(units.rated_current_a)
        values[(od.MOTOR_RATED_TORQUE, 0)] = codec.RATED_TORQUE.encode(units.rated_torque_nm)
        values[(od.MAX_TORQUE, 0)] = cfg.max_torque_permille
        values[(od.POSITION_ENCODER_RESOLUTION, 1)] = self.config.encoder_increments_per_rev
        values[(od.POSITION_ENCODER_RESOLUTION, 2)] = 1
        values[(od.SUPPORTED_DRIVE_MODES, 0)] = cia402.SUPPORTED_DRIVE_MODES_BITS
        return values

    def _live_objects(self, axis: Drive) -> dict[tuple[int, int], Callable[[], int]]:
        """A getter per computed object, its codec bound once (TPDOs call these every SYNC).

        The plant's arrays are read-only views the simulator updates in place, so the getters
        read the state of the moment.
        """
        state, modes, signals = self._state, self._modes, self._signals
        a, gear = axis.plant_index, axis.gear_ratio
        encode_position = codec.position(axis.units).encode
        encode_velocity = codec.velocity(axis.units).encode
        encode_current = codec.current(axis.units).encode
        encode_stall = codec.codec_for(od.entry(od.LONGEST_STALL)).encode
        live: dict[tuple[int, int], Callable[[], int]] = {
            (od.STATUSWORD, 0): lambda: self._statusword(axis),
            (od.CONTROLWORD, 0): lambda: axis.drive.controlword,
            (od.MODES_OF_OPERATION, 0): lambda: axis.drive.mode,
            (od.MODES_OF_OPERATION_DISPLAY, 0): lambda: axis.drive.mode,
            (od.POSITION_ACTUAL, 0): lambda: encode_position(float(state[0, a]) * gear),
            (od.VELOCITY_ACTUAL, 0): lambda: encode_velocity(float(state[1, a]) * gear),
            (od.TORQUE_ACTUAL, 0): lambda: self._torque_actual_permille(axis),
            (od.CURRENT_ACTUAL, 0): lambda: encode_current(float(state[2, a])),
            (od.DRIVE_STATE, 0): lambda: int(modes[1, a]),
            (od.MOTION_STATE, 0): lambda: int(modes[0, a]),
            (od.PROCESS_STALLS, 0): lambda: min(self._counters.process_freezes, 0xFFFFFFFF),
            (od.LONGEST_STALL, 0): lambda: encode_stall(self._watchdogs.freeze_watch.longest_s),
            (od.FAULT_INJECTION, od.FAULT_LOST_TPDOS): lambda: axis.faults.lost_tpdos,
            (od.FAULT_INJECTION, od.FAULT_HEARTBEAT_OFF): lambda: int(axis.faults.heartbeat_off),
            (od.FAULT_INJECTION, od.FAULT_RAISE_EMCY): lambda: axis.faults.emcy_code,
            (od.FAULT_INJECTION, od.FAULT_DRIVE_FAULT): lambda: axis.faults.drive_fault,
            (od.FAULT_INJECTION, od.FAULT_BUS_OFF): lambda: (
                axis.faults.bus_off_ms or int(axis.faults.bus_off)
            ),
        }
        for name, obj in od.SIGNAL_OBJECTS.items():  # eta_m, eta_l, load torque, ...
            live[obj.key] = _signal_getter(
                signals, SIGNAL_NAMES.index(name), a, codec.codec_for(obj, axis.units).encode
            )
        return live

    def _value(self, axis: Drive, index: int, subindex: int) -> int | None:
        """The value of an object: live for process data, stored for the rest."""
        live = axis.live.get((index, subindex))
        return live() if live is not None else axis.values.get((index, subindex))

    def _torque_actual_permille(self, axis: Drive) -> int:
        current_a = float(self._state[2, axis.plant_index])
        return axis.torque.encode(axis.torque_constant_nm_per_a * current_a)

    def _demand(self, axis: Drive) -> cia402.TorqueDemand:
        target = axis.csv_permille if axis.drive.mode == cia402.MODE_CSV else None
        return cia402.torque_demand(
            axis.drive,
            axis.value(od.TARGET_TORQUE) if target is None else target,
            axis.value(od.MAX_TORQUE),
        )

    def _velocity_loop(self, axis: Drive, dt_s: float) -> None:
        """CSV (CiA 402-2 mode 9): the drive's velocity PI turns 0x60FF into its torque demand.

        Runs once per SYNC that advances the plant, over that period, on the joint velocity
        (0x60FF and 0x606C are the motor's, / the gear ratio), with lca_control's PI (the
        paper's gains by default: the same loop the controller node would close, here at the
        bus cycle). Its output, a current, is the demand the current loop then follows, in per
        mille of 0x6075 and clamped to 0x6072 like a CST target. Outside operation enabled, or
        halted, the loop starts again from 0.
        """
        loop = axis.velocity_loop
        assert loop is not None
        drive = axis.drive
        if drive.power is not PowerState.OPERATION_ENABLED or drive.halted:
            loop.reset()
            axis.csv_permille = 0
            return
        if dt_s <= 0.0:
            return
        target_rad_s = axis.velocity.decode(axis.value(od.TARGET_VELOCITY)) / axis.gear_ratio
        current_a = loop.update(target_rad_s, float(self._state[1, axis.plant_index]), dt_s)
        axis.csv_permille = axis.current.encode(current_a)

    def _statusword(self, axis: Drive) -> int:
        demand = self._demand(axis)
        reached = (
            axis.drive.power is PowerState.OPERATION_ENABLED
            and abs(self._torque_actual_permille(axis) - demand.permille)
            <= cia402.TARGET_TORQUE_WINDOW_PERMILLE
        )
        return cia402.statusword(axis.drive, target_reached=reached, internal_limit=demand.limited)

    def _read_callback(self, axis: Drive) -> Callable[..., int | None]:
        def on_read(*, index: int, subindex: int, od: ODVariable, **_: Any) -> int | None:
            if od.subindex != subindex:
                raise SdoAbortedError(cia301.ABORT_NO_SUBINDEX)
            with self._lock:
                return self._value(axis, index, subindex)

        return on_read

    def _write_callback(self, axis: Drive) -> Callable[..., None]:
        def on_write(*, index: int, subindex: int, od: ODVariable, data: bytes, **_: Any) -> None:
            if od.subindex != subindex:
                raise SdoAbortedError(cia301.ABORT_NO_SUBINDEX)
            value = od.decode_raw(data)
            if not isinstance(value, int):
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            with self._lock:
                self._write(axis, index, subindex, value, self._clock())

        return on_write

    def _write(self, axis: Drive, index: int, subindex: int, value: int, now: float) -> None:
        """Validate and apply a write (SDO or RPDO); SdoAbortedError refuses it."""
        if index == od.FAULT_INJECTION:
            self._faults.write(axis, subindex, value, now)
            return
        if index == od.CONTROLWORD:
            self._apply_controlword(axis, value, now)
            return
        if index == od.MODES_OF_OPERATION:
            if not cia402.is_supported_mode(value):
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            axis.drive = replace(axis.drive, mode=value)
            return
        if index == od.MAX_TORQUE and value > axis.config.max_torque_permille:
            raise SdoAbortedError(cia301.ABORT_VALUE_TOO_HIGH)
        allowed = _OPTION_VALUES.get((index, subindex))
        if allowed is not None and value not in allowed:
            raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
        value = self._pdos.write(axis, index, subindex, value)
        if index == od.HEARTBEAT_CONSUMER:
            axis.heartbeat_last_rx_s = None
        axis.values[(index, subindex)] = value

    # --- CiA 402 state ---------------------------------------------------------------------

    def _quick_stop_option(self, axis: Drive) -> int:
        return axis.value(od.QUICK_STOP_OPTION)

    def _standstill(self, axis: Drive) -> bool:
        return bool(self._modes[0, axis.plant_index] == 0.0)

    def _set_drive(self, axis: Drive, state: Cia402AxisState, now: float) -> None:
        state = cia402.settle(
            state,
            standstill=self._standstill(axis),
            quick_stop_option=self._quick_stop_option(axis),
        )
        enabled = PowerState.OPERATION_ENABLED
        if state.power is enabled and axis.drive.power is not enabled:
            axis.sync_armed_s = now  # SYNC loss is watched from here on
            axis.sync_loss_reported = False
        axis.drive = state

    def _apply_controlword(self, axis: Drive, controlword: int, now: float) -> None:
        persisting = axis.faults.drive_fault  # an injected drive fault whose cause lasts
        if cia402.is_fault_reset_edge(controlword, axis.drive.controlword) and not persisting:
            self._clear_errors(axis)
            if axis.faults.emcy_code:  # the raised EMCY is reset with the other errors
                self._faults.set(axis, "emcy", 0, "fault reset", now)
        state = cia402.apply_controlword(axis.drive, controlword, self._quick_stop_option(axis))
        if persisting:
            # CiA 402-2: a fault reset leaves FAULT only once the fault's cause is gone.
            state = cia402.fault(state)
        self._set_drive(axis, state, now)

    def _clear_errors(self, axis: Drive) -> None:
        if axis.value(od.ERROR_REGISTER) or axis.value(od.ERROR_CODE):
            axis.values[(od.ERROR_REGISTER, 0)] = 0
            axis.values[(od.ERROR_CODE, 0)] = 0
            self._emcy(axis, cia402.EMCY_ERROR_RESET)

    def _set_error(self, axis: Drive, code: int) -> None:
        """A communication error: 0x603F, 0x1001 (generic + communication), then its EMCY."""
        axis.values[(od.ERROR_CODE, 0)] = code
        axis.values[(od.ERROR_REGISTER, 0)] = axis.value(od.ERROR_REGISTER) | (
            cia402.ERROR_REGISTER_GENERIC | cia402.ERROR_REGISTER_COMMUNICATION
        )
        self._emcy(axis, code)  # not in STOPPED

    def _connection_lost(self, axis: Drive, code: int | None, now: float) -> None:
        """A watchdog fired (or NMT stop): error code, EMCY, then the 0x6007 reaction."""
        if code is not None:
            self._set_error(axis, code)
        state = cia402.abort_connection(
            axis.drive,
            axis.value(od.ABORT_CONNECTION_OPTION),
            self._quick_stop_option(axis),
        )
        self._set_drive(axis, state, now)

    def _communication_error(self, axis: Drive, code: int, now: float) -> None:
        """A watchdog fired: 0x603F, 0x1001, EMCY, the 0x6007 reaction, then 0x1029's NMT change.

        CiA 301 7.5.2.32 (0x1029 error behaviour, sub 1 communication error): 0 to
        PRE-OPERATIONAL if the node is OPERATIONAL, 1 no change, 2 to STOPPED.
        """
        self._connection_lost(axis, code, now)
        behaviour = axis.value(od.ERROR_BEHAVIOUR, 1)
        if behaviour == od.ERROR_BEHAVIOUR_PRE_OPERATIONAL and axis.nmt == NMT_OPERATIONAL:
            axis.node.nmt.send_command(
                cia301.NMT_ENTER_PRE_OPERATIONAL
            )  # the heartbeat says so too
            self._enter_nmt(axis, NMT_PRE_OPERATIONAL, now)
        elif behaviour == od.ERROR_BEHAVIOUR_STOPPED and axis.nmt != NMT_STOPPED:
            axis.node.nmt.send_command(cia301.NMT_STOP)
            self._enter_nmt(axis, NMT_STOPPED, now)

    def _nmt_reaction(self, axis: Drive, now: float) -> None:
        """The master took the node out of OPERATIONAL, stopped or reset it: the 0x6007 reaction.

        CiA 402-2 0x6007 (abort connection option code) covers the NMT master stopping the
        node as well as a lost connection. Where the reaction acted (the drive could produce
        torque), 0x603F and 0x1001 say so with `EMCY_LEFT_OPERATIONAL`, and the EMCY goes
        out unless the node is now STOPPED (CiA 301: no EMCY there).
        """
        before = axis.drive.power
        self._connection_lost(axis, None, now)
        if axis.drive.power is not before:
            self._set_error(axis, cia402.EMCY_LEFT_OPERATIONAL)

    # --- NMT -------------------------------------------------------------------------------

    def _reset(self, axis: Drive, communication_only: bool, now: float) -> None:
        """Objects back to their defaults (0x1000-0x1FFF only for reset communication).

        Reset communication keeps 0x1001: the error register reports the drive's errors (0x603F
        and the FAULT it is in survive the reset), it is not a communication parameter.
        """
        for key, default in axis.defaults.items():
            if communication_only and key == (od.ERROR_REGISTER, 0):
                continue
            if not communication_only or key[0] < 0x2000:
                axis.values[key] = default
        for index in list(axis.node.data_store):
            if not communication_only or index < 0x2000:
                del axis.node.data_store[index]
        self._pdos.load(axis)
        if not communication_only:
            axis.drive = Cia402AxisState(mode=axis.value(od.MODES_OF_OPERATION))
            self._set_drive(axis, axis.drive, now)
        axis.heartbeat_last_rx_s = None
        axis.sync_armed_s = now
        axis.sync_loss_reported = False

    def _boot(self, axis: Drive) -> None:
        """Boot-up message, then PRE-OPERATIONAL with the heartbeat of 0x1017 running."""
        axis.node.nmt.send_command(cia301.NMT_RESET_NODE)  # from INITIALISING: sends the boot-up
        axis.node.nmt.send_command(cia301.NMT_ENTER_PRE_OPERATIONAL)  # starts the heartbeat
        axis.nmt = NMT_PRE_OPERATIONAL

    def _leave_operational(self, axis: Drive) -> None:
        for pdo in axis.rpdos:
            pdo.latched, pdo.last_rx_s = None, None

    def _on_nmt(self, data: bytes, now: float) -> None:
        """Post-process an NMT command (canopen's NmtSlave has already set its state)."""
        if len(data) != 2:
            self._counters.bad_frames += 1
            return
        command, node_id = data[0], data[1]
        states = {
            cia301.NMT_START: NMT_OPERATIONAL,
            cia301.NMT_STOP: NMT_STOPPED,
            cia301.NMT_ENTER_PRE_OPERATIONAL: NMT_PRE_OPERATIONAL,
        }
        for axis in self._axes:
            if node_id not in (0, axis.config.node_id) or axis.faults.bus_off:
                continue
            if command in states:
                self._enter_nmt(axis, states[command], now)
            elif command in (cia301.NMT_RESET_NODE, cia301.NMT_RESET_COMMUNICATION):
                communication_only = command == cia301.NMT_RESET_COMMUNICATION
                if communication_only:
                    self._nmt_reaction(axis, now)
                self._reset(axis, communication_only, now)
                self._boot(axis)
                self._faults.reassert(axis, now)

    def _enter_nmt(self, axis: Drive, state: str, now: float) -> None:
        """Move a node to an NMT state (its canopen NmtSlave is set by the caller).

        Leaving OPERATIONAL (no more PDOs: the last target must not stay applied) and entering
        STOPPED (no more SDO either) apply the 0x6007 reaction (`_nmt_reaction`).
        """
        previous = axis.nmt
        if state == previous:
            return
        axis.nmt = state
        if state == NMT_OPERATIONAL:
            axis.sync_armed_s = now
            axis.sync_loss_reported = False
            for pdo in axis.tpdos:
                pdo.last_data, pdo.sync_count = None, 0
            return
        self._leave_operational(axis)
        if previous == NMT_OPERATIONAL or state == NMT_STOPPED:
            self._nmt_reaction(axis, now)

    # --- frames ----------------------------------------------------------------------------

    def _on_message(self, msg: can.Message) -> None:
        """Every frame the notifier reads: filter it, then canopen's services, then `_on_frame`.

        Never raises: the receive thread must survive whatever arrives.
        The nodes are classical CANopen nodes with 11-bit identifiers (CiA 301 uses CAN base
        frames; a 29-bit or a CAN FD frame is not CANopen CC traffic even when its identifier
        looks like an SDO or NMT one): those, remote frames (no object of these nodes answers
        RTR: TPDO COB-IDs carry bit 30) and error frames are counted and go no further.
        """
        counters = self._counters
        if not self._is_classical_data_frame(msg):
            return
        cob = msg.arbitration_id
        if len(msg.data) > 8:
            counters.bad_frames += 1
            return
        sdo_server = self._sdo_servers.get(cob)
        if sdo_server is not None:
            if len(msg.data) != 8:
                counters.bad_frames += 1  # CiA 301: an SDO request is 8 bytes; ignored otherwise
                return
            if sdo_server.nmt == NMT_STOPPED:
                # CiA 301 7.3.2.2 (NMT state machine, table of services per state): in STOPPED
                # only NMT and node guarding / heartbeat are active, so SDO is not answered.
                counters.sdo_ignored_stopped += 1
                return
        # An NMT frame of the wrong length goes to `_on_frame` (which counts it) only: canopen's
        # NMT slave would act on the first two bytes of a longer one.
        if cob != cia301.NMT_COB_ID or len(msg.data) == 2:
            try:
                self._network.notify(cob, msg.data, msg.timestamp)
            except Exception:
                counters.handler_errors += 1
                logger.exception("virtual drive: canopen failed on frame 0x%03X", cob)
        self._on_frame(msg)

    def _is_classical_data_frame(self, msg: can.Message) -> bool:
        """An 11-bit classical CAN data frame; anything else is counted by its kind."""
        counters = self._counters
        if msg.is_error_frame:
            counters.error_frames += 1
        elif msg.is_fd:
            counters.fd_frames += 1
        elif msg.is_extended_id:
            counters.extended_frames += 1
        elif msg.is_remote_frame:
            counters.remote_frames += 1
        else:
            return True
        return False

    def _on_frame(self, msg: can.Message) -> None:
        """Dispatch one received (filtered) frame; never raises."""
        cob = msg.arbitration_id
        data = bytes(msg.data)
        try:
            now = self._clock()
            if cob == cia301.SYNC_COB_ID:
                # The bus's reception stamp, not `now`: SYNCs queued while this process stood
                # still keep their spacing for the SYNC rate check (`_sync_in_time`).
                stamp_s = msg.timestamp if msg.timestamp > 0.0 else time.time()
                with self._lock:
                    self._on_sync(data, now, stamp_s)
            elif cob == cia301.NMT_COB_ID:
                with self._lock:
                    self._on_nmt(data, now)
            elif cia301.HEARTBEAT_COB_BASE < cob <= cia301.HEARTBEAT_COB_BASE + cia301.NODE_ID_MAX:
                with self._lock:
                    self._on_heartbeat(cob - cia301.HEARTBEAT_COB_BASE, data, now)
            else:
                targets = self._pdos.rpdo_table.get(cob)
                if targets:
                    with self._lock:
                        for axis, pdo in targets:
                            self._on_rpdo(axis, pdo, data, now)
        except Exception:
            self._counters.handler_errors += 1
            logger.exception("virtual drive: error handling frame 0x%03X %s", cob, data.hex())

    def _on_bus_error(self, exc: Exception) -> None:
        """The bus layer raised in the receive thread (a malformed datagram): count it, go on.

        The notifier's thread survives because this listener handles the error; the exception
        it keeps is cleared so that the next send does not re-raise it (`RackNetwork`).
        """
        self._counters.bus_errors += 1
        notifier = self._network.notifier
        if notifier is not None:
            notifier.exception = None
        self._warn_once(f"bus-error-{type(exc).__name__}", f"CAN receive error: {exc!r}")

    def _on_heartbeat(self, producer: int, data: bytes, now: float) -> None:
        if len(data) != 1:
            self._counters.bad_frames += 1
            return
        for axis in self._axes:
            node_id, time_ms = cia402.heartbeat_consumer_entry(axis.value(od.HEARTBEAT_CONSUMER, 1))
            if node_id == producer and time_ms and not axis.faults.bus_off:
                axis.heartbeat_last_rx_s = now

    def _on_rpdo(self, axis: Drive, pdo: Pdo, data: bytes, now: float) -> None:
        if axis.faults.bus_off:
            return  # its controller takes no frame
        self._counters.rpdos_received += 1
        if axis.nmt != NMT_OPERATIONAL or not pdo.valid:
            self._counters.pdos_ignored_not_operational += 1
            return
        if len(data) != pdo.size_bytes:
            # CiA 301 EMCY error codes: 0x8210 "PDO not processed due to length error", 0x8220
            # "PDO length exceeded". The frame is not applied; one EMCY per run of wrong frames
            # (each is counted), so that a flood of them does not flood the bus with EMCYs.
            self._counters.bad_frames += 1
            code = (
                cia402.EMCY_PDO_LENGTH
                if len(data) < pdo.size_bytes
                else cia402.EMCY_PDO_LENGTH_EXCEEDED
            )
            if pdo.length_error != code:
                pdo.length_error = code
                self._emcy(axis, code)
            self._warn_once(
                f"rpdo-length-{axis.config.node_id}-{pdo.number}",
                f"node {axis.config.node_id} RPDO{pdo.number}: {len(data)} bytes, "
                f"mapping has {pdo.size_bytes}; dropped",
            )
            return
        pdo.length_error = 0
        pdo.last_rx_s = now
        if pdo.transmission_type <= cia402.SYNC_TRANSMISSION_MAX:
            pdo.latched = data
        else:
            self._apply_rpdo(axis, pdo, data, now)

    def _apply_rpdo(self, axis: Drive, pdo: Pdo, data: bytes, now: float) -> None:
        for obj, value in zip(pdo.objects, pdo.frame.unpack(data), strict=True):
            try:
                self._write(axis, obj.index, obj.subindex, int(value), now)
            except SdoAbortedError:
                self._counters.rpdo_values_rejected += 1
        self._counters.rpdos_applied += 1

    def _on_sync(self, data: bytes, now: float, stamp_s: float) -> None:
        """Apply the latched RPDOs, send the synchronous TPDOs, advance the plant one cycle."""
        if not self._sync_length_ok(data):
            return
        self._counters.syncs += 1
        if not self._faults.idle:
            self._faults.run_clock(now)
        operational = [a for a in self._axes if a.nmt == NMT_OPERATIONAL and not a.faults.bus_off]
        for axis in operational:
            self._apply_latched_rpdos(axis, now)
        for axis in self._axes:
            self._set_drive(axis, axis.drive, now)
            axis.sync_loss_reported = False
        self._send_tpdos_of_sync(operational, now)
        # A real drive's TPDOs leave in hardware while its CPU goes on; a master in this
        # process on python-can's virtual bus reads them on another thread, so let it before
        # the plant's period is computed. A linked master has read them already, inside the
        # sends (`LinkedVirtualBus`); a master behind a socket (lca_remote, socketcan) is in
        # another process.
        if self._yield_after_tpdos:
            yield_gil()
        self._advance(now, stamp_s)
        for axis in self._axes:
            self._set_drive(axis, axis.drive, now)
        done = self._clock()
        if self._lockstep:  # the monitor's work, at the rack's time after this cycle
            self._watchdogs.last_sync_done_s = done
            self._watchdogs.check(done)
            self._network.send_due(done)
        self._pdos.service_event_tpdos(done)
        self._watchdogs.last_sync_done_s = done

    def _send_tpdos_of_sync(self, operational: list[Drive], now: float) -> None:
        """Every operational node's synchronous TPDOs; over lca_remote, in one write."""
        try:
            with batched_sends(self._network.bus):
                for axis in operational:
                    self._pdos.send_sync_tpdos(axis, now)
        except (can.CanError, OSError) as exc:  # the batch's one write failed
            self._counters.send_errors += 1
            self._warn_once(f"send-{type(exc).__name__}", f"send of the TPDOs failed: {exc}")

    def _sync_length_ok(self, data: bytes) -> bool:
        """CiA 301: a SYNC carries no data, or the 1-byte counter.

        Anything else is EMCY 0x8240 "unexpected SYNC data length" from each consumer (once per
        run of them), counted, and not a SYNC.
        """
        if len(data) <= 1:
            self._sync_length_error = False
            return True
        self._counters.bad_frames += 1
        if not self._sync_length_error:
            self._sync_length_error = True
            for axis in self._axes:
                self._emcy(axis, cia402.EMCY_SYNC_LENGTH)
        return False

    def _apply_latched_rpdos(self, axis: Drive, now: float) -> None:
        """At a SYNC: the synchronous RPDOs received since the previous one (the latest wins)."""
        for pdo in axis.rpdos:
            if pdo.latched is not None:
                latched, pdo.latched = pdo.latched, None
                self._apply_rpdo(axis, pdo, latched, now)

    def _cycle_period_s(self) -> float:
        return max(a.value(od.CYCLE_PERIOD) for a in self._axes) * 1e-6

    def _sync_in_time(self, period_s: float, stamp_s: float) -> bool:
        """Whether this SYNC may advance the plant a period (0x1006 > 0), or comes too early.

        SYNCs faster than 0x1006 (a second producer, a master whose cycle does not match what
        it wrote there) would run the plant faster than the wall clock; the watchdogs' judge
        (`RackWatchdogs.sync_verdict`) tells them. The excess SYNCs are handled as any SYNC
        (RPDOs applied, TPDOs sent) but do not advance the plant; each is counted
        (`syncs_too_fast`), and every node sends EMCY 0x8100 once per episode (over after a
        window without excess).
        """
        verdict = self._watchdogs.sync_verdict(period_s, stamp_s)
        if verdict is sync_rate.SyncVerdict.IN_TIME:
            return True
        self._counters.syncs_too_fast += 1
        if verdict is sync_rate.SyncVerdict.TOO_FAST_REPORT:
            self._warn_once(
                "sync-too-fast",
                f"SYNCs faster than 0x1006 ({period_s * 1e6:.0f} us), a second SYNC producer? "
                "The excess ones do not advance the plant",
            )
            for axis in self._axes:
                self._emcy(axis, cia402.EMCY_SYNC_TOO_FAST)
        return False

    def _advance(self, now: float, stamp_s: float) -> None:
        """Command the torque demands and run the plant one cycle (see the module docstring)."""
        period_s = self._cycle_period_s()
        if self._lockstep:
            # The master is the clock: each SYNC is one 0x1006 period, however fast it comes.
            span_s = period_s
            if period_s <= 0.0:
                self._warn_once("lockstep-0x1006", "lockstep needs 0x1006 > 0: the plant stands")
            self._lockstep_time_s += span_s
        elif period_s > 0.0:
            span_s = period_s if self._sync_in_time(period_s, stamp_s) else 0.0
        elif self._last_sync_rx_s is None:
            span_s = 0.0
        else:
            span_s = min(max(now - self._last_sync_rx_s, 0.0), MAX_WALL_ADVANCE_S)
        self._last_sync_rx_s = now
        dt_s = self._sim.dt_s
        self._step_budget_s += span_s
        steps = math.floor(self._step_budget_s / dt_s + 1e-6)
        self._step_budget_s = max(self._step_budget_s - steps * dt_s, 0.0)
        currents_a = [0.0] * len(self._axes)
        any_enabled = False
        for axis in self._axes:
            if axis.drive.mode == cia402.MODE_CSV:
                self._velocity_loop(axis, span_s)
            demand = self._demand(axis)
            # Rated torque is k_t x rated current: a torque in per mille of 0x6076 is the same
            # per mille of 0x6075 (CiA 402-2 0x6071 / 0x6075), the drive's current setpoint.
            currents_a[axis.joint_index] = axis.current.decode(demand.permille)
            any_enabled = any_enabled or axis.drive.power is PowerState.OPERATION_ENABLED
        if any_enabled:
            refused = self._plant.command(currents_a)
            if refused is not None:
                self._counters.handler_errors += 1
                self._warn_once("plant-command", f"plant refused currents: {refused}")
                self._plant.hold_zero()
        else:
            self._plant.hold_zero()  # every power stage off: no current, loops reset
        if steps:
            self._plant.advance(steps)
            self._steps_done += steps

    # --- transmission ----------------------------------------------------------------------

    def _send(self, cob_id: int, data: bytes) -> bool:
        try:
            self._network.send_message(cob_id, data)
        except (can.CanError, OSError, RuntimeError) as exc:
            self._counters.send_errors += 1
            self._warn_once(f"send-{type(exc).__name__}", f"send of 0x{cob_id:03X} failed: {exc}")
            return False
        return True

    def _emcy(self, axis: Drive, code: int, data: bytes = b"") -> None:
        """Send an EMCY: code, 0x1001, and up to 5 manufacturer-specific bytes."""
        if axis.nmt == NMT_STOPPED:
            return  # no EMCY in STOPPED (CiA 301)
        if axis.faults.bus_off:
            self._counters.frames_dropped_bus_off += 1
            return
        register = axis.value(od.ERROR_REGISTER)
        try:
            axis.node.emcy.send(code, register, data)
        except (can.CanError, OSError, RuntimeError) as exc:
            self._counters.send_errors += 1
            self._warn_once("emcy", f"EMCY send failed: {exc}")
            return
        self._counters.emcy_sent += 1

    # --- watchdogs -------------------------------------------------------------------------

    def _monitor(self) -> None:
        due = time.monotonic() + MONITOR_PERIOD_S
        while not self._stop_event.wait(max(due - time.monotonic(), 0.0)):
            try:
                with self._lock:
                    now = time.monotonic()
                    late_s = now - due
                    due = now + MONITOR_PERIOD_S
                    self._watchdogs.tick(late_s, now)
                    self._pdos.service_event_tpdos(now)
            except Exception:
                self._counters.handler_errors += 1
                logger.exception("virtual drive: error in the monitor")

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            logger.warning("virtual drive: %s (further ones are only counted)", message)


def _signal_getter(
    signals: Any, row: int, column: int, encode: Callable[[float], int]
) -> Callable[[], int]:
    """A getter encoding one plant signal of one axis (`SIGNAL_NAMES` row, axis column)."""

    def get() -> int:
        return encode(float(signals[row, column]))

    return get
