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
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import ParameterType, ParameterValue, SetParametersResult
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from lca_control import contract as ri
from lca_control.contract import FloatArray, PlantSnapshot
from lca_control.parameters import ParameterError
from lca_sim.canbus import emcy
from lca_sim.canbus.master import (
    AxisState,
    BridgeError,
    BridgeParams,
    Cia402Master,
    Snapshot,
)
from lca_sim.cia402.master import bus_load_pct
from lca_sim.config.loader import config_dir, load_robot
from lca_sim.errors import ConfigError
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

SDO_ERRORS = (ValueError, KeyError, canopen.SdoAbortedError, canopen.SdoCommunicationError)


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


class CanBridgeNode(Node):
    """Publishes the drives' states and sends them the controller's current commands."""

    def __init__(self, node_name: str = "can_bridge", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
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
        robot = load_robot(p.robot)
        axes = {a.name: a for a in robot.axes}
        eds = Path(p.eds) if p.eds else config_dir() / "can" / "lca_drive.eds"
        if not eds.is_file():
            raise ConfigError("parameters", "eds", f"no such file: {eds}")
        self._rack: Any = None
        self._rack_bus: can.BusABC | None = None
        bus = open_bus(p.interface, p.channel, p.bitrate)
        try:
            if p.interface == "virtual":
                self._start_rack(p)
            self.network = canopen.Network(bus)
            self.network.connect()
            self.bridge = Cia402Master(
                self.network,
                BridgeParams(
                    joints=p.joints,
                    node_ids=p.node_ids,
                    torque_constants_nm_per_a=tuple(
                        axes[j].motor.torque_constant_nm_per_a for j in p.joints
                    ),
                    gear_ratios=tuple(axes[j].gear_ratio for j in p.joints),
                    drive_state_names=robot.state_machine.state_names,
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
                ),
                eds,
                on_state=self._on_state,
            )
        except Exception:
            self._close_bus(bus)
            raise
        self._bus = bus
        self._state_names = robot.state_machine.state_names
        self._published = 0
        self._wrong_interface = 0
        self._commands_lost = False  # the controller peer, as /diagnostics reports it
        self._command_losses = 0
        self._last_diag_t = time.monotonic()
        self._last_frames_bits = (0, 0)  # frames and bits at the previous diagnostics
        self._init_lock = threading.Lock()

        self._plant = PlantPublisher(self, p.joints, joint_state_topic=p.joint_state_topic)
        self._torque_constants = np.array(self.bridge.params.torque_constants_nm_per_a)
        self._gear_ratios = np.array(self.bridge.params.gear_ratios)
        command_qos = qos_profile(ri.COMMAND_QOS)
        self.create_subscription(
            Float64MultiArray, ri.CURRENT_COMMANDS, self._on_command, command_qos
        )
        self.create_subscription(
            Float64MultiArray, ri.VOLTAGE_COMMANDS, self._on_voltage_command, command_qos
        )
        if self.bridge.velocity_axes:  # CSV axes close their velocity loop in the drive
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
        drives = dict(zip(p.joints, p.node_ids, strict=True))
        self.get_logger().info(
            f"{p.interface} bus {p.channel!r}, drives {drives}, {p.cycle_hz:g} Hz, EDS {eds}"
        )
        if p.auto_init:
            message = self._init()
            if message:
                self.get_logger().error(f"init failed: {message} (retry with ~/init)")
            elif p.auto_enable:
                self.get_logger().info(self.bridge.enable(True))

    @property
    def params(self) -> CanBridgeNodeParams:
        """The parameters in force (a live set replaces them as a whole)."""
        return self._live.params

    def _apply_params(
        self, old: CanBridgeNodeParams, new: CanBridgeNodeParams, changed: frozenset[str]
    ) -> None:
        """A live set of the bridge's safety timing: in force from the next cycle.

        The cycle thread reads `Cia402Master.params` once per cycle, so one reference swap
        hands it the new values whole. Read-only parameters never get here.
        """
        bridge = getattr(self, "bridge", None)
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

    # --- set-up and tear-down ------------------------------------------------------------

    def _start_rack(self, p: CanBridgeNodeParams) -> None:
        from lca_sim.canbus.virtual_rack import VirtualDriveRack, load_rack_config  # noqa: PLC0415

        config = load_rack_config(Path(p.rack_config) if p.rack_config else None)
        self._rack_bus = open_bus("virtual", p.channel, p.bitrate)
        self._rack = VirtualDriveRack(self._rack_bus, config)
        self._rack.start()

    def _init(self) -> str:
        """Configure and start the drives, then the cycle; '' or the error."""
        with self._init_lock:
            self.bridge.stop()
            try:
                self.bridge.init()
            except BridgeError as exc:
                return str(exc)
            settle_heap()  # before the cycle runs: a full collection would stall it
            self.bridge.start()
            return ""

    def destroy_node(self) -> None:
        """Stop the cycle (the drives' watchdogs take over), the rack, and close the buses."""
        bridge = getattr(self, "bridge", None)
        if bridge is not None:
            bridge.stop()
            self.network.disconnect()
        if self._rack is not None:
            self._rack.stop()
        if self._rack_bus is not None:
            self._rack_bus.shutdown()
        super().destroy_node()

    @staticmethod
    def _close_bus(bus: can.BusABC) -> None:
        with contextlib.suppress(can.CanError):
            bus.shutdown()

    # --- topics --------------------------------------------------------------------------

    def _on_command(self, msg: Float64MultiArray) -> None:
        self._set_currents(list(msg.data))

    def _set_currents(self, currents_a: list[float]) -> None:
        reason = self.bridge.set_currents(currents_a)
        if reason is None:
            self._held_current_a[:] = currents_a
        else:
            self.get_logger().warning(
                f"command rejected ({self.bridge.counters.commands_rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )

    def _on_velocity_command(self, msg: Float64MultiArray) -> None:
        self._set_velocities(list(msg.data))

    def _set_velocities(self, velocities: list[float]) -> None:
        reason = self.bridge.set_velocities(velocities)
        if reason is None:
            self._held_velocity[:] = velocities
        else:
            self.get_logger().warning(
                f"velocity command rejected ({self.bridge.counters.commands_rejected} so far): "
                f"{reason}",
                throttle_duration_sec=1.0,
            )

    def _on_joint_command(self, msg: JointState) -> None:
        """A JointState command (docs/ros2_control.md), each joint by its drive's mode.

        A cst joint takes its effort entry (A, or joint torque per `joint_command_effort`),
        a csv joint its velocity entry (the drive closes the loop); joints not named, or with
        NaN, keep their command. The entry of the other field is ignored when zero (what the
        interface sends for an interface no controller claims) and refused when not.
        """
        p = self.params
        counts = self.joint_command_counts
        cmd = read_joint_command(msg.name, msg.velocity, msg.effort, p.joints)
        counts["unknown_names"] += len(cmd.unknown)
        csv = set(self.bridge.velocity_axes)
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
                self._set_currents(currents)
            if velocities:
                wanted = self._held_velocity.tolist()
                for k, joint in enumerate(p.joints):
                    if joint in velocities:
                        wanted[k] = cmd.velocity[joint]
                self._set_velocities(wanted)
        if problems:
            self.get_logger().warning(
                f"{p.joint_command_topic}: {'; '.join(problems)} ({counts['refused']} refused, "
                f"{counts['unknown_names']} unknown names so far)",
                throttle_duration_sec=1.0,
            )

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
        """A complete cycle (notifier thread): publish it. rclpy publishers are thread-safe."""
        self._plant.publish(
            plant_snapshot(
                snap,
                self._plant.joints,
                self._torque_constants,
                self._gear_ratios,
                self._state_names,
                self.bridge.decoded_fields(),
            )
        )
        self._published += 1

    # --- services ------------------------------------------------------------------------

    def _srv_init(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        message = self._init()
        res.success = not message
        res.message = message or "drives configured and operational; call ~/enable"
        return res

    def _srv_enable(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        res.message = self.bridge.enable(True)
        res.success = res.message == "enabling"
        return res

    def _srv_disable(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        res.message = self.bridge.enable(False)
        res.success = True
        return res

    def _srv_halt(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        self.bridge.halt()
        res.success, res.message = True, "halted: zero torque until the next ~/enable"
        return res

    def _srv_recover(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        self.bridge.recover()
        res.success, res.message = True, "latches cleared, faults reset; call ~/enable"
        return res

    def _srv_cst(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        try:
            for joint in self.params.joints:
                self.bridge.sdo_write(joint, 0x6060, 0, 10)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            res.success, res.message = False, f"mode 10 refused: {exc}"
            return res
        res.success, res.message = True, "cyclic synchronous torque (mode 10) on every drive"
        return res

    def _srv_sdo_read(
        self, req: GetParameters.Request, res: GetParameters.Response
    ) -> GetParameters.Response:
        for name in req.names:
            try:
                joint, index, subindex = parse_object_name(name)
                raw = self.bridge.sdo_read(joint, index, subindex)
            except SDO_ERRORS as exc:
                raw = f"error: {exc}"
            res.values.append(_parameter_value(raw))
        return res

    def _srv_sdo_write(
        self, req: SetParameters.Request, res: SetParameters.Response
    ) -> SetParameters.Response:
        for param in req.parameters:
            result = SetParametersResult(successful=True)
            try:
                joint, index, subindex = parse_object_name(param.name)
                v = param.value
                if v.type == ParameterType.PARAMETER_INTEGER:
                    self.bridge.sdo_write(joint, index, subindex, int(v.integer_value))
                elif v.type == ParameterType.PARAMETER_DOUBLE:
                    self.bridge.sdo_write(joint, index, subindex, float(v.double_value))
                else:
                    raise ValueError("only integer or double values can be written")
            except SDO_ERRORS as exc:
                result = SetParametersResult(successful=False, reason=str(exc))
            res.results.append(result)
        return res

    # --- diagnostics ---------------------------------------------------------------------

    def _axis_status(self, joint: str, latched: int, advisory: tuple[int, int]) -> DiagnosticStatus:
        """One drive: ERROR with the latched EMCY's text, WARN for an advisory EMCY, else OK.

        The message is the power state, then the EMCY decoded to text (`emcy.describe`).
        """
        s = self.bridge.axis_state(joint)
        power = s.power_state
        message = power.name.lower() if power else f"statusword 0x{s.statusword:04X}"
        level = DiagnosticStatus.OK
        code, count = advisory
        ours = self.bridge.has_drive_state()  # lca_hil's drive: its own codes have text
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

    def _command_health(self, now: float) -> tuple[bytes, str] | None:
        """The controller peer: WARN while the drives are halted for want of commands.

        ERROR once the silence has lasted into the quick stop, which holds until ~/enable.
        Nothing while the drives are not enabled. The loss is logged once when it begins (by
        the master, with its reaction) and once here when commands return.
        """
        silence = self.bridge.command_silence(now)
        if silence is None:
            if self._commands_lost:
                self._commands_lost = False
                self.get_logger().info("commands again")
            return None
        latched, why = silence
        if not self._commands_lost and self.bridge.counters.commands_accepted:
            self._commands_lost = True
            self._command_losses += 1
            self.get_logger().warning(f"{why}; is the controller running?")
        return (DiagnosticStatus.ERROR if latched else DiagnosticStatus.WARN), why

    def _publish_diagnostics(self) -> None:
        bridge = self.bridge
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
        found: list[tuple[bytes, str]] = [
            (DiagnosticStatus.ERROR, latched)
            if latched
            else (DiagnosticStatus.OK, "commands again" if self._command_losses else "running")
        ]
        if (
            c.commands_rejected
            or c.send_failures
            or self._wrong_interface
            or self.joint_command_counts["refused"]
        ):
            found.append((DiagnosticStatus.WARN, "rejected commands or failed sends"))
        peer = self._command_health(now)
        if peer is not None:
            found.append(peer)
        values: dict[str, object] = {
            "interface": self.params.interface,
            "channel": self.params.channel,
            "cycle_hz": self.params.cycle_hz,
            "frames_per_s": frames_per_s,
            "bus_load_pct": bus_load_pct(bits_per_s, float(self.params.bitrate)),
            "command_age_s": bridge.command_age_s(now),
            "states_published": self._published,
            "commands_wrong_interface": self._wrong_interface,
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
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(status("lca_hil/can_bridge", level, message, values))
        codes = bridge.emcy_codes()
        advisory = bridge.advisory_emcy()
        for joint in self.params.joints:
            array.status.append(self._axis_status(joint, codes[joint], advisory[joint]))
        self._plant.publish_diagnostics(array)


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-can-bridge` / `ros2 run lca_hil can_bridge`."""
    return run_node("lca-can-bridge", CanBridgeNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
