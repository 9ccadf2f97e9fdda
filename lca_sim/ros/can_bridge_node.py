r"""The CAN bridge node: `ros2 run lca_hil can_bridge` (console script `lca-can-bridge`).

Swaps the simulator node for CiA 402 drives on a CAN bus behind the same topics (the plant
contract, docs/contract.md): `current_commands` in; `joint_states`, `motor_states`,
`drive_chain_states` and `/diagnostics` out, once per complete SYNC cycle.

    lca-can-bridge --ros-args --params-file config/ros/can_bridge.yaml           # virtual rack
    lca-can-bridge --ros-args --params-file config/ros/can_bridge.yaml \\
        -p interface:=socketcan -p channel:=can0                               # a real bus

A managed node: configure opens the bus (`can_drives.CanDrives`), activate enables the drives,
deactivate takes them out of operation with zero torque, cleanup closes the bus; `autostart`
(the default) does configure and activate at start-up. Services `~/init`, `~/enable`,
`~/disable`, `~/halt`, `~/recover`, `~/cyclic_torque_mode` (std_srvs/Trigger) and the SDO
services (`sdo_services`). docs/can.md ("The bridge as a managed node") has the whole story.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import canopen
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from lca_control.parameters import ParameterError
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_state import Snapshot
from lca_sim.config.can_bridge_params import (
    CAN_BRIDGE_PARAMETERS,
    CanBridgeNodeParams,
    validate_can_bridge_params,
)
from lca_sim.config.loader import load_robot
from lca_sim.config.paths import config_dir
from lca_sim.errors import FILE_NOT_FOUND, USER_ERRORS, ConfigError
from lca_sim.model.params import RobotParams
from lca_sim.ros.can_bridge_commands import BridgeCommands
from lca_sim.ros.can_bridge_diagnostics import BridgeDiagnostics, BridgeView
from lca_sim.ros.can_drives import (
    TORQUE_FREE_TIMEOUT_S,
    CanDrives,
    CycleValues,
    drives_in_process,
    live_bridge_params,
)
from lca_sim.ros.dds_profile import PROFILE_ENV, shipped_profile
from lca_sim.ros.drive_services import DriveServices
from lca_sim.ros.node_util import LiveParameters, declare_table, run_node
from lca_sim.ros.plant_contract import PlantPublisher
from lca_sim.ros.sdo_services import SdoServices
from lca_sim.runtime import GIL_SWITCH_INTERVAL_S, SlowCalls

if TYPE_CHECKING:
    from lca_sim.canbus.virtual_rack import VirtualDriveRack

# Lockstep: how often the node looks whether to start the loop, re-send a state or give up on
# an incomplete cycle, s (wall time).
LOCKSTEP_TICK_S = 0.05


def _publish_timing(p: CanBridgeNodeParams) -> SlowCalls:
    """The timing of the state publishes: slow ones counted, the first ones said.

    Drives in this process (`drives_in_process`) stand still with a publish that waits: no
    deadline of theirs to trip, so every such wait is a note (`SafetyWatch` says the same of
    the freeze).
    """
    return SlowCalls(
        "publishing the plant's state",
        math.inf if drives_in_process(p) else p.rpdo_deadline_ms / 1e3,
        "Fast DDS's write waited, with the GIL, and the cycle thread with it; it does while "
        "a newly joined peer's shared-memory port is checked: start other ROS tools with "
        f"{PROFILE_ENV}={shipped_profile()} (docs/can-transport.md, 'The 331 ms stall')",
    )


class CanBridgeNode(LifecycleNode):
    """Publishes the drives' states and sends them the controller's current commands.

    A managed node (ROS 2 "Managed nodes" design, rclpy.lifecycle). With `autostart` (the
    default) it configures and activates itself at start-up, so a plain start comes up active;
    `auto_init` and `auto_enable` then say whether that start configures and enables the drives.
    The services, topics and parameters exist in every state; a service that needs the drives
    says so when they are not there.
    """

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
        eds = Path(p.eds) if p.eds else config_dir() / "can" / "lca_drive.eds"
        if not eds.is_file():
            raise ConfigError("parameters", "eds", f"{FILE_NOT_FOUND}: {eds}")
        self._lockstep = p.timing_mode == "lockstep"
        self._drives = CanDrives(robot, p.joints, eds, self._on_state, self._poll_commands)
        self._active = False  # lifecycle ACTIVE: states published, commands passed on
        self._autostarting = False  # inside the start-up's configure and activate
        self._startup_error: Exception | None = None  # a user error of that start-up
        self._transition_error = ""  # why the last transition failed, until one succeeds
        self._published = 0
        self._slow_publishes = _publish_timing(p)
        self._last_plant: CycleValues | None = None  # lockstep: sent again to a silent peer
        self._create_interfaces(p, robot)
        drives = dict(zip(p.joints, p.node_ids, strict=True))
        self.get_logger().info(
            f"{p.interface} bus {p.channel!r}, drives {drives}, {p.cycle_hz:g} Hz, EDS {eds}"
        )
        if p.autostart:
            self._autostart()
        else:
            self.get_logger().info("unconfigured: waiting for a lifecycle manager (configure)")

    def _create_interfaces(self, p: CanBridgeNodeParams, robot: RobotParams) -> None:
        """Publishers, subscriptions, services and the diagnostics timer (every state)."""
        self._plant = PlantPublisher(
            self, p.joints, clock=self._lockstep, joint_state_topic=p.joint_state_topic
        )
        self._diagnostics = BridgeDiagnostics(self, self._plant)
        self._commands = BridgeCommands(
            self,
            p,
            robot,
            self._drives,
            lambda: self._active,
            lambda: self.lifecycle_state,
            polled=not self._lockstep,
        )
        self._drive_services = DriveServices(
            self, self._drives, lambda: self._active, lambda: self.lifecycle_state
        )
        self._sdo = SdoServices(self, lambda: self._drives.master, lambda: self.lifecycle_state)
        self._diag_timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        if self._lockstep:
            self._kick_timer = self.create_timer(LOCKSTEP_TICK_S, self._lockstep_tick)

    @property
    def params(self) -> CanBridgeNodeParams:
        """The parameters in force (a live set replaces them as a whole)."""
        return self._live.params

    @property
    def joint_command_counts(self) -> dict[str, int]:
        """JointState commands accepted and refused, and unknown joint names in them."""
        return self._commands.joint_commands.counts

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
        return self._drives.master

    @property
    def network(self) -> canopen.Network | None:
        """The master's canopen network while configured, else None."""
        return self._drives.network

    @property
    def rack(self) -> VirtualDriveRack | None:
        """The virtual drive rack this node runs (`interface: virtual`, while configured)."""
        return self._drives.rack

    def _apply_params(
        self, old: CanBridgeNodeParams, new: CanBridgeNodeParams, changed: frozenset[str]
    ) -> None:
        """A live set of the bridge's safety timing: in force from the next cycle.

        The cycle thread reads `Cia402Master.params` once per cycle, so one reference swap
        hands it the new values whole. Read-only parameters never get here. Unconfigured, the
        next configure builds the master from the new values.
        """
        drives = getattr(self, "_drives", None)
        master = None if drives is None else drives.master
        if master is not None:
            try:
                master.params = live_bridge_params(master.params, new)
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
            self._drives.open(p)
        except Exception:
            self._teardown()
            raise
        if self._autostarting and not p.auto_init:
            self.get_logger().info("auto_init false: the drives wait for ~/init")
            return ""
        message = self._drives.init()
        if not message:
            return ""
        if self._autostarting:  # a plain start stays up as it always did, to retry ~/init
            self.get_logger().error(f"init failed: {message} (retry with ~/init)")
            return ""
        self._teardown()
        return f"init failed: {message}"

    def _activate(self) -> str:
        """Enable the drives, then pass commands on and publish.

        CiA 402-2 (IEC 61800-7-201) drive state machine: the master walks each drive with the
        controlwords shutdown 0x0006, switch on 0x0007, enable operation 0x000F (transitions
        2, 3, 4) to OPERATION ENABLED, one legal step per cycle
        (`lca_sim.cia402.controlword.next_controlword`).
        """
        bridge = self._configured()
        configured = self._drives.configured
        if self._autostarting and not (self.params.auto_enable and configured):
            self._active = True  # a plain start without auto_enable: ~/enable later
            return ""
        if not configured:
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
        master = self._drives.master
        if master is None:
            raise RuntimeError("the CANopen master is not running (node unconfigured)")
        return master

    def _teardown_torque_free(self) -> str:
        self._torque_free()
        return self._teardown()

    def _torque_free(self) -> None:
        """No torque on any drive (`CanDrives.torque_free`); warned when one does not answer."""
        self._active = False
        enabled = self._drives.torque_free()
        if enabled:
            self.get_logger().warning(
                f"drives {enabled} still report operation enabled after "
                f"{TORQUE_FREE_TIMEOUT_S:g} s; their watchdogs take over"
            )

    def _teardown(self) -> str:
        """Stop the cycle (the drives' watchdogs then react), close the bus, stop the rack."""
        self._active = False
        self._drives.close()
        return ""

    def destroy_node(self) -> None:
        """Leave the drives torque-free and close the buses (as on shutdown), then destroy."""
        self._torque_free()
        self._teardown()
        self._commands.destroy()
        super().destroy_node()

    # --- topics --------------------------------------------------------------------------

    def _on_state(self, snap: Snapshot) -> None:
        """A complete cycle (notifier thread): publish it while active.

        rclpy publishers are thread-safe. Inactive, the node publishes nothing but
        /diagnostics, as a LifecyclePublisher would.
        """
        bridge = self._drives.master
        if not self._active or bridge is None:
            return
        plant = self._drives.cycle_values(snap, bridge.decoded_fields())
        loop = self._drives.loop
        if loop is not None:  # waiting before the state goes: the answer may be quick
            self._last_plant = plant
            loop.on_state(time.monotonic())
        self._publish(plant)
        self._published += 1

    def _publish(self, plant: CycleValues) -> None:
        start_s = time.monotonic()
        self._plant.publish_values(plant.stamp_s, plant.joint, plant.motor, plant.drive_chain)
        said = self._slow_publishes.took(time.monotonic() - start_s)
        if said is not None:
            level, text = said
            log = self.get_logger()
            (log.warning if level >= logging.WARNING else log.info)(text)

    def _lockstep_tick(self) -> None:
        """Lockstep: start the loop once the controller listens; keep it going when stuck.

        The first SYNC goes once the node is active with its drives configured and
        `lockstep_subscribers` subscribers of joint_states have matched (as the simulator's
        lockstep start). A controller silent for `lockstep_resend_s` gets the last state again
        (it ignores a stamp it has seen); a cycle incomplete for as long (a TPDO lost) is
        given up and the next SYNC sent, so the master's stall watch judges it in SYNCs.
        """
        loop = self._drives.loop
        if loop is None or not (self._active and self._drives.configured):
            return
        wall_s = time.monotonic()
        if not loop.started:
            p = self.params
            if self._plant.joint_pub.get_subscription_count() >= p.lockstep_subscribers:
                loop.start(wall_s)
            return
        action = loop.on_tick(wall_s)
        if action == "resend" and self._last_plant is not None:
            self._publish(self._last_plant)
        elif action == "incomplete":
            self.get_logger().warning(
                f"lockstep: no complete cycle for {loop.resend_s:g} s; the next SYNC goes "
                f"({loop.counters.incomplete_cycles} so far)",
                throttle_duration_sec=5.0,
            )

    # --- diagnostics ---------------------------------------------------------------------

    def _poll_commands(self) -> None:
        """The cycle thread, before each SYNC: the commands that came since the last one."""
        self._commands.poll()

    def _publish_diagnostics(self) -> None:
        commands = self._commands
        commands.poll()  # what came while no cycle runs (unconfigured) is counted too
        counts = commands.joint_commands.counts
        failures = [self._transition_error] if self._transition_error else []
        master = self._drives.master
        if self._drives.init_error and master is not None:
            failures.append(f"init failed: {self._drives.init_error} (~/init)")
        if master is not None and (receiving := master.receive_failure()):
            failures.append(receiving)
        view = BridgeView(
            lifecycle_state=self.lifecycle_state,
            active=self._active,
            params=self.params,
            failures=tuple(failures),
            counts={
                "states_published": self._published,
                "slow_publishes": self._slow_publishes.count,
                "longest_publish_ms": round(self._slow_publishes.longest_s * 1e3),
                "commands_wrong_interface": commands.wrong_interface,
                "commands_undecodable": commands.undecodable,
                "commands_ignored_inactive": commands.ignored_inactive,
                "joint_commands_accepted": counts["accepted"],
                "joint_commands_refused": counts["refused"],
                "joint_command_unknown_names": counts["unknown_names"],
            },
            refused=bool(commands.wrong_interface or commands.undecodable or counts["refused"]),
            warnings=tuple(filter(None, [commands.unserved()])),
        )
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = self._diagnostics.statuses(view, self._drives.master, self._drives.loop)
        self._plant.publish_diagnostics(array)


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-can-bridge` / `ros2 run lca_hil can_bridge`."""
    return run_node("lca-can-bridge", CanBridgeNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
