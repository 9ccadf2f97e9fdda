r"""The CAN bridge node: `ros2 run lca_hil can_bridge` (console script `lca-can-bridge`).

Swaps the simulator node for CiA 402 drives on a CAN bus, with the same topics (the plant
contract, `lca_control.contract`): it takes `current_commands` from the controller and publishes
`joint_states`, `motor_states`, `drive_chain_states` and `/diagnostics` through the contract's
builder (`lca_sim.ros.plant_contract`). Each complete SYNC cycle becomes one `PlantSnapshot`
(`plant_snapshot`): what the drives do not report (a real drive: the drive and motion states,
the efficiencies, the load and friction torques, the voltage) is NaN or `unknown`. The CANopen
master itself is `lca_sim.canbus.master.Cia402Master`.

    lca-can-bridge --ros-args --params-file config/ros/can_bridge.yaml           # virtual rack
    lca-can-bridge --ros-args --params-file config/ros/can_bridge.yaml \\
        -p interface:=socketcan -p channel:=can0                               # a real bus

With `interface: virtual` the node also starts the virtual drive rack
(`lca_sim.canbus.virtual_rack`) in its own process, on python-can's in-process virtual bus.

Services (std_srvs/Trigger, named like ros2_canopen's CiA 402 driver): `~/init`, `~/enable`,
`~/disable`, `~/halt`, `~/recover`, `~/cyclic_torque_mode`. SDO access for diagnosis, with
rcl_interfaces types (an ament_python package cannot define its own): `~/sdo_read`
(GetParameters; names `<joint>/<index>[/<subindex>]`, e.g. `pivot/0x6041`, `lift/0x1400/5`)
and `~/sdo_write` (SetParameters; the same names, integer or double values).

A managed node (lifecycle_msgs services `~/change_state`, `~/get_state`, ...): configure opens
the bus and configures the drives over SDO, activate enables them, deactivate takes them out of
operation with zero torque, cleanup closes the bus. With `autostart` (the default) it configures
and activates itself at start-up; docs/can.md ("The bridge as a managed node").
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import canopen
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import ParameterType, ParameterValue, SetParametersResult
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from lca_control import contract as ri
from lca_control.contract import FloatArray, PlantSnapshot
from lca_control.parameters import ParameterError
from lca_sim.canbus import emcy
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.lockstep import CycleClock, LockstepLoop
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_params import BridgeError, BridgeParams
from lca_sim.canbus.master_state import AxisState, Snapshot
from lca_sim.cia402 import objects as od
from lca_sim.cia402.bus_load import bus_load_pct
from lca_sim.cia402.device import MODE_CST, PowerState
from lca_sim.config.loader import config_dir, load_robot
from lca_sim.errors import FILE_NOT_FOUND, USER_ERRORS, ConfigError
from lca_sim.ros.can_bridge_params import (
    CAN_BRIDGE_PARAMETERS,
    CanBridgeNodeParams,
    validate_can_bridge_params,
)
from lca_sim.ros.node_util import LiveParameters, declare_table, run_node, status
from lca_sim.ros.plant_contract import (
    JointCommand,
    PlantPublisher,
    qos_profile,
    read_joint_command,
    worst_first,
)
from lca_sim.runtime import GIL_SWITCH_INTERVAL_S, settle_heap

if TYPE_CHECKING:
    from lca_sim.canbus.virtual_rack import VirtualDriveRack

# More than this share of the cycles sending the previous command again is a WARN.
LATE_COMMAND_SHARE = 0.05
SDO_ERRORS = (ValueError, KeyError, canopen.SdoAbortedError, canopen.SdoCommunicationError)
# How long the master's notifier waits in one receive on the linked virtual bus, s.
NOTIFIER_POLL_S = 0.05
# Lockstep: how often the node looks whether to start the loop, re-send a state or give up on
# an incomplete cycle, s (wall time).
LOCKSTEP_TICK_S = 0.05
# How long shutdown and error processing wait for the drives to leave OPERATION ENABLED: a
# disable is one cycle, its statusword the next slow TPDO (50 Hz by default).
TORQUE_FREE_TIMEOUT_S = 0.5


def _parameter_value(raw: object) -> ParameterValue:
    """An SDO value (or an error text) as an rcl_interfaces ParameterValue."""
    if isinstance(raw, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=raw)
    if isinstance(raw, int):
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=raw)
    if isinstance(raw, float):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=raw)
    return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=str(raw))


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


def _axis_row(a: AxisState) -> tuple[float, ...]:
    """One drive's values in `plant_snapshot`'s row order."""
    return (
        a.position,
        a.velocity,
        a.motor_position_rad,
        a.motor_velocity_rad_s,
        a.current_a,
        a.motion_state,
        a.drive_state,
        a.eta_m,
        a.eta_l,
        a.load_torque_nm,
        a.friction_torque_nm,
        a.voltage_v,
    )


def plant_snapshot(
    snap: Snapshot,
    joints: tuple[str, ...],
    torque_constants_nm_per_a: FloatArray,
    gear_ratios: FloatArray,
    state_names: tuple[str, ...],
    decoded: frozenset[str],
) -> PlantSnapshot:
    """One SYNC cycle of the drives as the plant contract's snapshot.

    effort = k_t * i * N (joint side), motor torque = k_t * i (motor side, k_t from the robot
    config). A field the drives' TPDOs do not fill (`decoded`: `Cia402Master.decoded_fields`)
    is unknown: the efficiencies, torques and voltage stay NaN (`AxisState`'s default), the drive
    state code becomes NaN, and the motion state is NaN unless it is mapped and has been
    reported (the drive-state code is -1 until the first drive-chain TPDO, and the motion code,
    0 by default, would read as `stop` before it).
    """
    rows = np.array([_axis_row(a) for a in snap.axes], dtype=np.float64).T
    position, velocity, motor_position, motor_velocity, current, motion, drive = rows[:7]
    if "drive_state" not in decoded:
        drive = np.full_like(drive, np.nan)
    if "motion_state" not in decoded:
        motion = np.full_like(motion, np.nan)
    elif "drive_state" in decoded:
        motion = np.where(drive >= 0.0, motion, np.nan)
    motor_torque = current * torque_constants_nm_per_a
    return PlantSnapshot(
        stamp_s=snap.sync_wall_s,
        joints=joints,
        position=position,
        velocity=velocity,
        effort=motor_torque * gear_ratios,
        motor_position_rad=motor_position,
        motor_velocity_rad_s=motor_velocity,
        current_a=current,
        motion_state=motion,
        drive_state=drive,
        state_names=state_names,
        eta_m=rows[7],
        eta_l=rows[8],
        motor_torque_nm=motor_torque,
        load_torque_nm=rows[9],
        friction_torque_nm=rows[10],
        voltage_v=rows[11],
    )


def parse_object_name(name: str) -> tuple[str, int, int]:
    """`pivot/0x6041` or `lift/0x1400/5` -> (joint, index, subindex)."""
    parts = name.split("/")
    if len(parts) not in (2, 3):
        raise ValueError(f"expected <joint>/<index>[/<subindex>], got {name!r}")
    index = int(parts[1], 0)
    subindex = int(parts[2], 0) if len(parts) == 3 else 0
    if not (0 <= index <= 0xFFFF and 0 <= subindex <= 0xFF):
        raise ValueError(f"index or subindex out of range in {name!r}")
    return parts[0], index, subindex


class CanBridgeNode(LifecycleNode):
    """Publishes the drives' states and sends them the controller's current commands.

    A managed node (ROS 2 "Managed nodes" design, rclpy.lifecycle): configure opens the bus
    (and, with `interface: virtual`, starts the rack), starts the CANopen master and configures
    the drives over SDO; activate enables them and starts publishing and commanding; deactivate
    takes them out of operation with zero torque and stops both; cleanup closes the bus;
    shutdown and error processing leave the drives torque-free and close it. With `autostart`
    (the default) the node configures and activates itself at start-up, so a plain start comes
    up active; `auto_init` and `auto_enable` then say whether that start configures and enables
    the drives, as before there was a lifecycle. The services, topics and parameters exist in
    every state; a service that needs the drives says so when they are not there.
    """

    def __init__(self, node_name: str = "can_bridge", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self._master: Cia402Master | None = None  # the CANopen master, while configured
        self.network: canopen.Network | None = None
        self._bus: can.BusABC | None = None
        self._rack: VirtualDriveRack | None = None
        self._rack_bus: can.BusABC | None = None
        self._live = LiveParameters(
            self,
            CAN_BRIDGE_PARAMETERS,
            declare_table(self, CAN_BRIDGE_PARAMETERS),
            validate_can_bridge_params,
            self._apply_params,
        )
        p = self.params
        # The cycle thread, the notifier threads (and with `virtual` the rack's) share the GIL
        # with the executor; Python's default 5 ms switch interval lets one of them hold it
        # for several CAN periods. 0.5 ms keeps the 500 Hz cycle regular.
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        self._robot = load_robot(p.robot)
        self._eds = Path(p.eds) if p.eds else config_dir() / "can" / "lca_drive.eds"
        if not self._eds.is_file():
            raise ConfigError("parameters", "eds", f"{FILE_NOT_FOUND}: {self._eds}")
        axes = {a.name: a for a in self._robot.axes}
        self._torque_constants = np.array(
            [axes[j].motor.torque_constant_nm_per_a for j in p.joints], dtype=np.float64
        )
        self._gear_ratios = np.array([axes[j].gear_ratio for j in p.joints], dtype=np.float64)
        self._state_names = self._robot.state_machine.state_names
        self._velocity_axes = tuple(
            j for j, m in zip(p.joints, p.modes, strict=False) if m == "csv"
        )
        self._active = False  # lifecycle ACTIVE: states published, commands passed on
        self._autostarting = False  # inside the start-up's configure and activate
        self._startup_error: Exception | None = None  # a user error of that start-up
        self._drives_configured = False  # the last init() succeeded
        self._init_error = ""  # why the last init() failed
        self._transition_error = ""  # why the last transition failed, until one succeeds
        self._published = 0
        self._wrong_interface = 0
        self._ignored_inactive = 0  # commands that came while not active
        self._commands_lost = False  # the controller peer, as /diagnostics reports it
        self._command_losses = 0
        self._last_diag_t = time.monotonic()
        self._last_frames_bits = (0, 0)  # frames and bits at the previous diagnostics
        self._last_command_timing = (0, 0)  # commands in time and late, at the previous one
        self._init_lock = threading.Lock()
        # Lockstep (`timing_mode`): the loop that sends one SYNC per command, its clock, and
        # the last state handed on (sent again to a silent controller).
        self._lockstep = p.timing_mode == "lockstep"
        self._loop: LockstepLoop | None = None
        self._last_plant: PlantSnapshot | None = None
        self._create_interfaces(p)
        drives = dict(zip(p.joints, p.node_ids, strict=True))
        self.get_logger().info(
            f"{p.interface} bus {p.channel!r}, drives {drives}, {p.cycle_hz:g} Hz, EDS {self._eds}"
        )
        if p.autostart:
            self._autostart()
        else:
            self.get_logger().info("unconfigured: waiting for a lifecycle manager (configure)")

    def _create_interfaces(self, p: CanBridgeNodeParams) -> None:
        """Publishers, subscriptions, services and the diagnostics timer (every state)."""
        self._plant = PlantPublisher(
            self, p.joints, clock=self._lockstep, joint_state_topic=p.joint_state_topic
        )
        command_qos = qos_profile(ri.COMMAND_QOS)
        self.create_subscription(
            Float64MultiArray, ri.CURRENT_COMMANDS, self._on_command, command_qos
        )
        self.create_subscription(
            Float64MultiArray, ri.VOLTAGE_COMMANDS, self._on_voltage_command, command_qos
        )
        if self._velocity_axes:  # CSV axes close their velocity loop in the drive
            self.create_subscription(
                Float64MultiArray, ri.VELOCITY_COMMANDS, self._on_velocity_command, command_qos
            )
        # ros2_control's topic-based interface: the commands in force, joint order, so a
        # JointState naming some joints leaves the others as they are.
        self._held_current_a = np.zeros(len(p.joints))
        self._held_velocity = np.zeros(len(p.joints))
        self._effort_to_current = (
            np.ones(len(p.joints))
            if p.joint_command_effort == "current"
            else 1.0 / (self._torque_constants * self._gear_ratios)
        )
        self.joint_command_counts = {"accepted": 0, "refused": 0, "unknown_names": 0}
        if p.joint_command_topic:
            self.create_subscription(
                JointState, p.joint_command_topic, self._on_joint_command, command_qos
            )
        for name, handler in (
            ("init", self._srv_init),
            ("enable", self._srv_enable),
            ("disable", self._srv_disable),
            ("halt", self._srv_halt),
            ("recover", self._srv_recover),
            ("cyclic_torque_mode", self._srv_cst),
        ):
            self.create_service(Trigger, f"~/{name}", handler)
        self.create_service(GetParameters, "~/sdo_read", self._srv_sdo_read)
        self.create_service(SetParameters, "~/sdo_write", self._srv_sdo_write)
        self._diag_timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        if self._lockstep:
            self._kick_timer = self.create_timer(LOCKSTEP_TICK_S, self._lockstep_tick)

    @property
    def params(self) -> CanBridgeNodeParams:
        """The parameters in force (a live set replaces them as a whole)."""
        return self._live.params

    @property
    def lifecycle_state(self) -> str:
        """The lifecycle state's label (unconfigured, inactive, active, finalized).

        While a transition runs, its own label (configuring, activating, ...).
        """
        label: str = self._state_machine.current_state[1]
        return label

    @property
    def bridge(self) -> Cia402Master:
        """The CANopen master (configured: inactive or active).

        Raises:
            RuntimeError: the node is not configured (no bus open).
        """
        return self._configured()

    @property
    def master(self) -> Cia402Master | None:
        """The CANopen master while configured, else None."""
        return self._master

    @property
    def rack(self) -> VirtualDriveRack | None:
        """The virtual drive rack this node runs (`interface: virtual`, while configured)."""
        return self._rack

    def _apply_params(
        self, old: CanBridgeNodeParams, new: CanBridgeNodeParams, changed: frozenset[str]
    ) -> None:
        """A live set of the bridge's safety timing: in force from the next cycle.

        The cycle thread reads `Cia402Master.params` once per cycle, so one reference swap
        hands it the new values whole. Read-only parameters never get here. Unconfigured, the
        next configure builds the master from the new values.
        """
        bridge = getattr(self, "_master", None)
        if bridge is not None:
            try:
                bridge.params = replace(
                    bridge.params,
                    command_timeout_s=new.command_timeout_s,
                    quick_stop_after_s=new.quick_stop_after_s,
                    stale_timeout_s=new.stale_timeout_s,
                    max_send_failures=new.max_send_failures,
                )
            except ValueError as exc:
                raise ParameterError(
                    ", ".join(sorted(changed)), f"values the CANopen master takes ({exc})"
                ) from exc
        if new.diagnostics_period_s != old.diagnostics_period_s:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(
                new.diagnostics_period_s, self._publish_diagnostics
            )

    # --- the lifecycle -------------------------------------------------------------------

    def _autostart(self) -> None:
        """Configure, then activate: a plain start without a lifecycle manager (`autostart`).

        A user error on the way (a bus that cannot be opened) is raised from here, so the
        console script reports it in one line and exits 2, as before the lifecycle.
        """
        self._autostarting = True
        try:
            if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
                self.trigger_activate()
        finally:
            self._autostarting = False
        error, self._startup_error = self._startup_error, None
        if error is not None:
            self.destroy_node()
            raise error

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the bus (and start the virtual rack), start the master, configure the drives."""
        return self._transition("configure", self._configure)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Enable the drives (CiA 402 enable operation); publish states, pass commands on."""
        return self._transition("activate", self._activate)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop commanding; the drives leave operation with zero torque."""
        return self._transition("deactivate", self._deactivate)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the cycle, close the master's network and the bus, stop the rack."""
        return self._transition("cleanup", self._teardown)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Leave the drives torque-free and close the bus, from any state."""
        return self._transition("shutdown", self._teardown_torque_free, clears_error=False)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised: leave the drives torque-free, close the bus: unconfigured."""
        return self._transition("error processing", self._teardown_torque_free, False)

    def _transition(
        self, name: str, body: Callable[[], str], clears_error: bool = True
    ) -> TransitionCallbackReturn:
        """Run one transition: its body returns '' (done) or why it failed.

        Failures are logged and shown on /diagnostics (ERROR) until a transition succeeds.
        An exception that is not a user error is logged here (rclpy would turn it into ERROR
        without a word) and returns ERROR, which runs `on_error`.
        """
        try:
            reason = body()
        except USER_ERRORS as exc:
            reason = str(exc)
            if self._autostarting:
                self._startup_error = exc  # raised by _autostart: one line, exit 2
        except Exception as exc:  # logged here, then rclpy's error processing
            self._transition_error = f"{name} raised {type(exc).__name__}: {exc}"
            self.get_logger().error(self._transition_error)
            return TransitionCallbackReturn.ERROR
        if reason:
            self._transition_error = f"{name} failed: {reason}"
            if self._startup_error is None:
                self.get_logger().error(f"lifecycle: {self._transition_error}")
            return TransitionCallbackReturn.FAILURE
        if clears_error:
            self._transition_error = ""
        self.get_logger().info(f"lifecycle: {name} done")
        return TransitionCallbackReturn.SUCCESS

    def _configure(self) -> str:
        p = self.params
        try:
            self._open(p)
        except Exception:
            self._teardown()
            raise
        if self._autostarting and not p.auto_init:
            self.get_logger().info("auto_init false: the drives wait for ~/init")
            return ""
        message = self._init()
        if not message:
            return ""
        if self._autostarting:  # a plain start stays up as it always did, to retry ~/init
            self.get_logger().error(f"init failed: {message} (retry with ~/init)")
            return ""
        self._teardown()
        return f"init failed: {message}"

    def _open(self, p: CanBridgeNodeParams) -> None:
        virtual = p.interface == "virtual"
        bus = (
            LinkedVirtualBus(channel=p.channel)
            if virtual
            else open_bus(p.interface, p.channel, p.bitrate)
        )
        self._bus = bus
        if virtual:
            self._start_rack(p)
        self.network = canopen.Network(bus)
        if virtual:
            # Over the link no frame of the rack comes through the queue, so the notifier's
            # receive would wait its whole poll (canopen's 1 s) before a disconnect ends it,
            # long enough for the rack's RPDO deadline to fire at shutdown.
            self.network.NOTIFIER_CYCLE = NOTIFIER_POLL_S
        self.network.connect()
        if isinstance(bus, LinkedVirtualBus) and self.network.notifier is not None:
            # The rack's frames reach the master in the rack's thread, and the master's the
            # rack in the master's: no copy, queue or thread hand-over per frame.
            bus.attach(self.network.notifier.listeners)
        if not self._lockstep:
            self._master = Cia402Master(
                self.network, self._bridge_params(p), self._eds, on_state=self._on_state
            )
            return
        clock = CycleClock(1.0 / p.cycle_hz)
        master = Cia402Master(
            self.network,
            self._bridge_params(p),
            self._eds,
            on_state=self._on_state,
            clock=clock.now,
            stamp_clock=clock.now,
        )
        self._master = master
        self._loop = LockstepLoop(clock, master.cycle, p.lockstep_resend_s)

    def _bridge_params(self, p: CanBridgeNodeParams) -> BridgeParams:
        return BridgeParams(
            joints=p.joints,
            node_ids=p.node_ids,
            torque_constants_nm_per_a=tuple(float(k) for k in self._torque_constants),
            gear_ratios=tuple(float(n) for n in self._gear_ratios),
            drive_state_names=self._state_names,
            master_node_id=p.master_node_id,
            cycle_hz=p.cycle_hz,
            bitrate_bit_s=float(p.bitrate),
            command_timeout_s=p.command_timeout_s,
            quick_stop_after_s=p.quick_stop_after_s,
            stale_timeout_s=p.stale_timeout_s,
            heartbeat_producer_ms=p.heartbeat_producer_ms,
            heartbeat_consumer_ms=p.heartbeat_consumer_ms,
            rpdo_deadline_ms=p.rpdo_deadline_ms,
            max_send_failures=p.max_send_failures,
            pdo_layout=p.pdo_layout,
            modes=p.modes,
            slow_tpdo_rate_hz=p.slow_tpdo_rate_hz,
        )

    def _activate(self) -> str:
        """Enable the drives, then pass commands on and publish.

        CiA 402-2 (IEC 61800-7-201) drive state machine: the master walks each drive with the
        controlwords shutdown 0x0006, switch on 0x0007, enable operation 0x000F (transitions
        2, 3, 4) to OPERATION ENABLED, one legal step per cycle
        (`lca_sim.cia402.master.next_controlword`).
        """
        bridge = self._configured()
        if self._autostarting and not (self.params.auto_enable and self._drives_configured):
            self._active = True  # a plain start without auto_enable: ~/enable later
            return ""
        if not self._drives_configured:
            return "the drives are not configured: ~/init first"
        message = bridge.enable(True)
        if message != "enabling" and not self._autostarting:
            return message  # a latch (EMCY, stale drive, bus-off): ~/recover first
        self.get_logger().info(message)
        self._active = True
        return ""

    def _deactivate(self) -> str:
        """Stop passing commands on; take the drives out of operation with zero torque.

        CiA 402-2 drive state machine transition 5, disable operation (controlword 0x0007):
        OPERATION ENABLED to SWITCHED ON, the drive function off (CST: no torque; a real drive
        brakes per its 0x605C), then transition 6, shutdown (0x0006), to READY TO SWITCH ON,
        where the master holds the drives until the next activate. Unlike `~/halt`
        (controlword bit 8, the drive still enabled) this leaves no enabled drive waiting for
        commands, so the master's command-silence watch, which would quick-stop a halted but
        enabled drive, stays quiet while the node is inactive.
        """
        self._active = False
        self._configured().enable(False)
        return ""

    def _configured(self) -> Cia402Master:
        if self._master is None:
            raise RuntimeError("the CANopen master is not running (node unconfigured)")
        return self._master

    def _teardown_torque_free(self) -> str:
        self._torque_free()
        return self._teardown()

    def _torque_free(self) -> None:
        """Disable every drive and wait, bounded, until none is in OPERATION ENABLED.

        CiA 402-2 transition 5 (disable operation, controlword 0x0007), then 6 (shutdown): no
        torque. A drive that does not answer is left to its own watchdogs (heartbeat consumer,
        RPDO deadline: its 0x6007 reaction once the cycle stops).
        """
        self._active = False
        bridge = self._master
        if bridge is None or not self._drives_configured:
            return
        bridge.enable(False)
        # Judged on statuswords sent after the disable: the slow TPDO that carries them goes
        # every `slow_tpdo_every`-th SYNC, so a state read before that may predate it.
        fresh_from = bridge.counters.cycles + bridge.params.slow_tpdo_every + 2
        deadline = time.monotonic() + TORQUE_FREE_TIMEOUT_S
        while True:
            enabled = [
                j
                for j in self.params.joints
                if bridge.axis_state(j).power_state is PowerState.OPERATION_ENABLED
            ]
            fresh = bridge.counters.cycles >= fresh_from
            if (fresh and not enabled) or time.monotonic() > deadline:
                break
            if self._loop is not None and self._loop.started:
                self._loop.sync_now()  # lockstep: no cycle runs unless sent
            time.sleep(0.005)
        if enabled:
            self.get_logger().warning(
                f"drives {enabled} still report operation enabled after "
                f"{TORQUE_FREE_TIMEOUT_S:g} s; their watchdogs take over"
            )

    def _teardown(self) -> str:
        """Stop the cycle (the drives' watchdogs then react), close the bus, stop the rack."""
        self._active = False
        self._drives_configured = False
        bridge, self._master = self._master, None
        network, self.network = self.network, None
        bus, self._bus = self._bus, None
        rack, self._rack = self._rack, None
        rack_bus, self._rack_bus = self._rack_bus, None
        try:
            if bridge is not None:
                bridge.stop()
            if network is not None and network.bus is not None:
                network.disconnect()  # its notifier, then the bus
            elif bus is not None:
                self._close_bus(bus)
        finally:
            if rack is not None:
                rack.stop()
            if rack_bus is not None:
                self._close_bus(rack_bus)
        return ""

    # --- set-up and tear-down ------------------------------------------------------------

    def _start_rack(self, p: CanBridgeNodeParams) -> None:
        from lca_sim.canbus.virtual_rack import VirtualDriveRack  # noqa: PLC0415
        from lca_sim.config.rack import load_rack_config  # noqa: PLC0415

        config = load_rack_config(Path(p.rack_config) if p.rack_config else None)
        config = replace(config, timing_mode=p.timing_mode)  # one clock for the whole loop
        self._rack_bus = LinkedVirtualBus(channel=p.channel)
        self._rack = VirtualDriveRack(self._rack_bus, config)
        self._rack.start()

    def _init(self) -> str:
        """Configure and start the drives, then the cycle; '' or the error."""
        bridge = self._configured()
        with self._init_lock:
            bridge.stop()
            try:
                bridge.init()
            except BridgeError as exc:
                self._drives_configured, self._init_error = False, str(exc)
                return str(exc)
            settle_heap()  # before the cycle runs: a full collection would stall it
            if not self._lockstep:
                bridge.start()  # lockstep: the loop sends the SYNCs (`_lockstep_tick`)
            self._drives_configured, self._init_error = True, ""
            return ""

    def destroy_node(self) -> None:
        """Leave the drives torque-free and close the buses (as on shutdown), then destroy."""
        self._torque_free()
        self._teardown()
        super().destroy_node()

    @staticmethod
    def _close_bus(bus: can.BusABC) -> None:
        with contextlib.suppress(can.CanError):
            bus.shutdown()

    # --- topics --------------------------------------------------------------------------

    def _commanding(self) -> Cia402Master | None:
        """The master, when the node is active; else None, the command counted and warned."""
        if self._active and self._master is not None:
            return self._master
        self._ignored_inactive += 1
        self.get_logger().warning(
            f"ignoring commands while {self.lifecycle_state} ({self._ignored_inactive} so far): "
            "activate the node",
            throttle_duration_sec=5.0,
        )
        return None

    def _on_command(self, msg: Float64MultiArray) -> None:
        bridge = self._commanding()
        if bridge is not None:
            self._set_currents(bridge, list(msg.data))
            if not self._velocity_axes:
                self._lockstep_command()

    def _lockstep_command(self) -> None:
        """Lockstep: the controller's answer (taken or refused) releases the next SYNC.

        The answer is the last message the controller sends per state: current_commands, or
        with CSV axes the velocity_commands it publishes after them (the currents are then in
        force already), or one JointState command.
        """
        if self._loop is not None:
            self._loop.on_command(time.monotonic())

    def _set_currents(self, bridge: Cia402Master, currents_a: list[float]) -> None:
        reason = bridge.set_currents(currents_a)
        if reason is None:
            self._held_current_a[:] = currents_a
        else:
            self.get_logger().warning(
                f"command rejected ({bridge.counters.commands_rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )

    def _on_velocity_command(self, msg: Float64MultiArray) -> None:
        bridge = self._commanding()
        if bridge is not None:
            self._set_velocities(bridge, list(msg.data))
            self._lockstep_command()

    def _set_velocities(self, bridge: Cia402Master, velocities: list[float]) -> None:
        reason = bridge.set_velocities(velocities)
        if reason is None:
            self._held_velocity[:] = velocities
        else:
            self.get_logger().warning(
                f"velocity command rejected ({bridge.counters.commands_rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )

    def _on_joint_command(self, msg: JointState) -> None:
        """A JointState command (docs/ros2_control.md), each joint by its drive's mode.

        A cst joint takes its effort entry (A, or joint torque per `joint_command_effort`),
        a csv joint its velocity entry (the drive closes the loop); joints not named, or with
        NaN, keep their command. The entry of the other field is ignored when zero (what the
        interface sends for an interface no controller claims) and refused when not.
        """
        bridge = self._commanding()
        if bridge is None:
            return
        p = self.params
        counts = self.joint_command_counts
        cmd = read_joint_command(msg.name, msg.velocity, msg.effort, p.joints)
        counts["unknown_names"] += len(cmd.unknown)
        csv = set(self._velocity_axes)
        problems = self._joint_command_problems(cmd, csv)
        efforts = [j for j in p.joints if j in cmd.effort and j not in csv]
        velocities = [j for j in p.joints if j in cmd.velocity and j in csv]
        if cmd.error or not (efforts or velocities):
            counts["refused"] += 1
        else:
            counts["accepted"] += 1
            if efforts:
                currents = self._held_current_a.tolist()
                for k, joint in enumerate(p.joints):
                    if joint in efforts:
                        currents[k] = cmd.effort[joint] * float(self._effort_to_current[k])
                self._set_currents(bridge, currents)
            if velocities:
                wanted = self._held_velocity.tolist()
                for k, joint in enumerate(p.joints):
                    if joint in velocities:
                        wanted[k] = cmd.velocity[joint]
                self._set_velocities(bridge, wanted)
        if problems:
            self.get_logger().warning(
                f"{p.joint_command_topic}: {'; '.join(problems)} ({counts['refused']} refused, "
                f"{counts['unknown_names']} unknown names so far)",
                throttle_duration_sec=1.0,
            )
        self._lockstep_command()

    def _joint_command_problems(self, cmd: JointCommand, csv: set[str]) -> list[str]:
        """What to warn about in a JointState command (empty: nothing)."""
        problems: list[str] = []
        if cmd.unknown:
            problems.append(
                f"unknown joints {list(cmd.unknown)} (this node's: {list(self.params.joints)})"
            )
        if cmd.error:
            problems.append(cmd.error)
        no_loop = sorted(j for j, v in cmd.velocity.items() if v != 0.0 and j not in csv)
        if no_loop:
            problems.append(f"velocity for {no_loop}: their drives run cst (modes), send effort")
        no_effort = sorted(j for j, v in cmd.effort.items() if v != 0.0 and j in csv)
        if no_effort:
            problems.append(f"effort for {no_effort}: their drives run csv (modes), send velocity")
        return problems

    def _on_voltage_command(self, msg: Float64MultiArray) -> None:
        self._wrong_interface += 1
        self.get_logger().warning(
            f"ignoring voltage commands ({self._wrong_interface} so far): CiA 402 drives take "
            "torque; run the controller with command_interface: current",
            throttle_duration_sec=5.0,
        )

    def _on_state(self, snap: Snapshot) -> None:
        """A complete cycle (notifier thread): publish it while active.

        rclpy publishers are thread-safe. Inactive, the node publishes nothing but
        /diagnostics, as a LifecyclePublisher would.
        """
        bridge = self._master
        if not self._active or bridge is None:
            return
        plant = plant_snapshot(
            snap,
            self._plant.joints,
            self._torque_constants,
            self._gear_ratios,
            self._state_names,
            bridge.decoded_fields(),
        )
        if self._loop is not None:  # waiting before the state goes: the answer may be quick
            self._last_plant = plant
            self._loop.on_state(time.monotonic())
        self._plant.publish(plant)
        self._published += 1

    def _lockstep_tick(self) -> None:
        """Lockstep: start the loop once the controller listens; keep it going when stuck.

        The first SYNC goes once the node is active with its drives configured and
        `lockstep_subscribers` subscribers of joint_states have matched (as the simulator's
        lockstep start). A controller silent for `lockstep_resend_s` gets the last state again
        (it ignores a stamp it has seen); a cycle incomplete for as long (a TPDO lost) is
        given up and the next SYNC sent, so the master's stall watch judges it in SYNCs.
        """
        loop = self._loop
        if loop is None or not (self._active and self._drives_configured):
            return
        wall_s = time.monotonic()
        if not loop.started:
            p = self.params
            if self._plant.joint_pub.get_subscription_count() >= p.lockstep_subscribers:
                loop.start(wall_s)
            return
        action = loop.on_tick(wall_s)
        if action == "resend" and self._last_plant is not None:
            self._plant.publish(self._last_plant)
        elif action == "incomplete":
            self.get_logger().warning(
                f"lockstep: no complete cycle for {loop.resend_s:g} s; the next SYNC goes "
                f"({loop.counters.incomplete_cycles} so far)",
                throttle_duration_sec=5.0,
            )

    # --- services ------------------------------------------------------------------------

    def _need_bridge(self, res: Trigger.Response) -> Cia402Master | None:
        """The master, or None with the response saying the node is not configured."""
        if self._master is None:
            res.success = False
            res.message = f"node {self.lifecycle_state}: configure it first (lifecycle)"
        return self._master

    def _srv_init(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        if self._need_bridge(res) is None:
            return res
        message = self._init()
        res.success = not message
        res.message = message or "drives configured and operational; call ~/enable"
        return res

    def _srv_enable(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        bridge = self._need_bridge(res)
        if bridge is None:
            return res
        if not self._active:  # an inactive node does not run the drives
            res.success = False
            res.message = f"node {self.lifecycle_state}: activate it (lifecycle) to enable"
            return res
        res.message = bridge.enable(True)
        res.success = res.message == "enabling"
        return res

    def _srv_disable(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        bridge = self._need_bridge(res)
        if bridge is not None:
            res.message = bridge.enable(False)
            res.success = True
        return res

    def _srv_halt(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        bridge = self._need_bridge(res)
        if bridge is not None:
            bridge.halt()
            res.success, res.message = True, "halted: zero torque until the next ~/enable"
        return res

    def _srv_recover(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        bridge = self._need_bridge(res)
        if bridge is not None:
            bridge.recover()
            res.success, res.message = True, "latches cleared, faults reset; call ~/enable"
        return res

    def _srv_cst(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        bridge = self._need_bridge(res)
        if bridge is None:
            return res
        try:
            for joint in self.params.joints:
                bridge.sdo_write(joint, od.MODES_OF_OPERATION, 0, MODE_CST)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            res.success, res.message = False, f"mode {MODE_CST} refused: {exc}"
            return res
        res.success = True
        res.message = f"cyclic synchronous torque (mode {MODE_CST}) on every drive"
        return res

    def _srv_sdo_read(
        self, req: GetParameters.Request, res: GetParameters.Response
    ) -> GetParameters.Response:
        for name in req.names:
            try:
                joint, index, subindex = parse_object_name(name)
                raw = self._sdo_master().sdo_read(joint, index, subindex)
            except SDO_ERRORS as exc:
                raw = f"error: {exc}"
            res.values.append(_parameter_value(raw))
        return res

    def _sdo_master(self) -> Cia402Master:
        """The master for SDO access; ValueError (an SDO error to the caller) unconfigured."""
        if self._master is None:
            raise ValueError(f"node {self.lifecycle_state}: configure it first (lifecycle)")
        return self._master

    def _srv_sdo_write(
        self, req: SetParameters.Request, res: SetParameters.Response
    ) -> SetParameters.Response:
        for param in req.parameters:
            result = SetParametersResult(successful=True)
            try:
                joint, index, subindex = parse_object_name(param.name)
                v = param.value
                if v.type == ParameterType.PARAMETER_INTEGER:
                    self._sdo_master().sdo_write(joint, index, subindex, int(v.integer_value))
                elif v.type == ParameterType.PARAMETER_DOUBLE:
                    self._sdo_master().sdo_write(joint, index, subindex, float(v.double_value))
                else:
                    raise ValueError("only integer or double values can be written")
            except SDO_ERRORS as exc:
                result = SetParametersResult(successful=False, reason=str(exc))
            res.results.append(result)
        return res

    # --- diagnostics ---------------------------------------------------------------------

    def _axis_status(
        self, bridge: Cia402Master, joint: str, latched: int, advisory: tuple[int, int]
    ) -> DiagnosticStatus:
        """One drive: ERROR with the latched EMCY's text, WARN for an advisory EMCY, else OK.

        The message is the power state, then the EMCY decoded to text (`emcy.describe`).
        """
        s = bridge.axis_state(joint)
        power = s.power_state
        message = power.name.lower() if power else f"statusword 0x{s.statusword:04X}"
        level = DiagnosticStatus.OK
        code, count = advisory
        ours = bridge.has_drive_state()  # lca_hil's drive: its own codes have text
        if code:
            level = DiagnosticStatus.WARN
            message += f"; EMCY {emcy.describe(code, ours)} ({count} received)"
        if latched:
            level = DiagnosticStatus.ERROR
            message += f"; EMCY {emcy.describe(latched, ours)}: stopped until ~/recover"
        return status(
            f"lca_hil/can_bridge/{joint}",
            level,
            message,
            {
                "statusword": f"0x{s.statusword:04X}",
                "emcy_code": f"0x{latched:04X}",
                "emcy_text": emcy.describe(latched, ours) if latched else "none",
                "advisory_emcy": emcy.describe(code, ours) if code else "none",
                "advisory_emcy_count": count,
                "position": s.position,
                "current_a": s.current_a,
            },
        )

    def _command_health(self, bridge: Cia402Master, now: float) -> tuple[bytes, str] | None:
        """The controller peer: WARN while the drives are halted for want of commands.

        ERROR once the silence has lasted into the quick stop, which holds until ~/enable.
        Nothing while the drives are not enabled. Before the first command ever the bridge
        waits for its controller, which is no fault: OK with the master's text. The loss is
        logged once when it begins (by the master, with its reaction) and once here when
        commands return.
        """
        silence = bridge.command_silence(now)
        if silence is None:
            if self._commands_lost:
                self._commands_lost = False
                self.get_logger().info("commands again")
            return None
        latched, why = silence
        if not latched and not bridge.counters.commands_accepted:
            return DiagnosticStatus.OK, why  # waiting for the controller's first command
        if not self._commands_lost and bridge.counters.commands_accepted:
            self._commands_lost = True
            self._command_losses += 1
            self.get_logger().warning(f"{why}; is the controller running?")
        return (DiagnosticStatus.ERROR if latched else DiagnosticStatus.WARN), why

    def _lifecycle_findings(self) -> list[tuple[bytes, str]]:
        """What the lifecycle adds to the bridge's status: a failed transition or init, ERROR."""
        found: list[tuple[bytes, str]] = []
        if self._transition_error:
            found.append((DiagnosticStatus.ERROR, self._transition_error))
        if self._init_error and self._master is not None:
            found.append((DiagnosticStatus.ERROR, f"init failed: {self._init_error} (~/init)"))
        return found

    def _publish_diagnostics(self) -> None:
        bridge = self._master
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        if bridge is None:
            array.status.append(self._unconfigured_status())
        else:
            array.status.append(self._bridge_status(bridge))
            codes = bridge.emcy_codes()
            advisory = bridge.advisory_emcy()
            for joint in self.params.joints:
                array.status.append(self._axis_status(bridge, joint, codes[joint], advisory[joint]))
        self._plant.publish_diagnostics(array)

    def _unconfigured_status(self) -> DiagnosticStatus:
        """The bridge's status with no bus open: the lifecycle state, or the failure."""
        state = self.lifecycle_state
        found = [(DiagnosticStatus.OK, f"{state}: no bus open; configure (lifecycle) to start")]
        level, message = worst_first([*found, *self._lifecycle_findings()])
        values: dict[str, object] = {
            "lifecycle_state": state,
            "interface": self.params.interface,
            "channel": self.params.channel,
            "cycle_hz": self.params.cycle_hz,
        }
        return status("lca_hil/can_bridge", level, message, values)

    def _late_commands(self, in_time: int, late: int) -> tuple[bytes, str] | None:
        """WARN while too many cycles of the last diagnostics period sent an old command.

        More than LATE_COMMAND_SHARE of the cycles sent the previous command again (the
        controller's answer came after the SYNC it was for): the loop then runs with two
        periods of delay instead of one, and a loop tuned for one (the paper's gains) rings.
        The host is too slow for `cycle_hz`.
        """
        last_in_time, last_late = self._last_command_timing
        self._last_command_timing = (in_time, late)
        window_late, window_all = late - last_late, in_time + late - last_in_time - last_late
        if window_all == 0 or window_late <= LATE_COMMAND_SHARE * window_all:
            return None
        return (
            DiagnosticStatus.WARN,
            f"{100.0 * window_late / window_all:.0f} % of the cycles sent the previous command "
            "(the controller answered after the next SYNC): the loop has two periods of delay; "
            "lower cycle_hz or unload the host",
        )

    def _lockstep_findings(self, wall_s: float) -> list[tuple[bytes, str]]:
        """Lockstep: OK while its start waits for subscribers, WARN while time stands.

        As the simulator's lockstep: a start waiting for its subscribers is no fault; simulated
        time standing for want of the controller's answer is.
        """
        loop = self._loop
        if loop is None or not self._active:
            return []
        if not loop.started:
            matched = self._plant.joint_pub.get_subscription_count()
            return [
                (
                    DiagnosticStatus.OK,
                    f"lockstep: waiting for {self.params.lockstep_subscribers} joint_states "
                    f"subscribers ({matched} so far): simulated time has not started",
                )
            ]
        waited_s = loop.waiting_for_command_s(wall_s)
        if waited_s > self.params.lockstep_resend_s:
            return [
                (
                    DiagnosticStatus.WARN,
                    f"lockstep: no command for {waited_s:.1f} s; simulated time stands at "
                    f"{loop.clock.now():.3f} s (is the controller running?)",
                )
            ]
        return []

    def _lockstep_values(self) -> dict[str, object]:
        loop = self._loop
        if loop is None:
            return {}
        c = loop.counters
        return {
            "timing_mode": "lockstep",
            "sim_time_s": loop.clock.now(),
            **{f"lockstep_{k}": getattr(c, k) for k in c.__slots__},
        }

    def _bridge_status(self, bridge: Cia402Master) -> DiagnosticStatus:
        c = bridge.counters
        now = time.monotonic()
        span = max(now - self._last_diag_t, 1e-6)
        frames = c.frames_sent + c.frames_received
        bits = c.bits_sent + c.bits_received
        last_frames, last_bits = self._last_frames_bits
        frames_per_s = (frames - last_frames) / span
        bits_per_s = (bits - last_bits) / span
        self._last_diag_t, self._last_frames_bits = now, (frames, bits)
        latched = bridge.latched_reason()
        if latched:
            first = (DiagnosticStatus.ERROR, latched)
        elif not self._active:
            first = (
                DiagnosticStatus.OK,
                f"{self.lifecycle_state}: drives out of operation, commands ignored; activate "
                "(lifecycle) to run",
            )
        else:
            first = (DiagnosticStatus.OK, "commands again" if self._command_losses else "running")
        found: list[tuple[bytes, str]] = [first, *self._lifecycle_findings()]
        if (
            c.commands_rejected
            or c.send_failures
            or self._wrong_interface
            or self.joint_command_counts["refused"]
        ):
            found.append((DiagnosticStatus.WARN, "rejected commands or failed sends"))
        peer = self._command_health(bridge, bridge.now())
        _merge_findings(found, [] if peer is None else [peer])
        _merge_findings(found, self._lockstep_findings(now))
        stall = bridge.cycle_stall()  # no complete cycle: a TPDO lost (latched while enabled)
        if stall and not latched:
            found.append((DiagnosticStatus.WARN, stall))
        late = self._late_commands(c.commands_in_time, c.commands_late)
        if late is not None:
            found.append(late)
        values: dict[str, object] = {
            "lifecycle_state": self.lifecycle_state,
            "interface": self.params.interface,
            "channel": self.params.channel,
            "cycle_hz": self.params.cycle_hz,
            "frames_per_s": frames_per_s,
            "bus_load_pct": bus_load_pct(bits_per_s, float(self.params.bitrate)),
            "command_age_s": bridge.command_age_s(bridge.now()),
            **_latency_values(bridge.take_command_latencies()),
            **self._lockstep_values(),
            "states_published": self._published,
            "commands_wrong_interface": self._wrong_interface,
            "commands_ignored_inactive": self._ignored_inactive,
            "joint_commands_accepted": self.joint_command_counts["accepted"],
            "joint_commands_refused": self.joint_command_counts["refused"],
            "joint_command_unknown_names": self.joint_command_counts["unknown_names"],
            "command_losses": self._command_losses,
            **{k: getattr(c, k) for k in c.__slots__},
        }
        graph = self._plant.graph_health(values)
        if graph is not None:
            found.append(graph)
        level, message = worst_first(found)
        return status("lca_hil/can_bridge", level, message, values)


def _merge_findings(found: list[tuple[bytes, str]], more: list[tuple[bytes, str]]) -> None:
    """Add findings to a status's list: WARN and above appended, OK ones as its text.

    An OK finding (a wait that is no fault: for the first command, for subscribers) becomes
    the status's text while nothing worse stands first.
    """
    for level, text in more:
        if level != DiagnosticStatus.OK:
            found.append((level, text))
        elif found[0][0] == DiagnosticStatus.OK:
            found[0] = (level, text)


def _latency_values(latencies_s: list[float]) -> dict[str, object]:
    """SYNC -> first command wall latency over a diagnostics period: p50, p99, max in ms.

    NaN when no command came (strict JSON tools read the level and message first).
    """
    if not latencies_s:
        return {f"command_latency_ms_{k}": math.nan for k in ("p50", "p99", "max")}
    ms = np.asarray(latencies_s) * 1e3
    return {
        "command_latency_ms_p50": float(np.percentile(ms, 50)),
        "command_latency_ms_p99": float(np.percentile(ms, 99)),
        "command_latency_ms_max": float(ms.max()),
    }


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-can-bridge` / `ros2 run lca_hil can_bridge`."""
    return run_node("lca-can-bridge", CanBridgeNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
