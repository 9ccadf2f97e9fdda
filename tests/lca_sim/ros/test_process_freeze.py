"""A plant whose process stood still does not blame its controller for the silence.

A paused host (a hypervisor's stall, a debugger, a swap-in) stops the plant and its controller
together. On waking, the plant has heard no command for the length of the pause; judging that
as the controller's silence put the simulator at 0 V with a WARN asking whether the controller
runs, though the controller had stood still with it. Both plants forgive a freeze of their own
process in the command deadline (`lca_sim.runtime.FreezeWatch`), say in their log how long they
stood still, and count it on /diagnostics; a controller that really goes silent is still caught.
The controller forgives its own freezes in the plant deadline the same way (last test).

Each backend runs as its console script with its shipped params file (`command_timeout_s` 0.1),
on its own domain; this test is the controller (0.2 A on the pivot, at 100 Hz). The host's
pause is the plant's SIGSTOP while the test sends nothing, for `FREEZE_S`; the test's commands
resume only once the plant has published again (its first tick after the pause has run, so the
judgement happens before any new command can arrive). Waits poll with deadlines.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.timer import Timer
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from support import (
    ManualClock,
    NodeProcess,
    hold_stopped,
    parameters,
    ros_context_on,
    spin_until,
    start_shipped,
)

from lca_control import contract as pc
from lca_sim.ros.can_bridge_diagnostics import BRIDGE_STATUS
from lca_sim.ros.controller_node import FREEZE_WATCH_PERIOD_S, ControllerNode

FREEZE_S = 0.3  # three command deadlines of the shipped files
COMMAND_PERIOD_S = 0.01
# A small current on the pivot: a plant that judged the pause as silence would drop it to 0
# (the simulator only acts, and logs, on a silence while some command is non-zero).
COMMAND_A = [0.0, 0.2, 0.0, 0.0]
START_S = 60.0  # a cold start on a slow host: imports, the model's compile cache, discovery
SILENCE = "no command for"
# backend: (console script, params file, status name, domain id)
CONTROLLER_DOMAIN_ID = 102
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
PLANTS = {
    "simulator": ("lca-simulator", "simulator.yaml", pc.SIMULATOR_STATUS, 100),
    "can_bridge": ("lca-can-bridge", "can_bridge.yaml", BRIDGE_STATUS, 101),
}


class Controller:
    """Constant current commands, the plant's statuses and its joint_states count."""

    def __init__(self, ctx: Context, executor: SingleThreadedExecutor, status: str) -> None:
        self.node = Node("freeze_test_controller", context=ctx)
        self.executor = executor
        self.status_name = status
        self.statuses: list[DiagnosticStatus] = []
        self.states = 0
        self._pub = self.node.create_publisher(
            Float64MultiArray, pc.CURRENT_COMMANDS, pc.COMMAND_QOS_DEPTH
        )
        self._timer: Timer | None = None
        self.node.create_subscription(DiagnosticArray, pc.DIAGNOSTICS, self._on_diagnostics, 50)
        self.node.create_subscription(
            JointState, pc.JOINT_STATES, self._on_state, pc.STATE_QOS_DEPTH
        )
        executor.add_node(self.node)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self.statuses += [s for s in msg.status if s.name == self.status_name]

    def _on_state(self, _msg: JointState) -> None:
        self.states += 1

    def send(self, on: bool) -> None:
        """Start or stop the commands."""
        if on and self._timer is None:
            msg = Float64MultiArray(data=COMMAND_A)
            self._pub.publish(msg)  # at once, not a period later
            self._timer = self.node.create_timer(COMMAND_PERIOD_S, lambda: self._pub.publish(msg))
        elif not on and self._timer is not None:
            self.node.destroy_timer(self._timer)
            self._timer = None

    def values(self, item: DiagnosticStatus) -> dict[str, str]:
        """The key/value pairs of one status."""
        return {kv.key: kv.value for kv in item.values}

    def wait_status(self, levels: bytes, text: str, since: int, timeout_s: float) -> None:
        """Spin until a status from index `since` on has one of `levels` and `text`."""

        def seen() -> bool:
            return any(s.level in levels and text in s.message for s in self.statuses[since:])

        spin_until(self.executor, seen, f"{self.status_name}: {levels!r} {text!r}", timeout_s)


