"""The virtual drive rack: one CiA 402 CANopen node per axis over one coupled lca_sim plant (shell).

Four `canopen.LocalNode`s (SDO server, NMT slave, EMCY producer) on one python-can bus, all
backed by ONE `CommandedPlant(interface="current")` of one `Simulator`, so the axes stay coupled
through the gantry model. docs/can.md, "The virtual drive rack", is the contract a master relies
on (boot, PDO timing on SYNC, modes 0x6060 = 10, 9 and 0, watchdogs, fault injection).

    rack = VirtualDriveRack(bus, load_rack_config(None))   # lca_sim.config.rack
    with rack: rack.power_state("pivot")                     # start() ... stop()

Its parts: `rack_state` (per-drive values), `rack_network` (the bus side and frame filter),
`rack_objects` (object store, SDO), `rack_cia402` (power state, errors, demand), `rack_nmt`
(NMT), `rack_pdo` (PDOs), `rack_watchdog` (deadlines, SYNC rate, freeze discount),
`rack_faults` (fault injection). The console script is `lca_sim.cli.virtual_drive`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from types import TracebackType
from typing import cast

import can
import canopen
from can.interfaces.virtual import VirtualBus

from lca_control.drive_loops import DriveLoopParams
from lca_control.pi import PIParams
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.rack_cia402 import DriveControl
from lca_sim.canbus.rack_faults import RackFaults
from lca_sim.canbus.rack_modes import AxisModes
from lca_sim.canbus.rack_network import RackListener, RackNetwork, RackSender
from lca_sim.canbus.rack_nmt import RackNmt
from lca_sim.canbus.rack_objects import ObjectStore, drive_units
from lca_sim.canbus.rack_pdo import PdoEngine
from lca_sim.canbus.rack_state import NMT_OPERATIONAL, Drive, FaultEvent, RackCounters
from lca_sim.canbus.rack_watchdog import RackWatchdogs
from lca_sim.canbus.remote import RemoteTransportBus
from lca_sim.cia402 import cia301, codec
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import DriveUnits
from lca_sim.cia402.device import PowerState
from lca_sim.config.loader import load_robot
from lca_sim.config.rack import (
    LOCKSTEP,
    AxisConfig,
    RackConfig,
    eds_path,
)
from lca_sim.errors import ConfigError, UnknownNameError
from lca_sim.model.commanded_plant import CURRENT, CommandedPlant
from lca_sim.model.params import RobotParams
from lca_sim.model.plant import PlantConfig, build_plant
from lca_sim.model.simulator import InputError, PlantState, Simulator
from lca_sim.runtime import (
    settle_heap,
    yield_gil,
)

logger = logging.getLogger(__name__)

MONITOR_PERIOD_S = 0.005  # watchdogs and event-driven TPDOs are checked this often
MAX_WALL_ADVANCE_S = 0.05  # 0x1006 = 0: the plant follows the wall time, at most this per SYNC
NOTIFIER_TIMEOUT_S = 0.05  # the receive thread's poll: bounds how long stop() waits for it
_CYCLE_PERIOD = (od.CYCLE_PERIOD, 0)  # read from every drive at every SYNC (`Drive.values`)


_LAST_HEARTBEAT_COB_ID = cia301.HEARTBEAT_COB_BASE + cia301.NODE_ID_MAX  # node 127's


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
        self._sim, self._plant, k_t, units = _build_plant(config, robot)
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
        self._warned: set[str] = set()
        self._sender = RackSender(self._network, self._counters, self._warn_once)
        self._axes: list[Drive] = []
        self._by_name: dict[str, Drive] = {}
        sdo_servers: dict[int, Drive] = {}  # SDO request COB-ID (0x600 + id) -> its node
        # canopen types its listener list narrowly; any can.Listener works there.
        cast("list[can.Listener]", self._network.listeners)[:] = [
            RackListener(
                self._network, self._counters, sdo_servers, self._on_frames, self._warn_once
            )
        ]
        # The parts call each other; the lambdas reach parts built further down, which exist
        # before any frame or call comes.
        self._control = DriveControl(
            self._sim.state_array,
            self._sim.mode_array,
            emcy=self._sender.emcy,
            reset_raised_emcy=lambda axis, now: self._faults.set(
                axis, "emcy", 0, "fault reset", now
            ),
        )
        self._pdos = PdoEngine(
            self._axes,
            self._counters,
            self._sender.send,
            write=lambda *write: self._objects.write(*write),  # noqa: PLW0108 (built below)
            emcy=self._sender.emcy,
            warn_once=self._warn_once,
            send_frames=self._sender.send_frames if self._sender.takes_frames else None,
        )
        self._nmt = RackNmt(
            self._axes,
            self._counters,
            self._control,
            load_pdos=self._pdos.load,
            reassert=lambda axis, now: self._faults.reassert(axis, now),  # noqa: PLW0108
        )
        self._last_sync_rx_s: float | None = None
        self._watchdogs = RackWatchdogs(
            self._axes,
            self._counters,
            config.sync_loss_periods,
            config.max_stall_discount_s,
            on_expired=self._nmt.communication_error,
            emcy=self._sender.emcy,
            warn_once=self._warn_once,
        )
        self._step_budget_s = 0.0
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
            emcy=self._sender.emcy,
            communication_error=self._nmt.communication_error,
            set_drive=self._control.set_drive,
        )
        self._objects = ObjectStore(
            config,
            (self._sim.state_array, self._sim.mode_array, self._sim.signal_array),
            self._counters,
            lambda: self._watchdogs.freeze_watch.longest_s,
            self._control,
            lock=self._lock,
            clock=self._clock,
            write_fault=self._faults.write,
            write_pdo=self._pdos.write,
        )
        eds = config.eds_path or str(eds_path())
        for joint_index, axis_config in enumerate(config.axes):
            axis = _build_drive(config, axis_config, joint_index, self._sim, robot, eds, k_t, units)
            self._objects.attach(axis)
            self._network.add_node(axis.node)
            self._axes.append(axis)
            self._by_name[axis_config.name] = axis
            sdo_servers[cia301.SDO_REQUEST_COB_BASE + axis_config.node_id] = axis
        self._stop_event = threading.Event()
        self._monitor_thread: threading.Thread | None = None
        self._stopped = False

    # --- lifecycle -------------------------------------------------------------------------

    def start(self, *, settle: bool = True) -> None:
        """Listen on the bus, boot every node (boot-up message, PRE-OPERATIONAL, heartbeat).

        Args:
            settle: first settle the heap (`lca_sim.runtime.settle_heap`) as the console
                script does, so that a full collection of the start-up objects (70-120 ms with
                the GIL held) does not stall the rack's cycle later; an embedding process that
                settles its heap itself may pass False.
        """
        if self._started:
            return
        self._started = True
        if settle:
            settle_heap()  # before the rack's threads run: a full collection would stall them
        self._network.connect()
        bus, notifier = self._network.bus, self._network.notifier
        if isinstance(bus, LinkedVirtualBus | RemoteTransportBus) and notifier is not None:
            # a linked master's frames come in its thread; both hand data frames as they are
            bus.attach(notifier.listeners)
        else:
            self._yield_after_tpdos = isinstance(bus, VirtualBus)
        with self._lock:
            now = self._clock()
            for axis in self._axes:
                self._nmt.power_on(axis, now)
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
        if isinstance(self._network.bus, LinkedVirtualBus | RemoteTransportBus):
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
        self._faults.set_checked(self._axis(axis_name), kind, value)

    def _axis(self, name: str) -> Drive:
        try:
            return self._by_name[name]
        except KeyError:
            raise UnknownNameError("axis", name, self.axis_names) from None

    # --- frames ----------------------------------------------------------------------------

    def _on_frames(self, frames: list[tuple[int, bytes]], timestamp: float) -> None:
        """Dispatch received (filtered) data frames, in order, under the lock; never raises.

        A run (a cycle's RPDOs and SYNC, read at once) takes the lock once. A frame that
        fails is counted and logged, and the ones after it are still handled.
        """
        with self._lock:
            now = self._clock()
            for cob, data in frames:
                try:
                    if cob == cia301.SYNC_COB_ID:
                        # The bus's reception stamp, not `now`: SYNCs queued while this
                        # process stood still keep their spacing for the SYNC rate check
                        # (`RackWatchdogs.sync_in_time`).
                        stamp_s = timestamp if timestamp > 0.0 else time.time()
                        try:
                            self._on_sync(data, now, stamp_s)
                        finally:
                            now = self._clock()  # the frames after it: after its handling
                    elif cob == cia301.NMT_COB_ID:
                        self._nmt.on_nmt(data, now)
                    elif cia301.HEARTBEAT_COB_BASE < cob <= _LAST_HEARTBEAT_COB_ID:
                        self._watchdogs.heard(cob - cia301.HEARTBEAT_COB_BASE, data, now)
                    else:
                        targets = self._pdos.rpdo_table.get(cob)
                        if targets:
                            for axis, pdo in targets:
                                self._pdos.receive(axis, pdo, data, now)
                except Exception:
                    self._counters.handler_errors += 1
                    logger.exception(
                        "virtual drive: error handling frame 0x%03X %s", cob, data.hex()
                    )

    def _on_sync(self, data: bytes, now: float, stamp_s: float) -> None:
        """Apply the latched RPDOs, send the synchronous TPDOs, advance the plant one cycle."""
        if not self._watchdogs.sync_length_ok(data):
            return
        self._counters.syncs += 1
        if not self._faults.idle:
            self._faults.run_clock(now)
        operational = [a for a in self._axes if a.nmt == NMT_OPERATIONAL and not a.faults.bus_off]
        self._pdos.apply_latched(operational, now)
        self._control.settle(self._axes, now)
        for axis in self._axes:
            axis.sync_loss_reported = False
        self._pdos.send_sync_tpdos(operational, now, self._network.bus)
        # A real drive's TPDOs leave in hardware while its CPU goes on; a master in this
        # process on python-can's virtual bus reads them on another thread, so let it before
        # the plant's period is computed. A linked master has read them already, inside the
        # sends (`LinkedVirtualBus`); a master behind a socket (lca_remote, socketcan) is in
        # another process.
        if self._yield_after_tpdos:
            yield_gil()
        self._advance(now, stamp_s)
        self._control.settle(self._axes, now)
        done = self._clock()
        if self._lockstep:  # the monitor's work, at the rack's time after this cycle
            self._watchdogs.last_sync_done_s = done
            self._watchdogs.check(done)
            self._network.send_due(done)
        self._pdos.service_event_tpdos(done)
        self._watchdogs.last_sync_done_s = done

    def _advance(self, now: float, stamp_s: float) -> None:
        """Command the torque demands and run the plant one SYNC's span."""
        period_s = max([a.values[_CYCLE_PERIOD] for a in self._axes]) * 1e-6
        if self._lockstep:
            # The master is the clock: each SYNC is one 0x1006 period, however fast it comes.
            span_s = period_s
            if period_s <= 0.0:
                self._warn_once("lockstep-0x1006", "lockstep needs 0x1006 > 0: the plant stands")
            self._lockstep_time_s += span_s
        elif period_s > 0.0:
            span_s = period_s if self._watchdogs.sync_in_time(period_s, stamp_s) else 0.0
        elif self._last_sync_rx_s is None:
            span_s = 0.0
        else:
            span_s = min(max(now - self._last_sync_rx_s, 0.0), MAX_WALL_ADVANCE_S)
        self._last_sync_rx_s = now
        dt_s = self._sim.dt_s
        self._step_budget_s += span_s
        steps = math.floor(self._step_budget_s / dt_s + 1e-6)
        self._step_budget_s = max(self._step_budget_s - steps * dt_s, 0.0)
        currents_a = self._control.currents_a(self._axes, span_s, now)
        if currents_a is not None:
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

    def _monitor(self) -> None:
        due = time.monotonic() + MONITOR_PERIOD_S
        while True:  # a sleep, not the stop event's wait: 15 us less CPU a tick, stop() waits one
            time.sleep(max(due - time.monotonic(), 0.0))
            if self._stop_event.is_set():
                return
            try:
                with self._lock:
                    now = time.monotonic()
                    late_s = now - due
                    due = now + MONITOR_PERIOD_S
                    self._watchdogs.tick(late_s, now)
                    if now - self._watchdogs.last_sync_done_s >= MONITOR_PERIOD_S:
                        # else a SYNC's handling served the event TPDOs since the last tick
                        self._pdos.service_event_tpdos(now)
            except Exception:
                self._counters.handler_errors += 1
                logger.exception("virtual drive: error in the monitor")

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            logger.warning("virtual drive: %s (further ones are only counted)", message)


def _build_plant(
    config: RackConfig, robot: RobotParams
) -> tuple[Simulator, CommandedPlant, dict[str, float], dict[str, DriveUnits]]:
    """The rack's one plant at its initial pose, each axis's k_t (N m/A) and drive units.

    Raises:
        ConfigError: an axis the robot does not have, or an initial position outside its end
            stops.
    """
    axis_names = robot.axis_names
    for axis_config in config.axes:
        if axis_config.name not in axis_names:
            raise ConfigError(
                config.source,
                f"axes.{axis_config.name}",
                f"the robot has no such axis (axes: {', '.join(axis_names)})",
            )
    k_t = {
        a.name: robot.axes[axis_names.index(a.name)].motor.torque_constant_nm_per_a
        for a in config.axes
    }
    units = {a.name: drive_units(config, a, k_t[a.name]) for a in config.axes}
    # Rated torque is k_t x rated current, so 0x6072 (per mille of 0x6076) is the same per
    # mille of 0x6075: the most current a drive may set (the codec's 0x6078 scaling).
    peak_current_a = max(
        codec.current(units[a.name]).decode(a.max_torque_permille) for a in config.axes
    )
    built = build_plant(
        PlantConfig(
            robot=robot,
            dt_s=config.dt_s,
            rigid_body_update_steps=config.rigid_body_update_steps,
            joints=config.axis_names,
            interface=CURRENT,
            current_kp_v_per_a=config.current_kp_v_per_a,
            current_ti_s=config.current_ti_s,
            max_abs_command=2.0 * peak_current_a,
            current_limit_a=peak_current_a,
        )
    )
    sim, plant = built.sim, built.commanded
    try:
        sim.reset({a.name: a.initial_position for a in config.axes})
    except InputError as exc:
        raise ConfigError(config.source, "axes", f"expected a valid pose ({exc})") from exc
    return sim, plant, k_t, units


def _build_drive(
    config: RackConfig,
    axis_config: AxisConfig,
    joint_index: int,
    sim: Simulator,
    robot: RobotParams,
    eds: str,
    k_t: dict[str, float],
    units: dict[str, DriveUnits],
) -> Drive:
    """One drive: its canopen node over the EDS, and its loops (`rack_modes`)."""
    plant_index = sim.axis_names.index(axis_config.name)
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
    limit_a = axis.current.decode(axis_config.max_torque_permille)
    loop_params = DriveLoopParams(
        PIParams(config.velocity_kp_a_per_rad_s, config.velocity_ti_s, -limit_a, limit_a),
        position_kp_per_s=config.position_kp_per_s,
        velocity_limit=config.velocity_limit,
    )
    axis.modes = AxisModes(
        loop_params,
        codec.increments_per_joint_unit(axis.units, axis.gear_ratio),
        sim.position_limits[plant_index],
    )
    return axis
