"""The simulator's /diagnostics: its `lca_hil/simulator` status and one per axis.

`SimulatorDiagnostics` builds them each period from the node's parts (the plant, its
simulated time, the faults, the per-axis watch) and keeps the controller peer's state: a
WARN while commands that came have stopped, OK "waiting for the first command" before any
came. The texts and keys are documented in docs/contract.md and docs/simulation-control.md;
the end of a lockstep run shows as `ended` = "True" (`ENDED_KEY`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node

from lca_control.contract import ENDED_KEY, SIMULATOR_STATUS
from lca_sim.config.simulator_params import SimulatorNodeParams
from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.faults import LINK, FaultInjector, StateLink
from lca_sim.ros.node_util import status
from lca_sim.ros.plant_contract import PlantPublisher, worst_first
from lca_sim.ros.sim_axes import AxisWatch
from lca_sim.ros.sim_pacing import SimPacing

Finding = tuple[bytes, str]


class SimulatorDiagnostics:
    """The simulator's /diagnostics statuses and the controller peer's state.

    Args:
        node: the simulator node (its logger: a command loss is logged when it begins and ends).
        params: the node's parameters in force.
        parts: the node's plant, simulated time, faults, state link, axis watch and plant
            publisher, read at each period.
    """

    def __init__(
        self,
        node: Node,
        params: Callable[[], SimulatorNodeParams],
        *,
        plant: CommandedPlant,
        pacing: SimPacing,
        faults: FaultInjector,
        link: StateLink,
        axes: AxisWatch,
        publisher: PlantPublisher,
        irreversible: bool,
    ) -> None:
        self._log = node.get_logger()  # type: ignore[no-untyped-call]  # rclpy is untyped here
        self._params = params
        self._plant = plant
        self._pacing = pacing
        self._faults = faults
        self._link = link
        self._axes = axes
        self._publisher = publisher
        self._irreversible = irreversible
        self._commands_lost = False  # the controller peer, as the status reports it
        self.command_losses = 0

    def statuses(
        self,
        published: int,
        wrong_interface: int,
        joint_commands: dict[str, int],
        unserved: str = "",
    ) -> list[DiagnosticStatus]:
        """The simulator's status, then one per axis, given the node's own counters.

        `unserved`: joints whose drive mode's topic brings nothing while another does (WARN).
        """
        p = self._params()
        pacing = self._pacing
        plant = self._plant
        level = DiagnosticStatus.OK
        message = "running" if plant.enabled else "disabled"
        if self.command_losses:
            message = "commands again" if plant.enabled else "disabled; commands again"
        counters = plant.counters
        if counters.rejected or wrong_interface or joint_commands["refused"]:
            level, message = DiagnosticStatus.WARN, "commands rejected"
        command_age_s = time.monotonic() - pacing.last_command_wall
        ended = pacing.ended  # no commands are wanted any more: not a peer problem
        # Paused, no command is due: silence then is no peer problem either.
        peer = None if ended or pacing.paused else self._command_health(command_age_s)
        if peer is not None and (peer[0] != DiagnosticStatus.OK or level == DiagnosticStatus.OK):
            level, message = peer
        if pacing.paused:
            message = f"paused at {pacing.sim_time_s:g} s"
        if ended:
            message = f"ended at {pacing.sim_time_s:g} s"
        faults = self._faults
        values: dict[str, object] = {
            "timing_mode": p.timing_mode,
            "command_interface": p.command_interface,
            "drive_modes": " ".join(p.joint_drive_modes),
            "enabled": plant.enabled,
            "sim_time_s": pacing.sim_time_s,
            "steps": pacing.steps,
            "states_published": published,
            "overrun_steps": pacing.overrun_steps,
            # Freezes of this process the command deadline forgave (`SimPacing.check_freeze`).
            "process_freezes": pacing.freezes.count,
            "longest_freeze_s": pacing.freezes.longest_s,
            "command_age_s": command_age_s,
            "commands_wrong_interface": wrong_interface,
            "joint_commands_accepted": joint_commands["accepted"],
            "joint_commands_refused": joint_commands["refused"],
            "joint_command_unknown_names": joint_commands["unknown_names"],
            "command_losses": self.command_losses,
            "lockstep_end_s": p.lockstep_end_s,
            ENDED_KEY: ended,
            "commands_after_end": pacing.after_end,
            "paused": pacing.paused,
            "command_pending": pacing.pending,
            "step_periods_left": pacing.step_budget,
            "realtime_factor_set": p.realtime_factor,
            "link_faults": faults.describe(LINK),
            "states_dropped": self._link.dropped,
            "states_stale": self._link.stale_sent,
            **counters.as_dict(),
        }
        found: list[Finding] = [(level, message)]
        if unserved:
            found.append((DiagnosticStatus.WARN, unserved))
        link_fault: Finding | None = None
        if faults.active(LINK):
            link_fault = (DiagnosticStatus.WARN, f"injected link faults: {faults.describe(LINK)}")
        for health in (
            pacing.timing_health(values),
            self._publisher.graph_health(values),
            link_fault,
        ):
            if health is not None:
                found.append(health)
        level, message = worst_first(found)
        return [status(SIMULATOR_STATUS, level, message, values), *self._axes.statuses()]

    def _command_health(self, command_age_s: float) -> Finding | None:
        """The controller peer: a WARN while commands that came are missing, else OK or None.

        Realtime: silence beyond command_timeout_s (the plant is at 0 V then). Lockstep: no
        command for lockstep_resend_s (simulated time stands still). Before the first command,
        and in lockstep while the start waits for its subscribers, nothing is lost yet: OK,
        saying what the simulator waits for. A loss is logged once when it begins and once
        when it ends.
        """
        p = self._params()
        pacing = self._pacing
        if pacing.lockstep and not pacing.started:
            matched = self._publisher.joint_pub.get_subscription_count()
            return DiagnosticStatus.OK, (
                f"waiting for {p.lockstep_subscribers} joint_states subscribers "
                f"({matched} so far): simulated time has not started"
            )
        limit_s = p.lockstep_resend_s if pacing.lockstep else p.command_timeout_s
        if command_age_s <= limit_s:
            if self._commands_lost:
                self._commands_lost = False
                self._log.info(f"commands again; simulated time {pacing.sim_time_s:.3f} s")
            return None
        if pacing.lockstep:
            what = "simulated time paused, the last state is re-sent"
        else:
            what = "holding (0 V)" if self._irreversible else "0 V, reversible gear (not held)"
        if not pacing.commanded:
            return DiagnosticStatus.OK, f"waiting for the first command: {what}"
        message = f"no command for {command_age_s:.1f} s: {what}"
        if not self._commands_lost:
            self._commands_lost = True
            self.command_losses += 1
            self._log.warning(f"{message}; is the controller running?")
        return DiagnosticStatus.WARN, message