def _log(plant: NodeProcess) -> str:
    return plant.log.read_text(encoding="utf-8", errors="replace")


@pytest.mark.parametrize("backend", sorted(PLANTS))
def test_a_plant_that_stood_still_does_not_blame_its_controller(
    backend: str, tmp_path: Path
) -> None:
    script, params, status, domain_id = PLANTS[backend]
    plant = start_shipped(script, params, domain_id, tmp_path)
    try:
        with ros_context_on(domain_id) as (ctx, executor):
            ctl = Controller(ctx, executor, status)
            ctl.send(True)
            # the plant runs on the test's commands
            ctl.wait_status(DiagnosticStatus.OK, "running", 0, START_S)
            plant.check_alive()
            # the host pauses: the plant stopped, the controller silent with it
            ctl.send(False)
            hold_stopped(plant.proc, FREEZE_S, lambda: executor.spin_once(timeout_sec=0.05))
            states_before = ctl.states
            since = len(ctl.statuses)
            plant.proc.send_signal(signal.SIGCONT)
            # the plant ticked after the pause before any new command could reach it
            spin_until(executor, lambda: ctl.states > states_before, "a state after the pause")
            ctl.send(True)
            # two reports after the pause: the first may have been due during it
            spin_until(
                executor, lambda: len(ctl.statuses) >= since + 2, "two reports after the pause"
            )
            blamed = [s.message for s in ctl.statuses[since:] if SILENCE in s.message]
            assert blamed == [], blamed
            log = _log(plant)
            assert SILENCE not in log, log[-3000:]
            assert "stood still for" in log, log[-3000:]
            freezes = int(ctl.values(ctl.statuses[-1])["process_freezes"])
            assert freezes >= 1, ctl.values(ctl.statuses[-1])
            # a controller that really goes silent is still caught, a deadline and a report later
            since = len(ctl.statuses)
            ctl.send(False)
            # (the bridge: WARN while halted, ERROR once the silence reached its quick stop)
            ctl.wait_status(DiagnosticStatus.WARN + DiagnosticStatus.ERROR, SILENCE, since, 30.0)
            plant.check_alive()
    finally:
        plant.proc.send_signal(signal.SIGCONT)
        plant.stop()


def test_a_controller_that_stood_still_does_not_blame_its_plant(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The controller's freeze watch: a 0.8 s freeze is no plant loss, a 0.6 s silence is.

    In-process and deterministic: the controller's callbacks are called in the order a frozen
    process runs them on waking (the overdue diagnostics first), on a wall clock moved by hand.
    """
    wall = ManualClock(1000.0)
    monkeypatch.setattr(time, "monotonic", wall)
    with ros_context_on(CONTROLLER_DOMAIN_ID) as (ctx, _executor):
        ctl = ControllerNode(
            "controller",
            context=ctx,
            parameter_overrides=parameters(reference_source="hold", plant_timeout_s=0.5),
        )
        try:
            state = JointState(name=list(JOINTS), position=[0.0] * 4, velocity=[0.0] * 4)
            ctl._wake()  # the watch's first call: its baseline (start-up is no freeze)
            ctl._on_joint_states(state)  # a state at 1000.0
            wall.now_s += FREEZE_WATCH_PERIOD_S
            ctl._wake()
            wall.now_s += 0.8  # the process stood still; the plant's states wait unread
            ctl._publish_diagnostics()
            assert ctl._plant_health() == (DiagnosticStatus.OK, "running")
            assert ctl.plant_losses == 0 and ctl._freezes.count == 1
            assert ctl._freezes.longest_s == pytest.approx(0.8 - FREEZE_WATCH_PERIOD_S)
            # the plant really goes silent while the controller runs: caught at its deadline
            for _ in range(12):  # 0.6 s of watch ticks on time
                wall.now_s += FREEZE_WATCH_PERIOD_S
                ctl._wake()
            level, message = ctl._plant_health()
            assert (level, message[:18]) == (DiagnosticStatus.WARN, "no plant state for")
            assert ctl.plant_losses == 1 and ctl._freezes.count == 1
        finally:
            ctl.destroy_node()  # type: ignore[no-untyped-call]  # rclpy leaves it unannotated
