"""A healthy run raises no alarm: every /diagnostics status of every node stays OK (issue 23).

The README's commands with the shipped params files unchanged, both processes started at once
as a user starts them: the simulator (realtime, as shipped) with the controller, and the CAN
bridge (the virtual rack in its process) with the controller. A probe collects every status of
every node until the pivot has passed Fig. 15's motor-driving -> load-driving transition (about
10 s into the ramp) and one more report of each node after it; the test fails listing whatever
was not OK, and any WARN or ERROR line in the nodes' logs. The main job's logs (`lca-hil
fig15`, lockstep) are checked on its run in tests/test_fault_matrix.py (item 7). Last, the
end-stop report itself: a lift parked on its lower stop is OK, one driven into it is not.
"""

from __future__ import annotations

import math
import re
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from support import (
    LOCKSTEP_SIMULATOR,
    Diagnostics,
    parameters,
    ros_context_on,
    spin_until,
    start_shipped,
    start_simulator,
    wait_until,
)

from lca_control import contract as pc
from lca_sim.ros.node_util import from_stamp, make_executor

SIMULATOR_DOMAIN_ID = 230
BRIDGE_DOMAIN_ID = 231
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
PIVOT = JOINTS.index("pivot")
LOAD_DRIVES = ("motor_and_load_driving", "load_driving")
OK_LEVEL = int.from_bytes(DiagnosticStatus.OK, "little")
REPORTS_AFTER = 2  # reports of every status after the transition (its period included)
# A log line at WARN or above, as rclpy writes it.
ALARM_LINE = re.compile(r"\[(WARN|ERROR|FATAL)\]")


@dataclass
class HealthProbe:
    """Every /diagnostics status of a run, and the pivot's drive states and position."""

    levels: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    not_ok: list[str] = field(default_factory=list)  # "t s: name: level message", in order
    started_s: float = field(default_factory=time.monotonic)
    pivot_rad: float = math.nan
    pivot_states: list[tuple[float, str, float]] = field(default_factory=list)  # s, state, rad

    def listen(self, node: Node) -> None:
        """Subscribe `node` to /diagnostics, joint_states and drive_chain_states."""
        node.create_subscription(DiagnosticArray, pc.DIAGNOSTICS, self._on_diagnostics, 50)
        node.create_subscription(JointState, pc.JOINT_STATES, self._on_joint, 100)
        node.create_subscription(DiagnosticArray, pc.DRIVE_CHAIN_STATES, self._on_drive, 100)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            level = int.from_bytes(status.level, "little")
            self.levels[status.name].append(level)
            if level != OK_LEVEL:
                t_s = time.monotonic() - self.started_s
                self.not_ok.append(f"{t_s:.1f} s: {status.name}: level {level} {status.message!r}")

    def _on_joint(self, msg: JointState) -> None:
        self.pivot_rad = msg.position[list(msg.name).index("pivot")]

    def _on_drive(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name != pc.DRIVE_STATUS_PREFIX + "pivot":
                continue
            if not self.pivot_states or self.pivot_states[-1][1] != status.message:
                stamp_s = from_stamp(msg.header.stamp)
                self.pivot_states.append((stamp_s, status.message, self.pivot_rad))

    def transition(self) -> tuple[float, str, float] | None:
        """The pivot's first load-driving state after motor driving, or None yet."""
        driving = False
        for change in self.pivot_states:
            driving = driving or change[1] == "motor_driving"
            if driving and change[1].startswith(LOAD_DRIVES):
                return change
        return None

    def reports(self) -> dict[str, int]:
        """How many reports of each status name came so far."""
        return {name: len(levels) for name, levels in self.levels.items()}


@contextmanager
def probe_on(domain_id: int) -> Iterator[tuple[HealthProbe, Executor]]:
    """A HealthProbe on its own node and Context on `domain_id` (loopback only), torn down.

    The probe takes joint_states and drive_chain_states at the plant's rate (500 Hz on the CAN
    bridge) on the same two cores as the loop it watches: on rclpy's events executor (about
    half the CPU per message of SingleThreadedExecutor, node_util.make_executor) so that the
    watching does not make the loop late.
    """
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    executor = make_executor(ctx)
    node = Node("health_probe", context=ctx)
    probe = HealthProbe()
    probe.listen(node)
    executor.add_node(node)
    try:
        yield probe, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def run_healthy(
    plant: tuple[str, str], domain_id: int, out: Path, expected: list[str]
) -> tuple[HealthProbe, list[str], list[int]]:
    """Run the plant and the shipped controller past the transition; what the probe saw.

    Returns the probe, the WARN-or-above lines the processes logged before they were
    stopped, and their exit codes.
    """
    with probe_on(domain_id) as (probe, executor):
        nodes = [
            start_shipped(*plant, domain_id, out),
            start_shipped("lca-controller", "controller.yaml", domain_id, out),
        ]

        def spin() -> None:
            executor.spin_once(timeout_sec=0.05)

        def alive() -> None:
            for node in nodes:
                node.check_alive()

        try:
            wait_until(
                lambda: probe.transition() is not None,
                "the pivot past the motor-driving -> load-driving transition",
                timeout_s=180.0,
                step=spin,
                check=alive,
            )
            seen = probe.reports()
            wait_until(
                lambda: all(
                    probe.reports().get(n, 0) >= seen.get(n, 0) + REPORTS_AFTER for n in expected
                ),
                f"{REPORTS_AFTER} more reports of each of {expected}",
                timeout_s=30.0,
                step=spin,
                check=alive,
            )
            # What the nodes logged while they ran (a stop may rightly say the peer went).
            alarms = [
                f"{node.log.name}: {line}"
                for node in nodes
                for line in node.log.read_text(encoding="utf-8", errors="replace").splitlines()
                if ALARM_LINE.search(line)
            ]
        finally:
            codes = [node.stop() for node in reversed(nodes)]
    return probe, alarms, codes


def assert_healthy(
    probe: HealthProbe, alarms: list[str], codes: list[int], expected: list[str]
) -> None:
    """Every expected status reported from early on, all OK; no alarm logged; clean exits."""
    reports = probe.reports()
    switch = probe.transition()
    assert switch is not None
    print(
        f"transition to {switch[1]} at {math.degrees(switch[2]):.2f} deg; "
        f"reports {dict(sorted(reports.items()))}; not OK {probe.not_ok[:20]}"
    )
    assert probe.not_ok == [], "\n".join(probe.not_ok)
    assert alarms == [], "\n".join(alarms)
    assert codes == [0, 0]
    # 1 Hz reports over about 10 s of ramp: each status was watched over the whole run.
    for name in expected:
        assert reports.get(name, 0) >= 8, (name, reports)
    assert all(levels == [OK_LEVEL] * len(levels) for levels in probe.levels.values())
    assert 54.0 < math.degrees(switch[2]) < 56.5, switch  # Fig. 15: at 55 deg


def test_the_shipped_simulator_and_controller_stay_ok(tmp_path: Path) -> None:
    """Realtime simulator + controller as shipped: every status OK through the transition."""
    expected = [
        "lca_hil/controller",
        "lca_hil/simulator",
        *(f"lca_hil/simulator/{joint}" for joint in JOINTS),
    ]
    probe, alarms, codes = run_healthy(
        ("lca-simulator", "simulator.yaml"), SIMULATOR_DOMAIN_ID, tmp_path, expected
    )
    assert_healthy(probe, alarms, codes, expected)


def test_the_shipped_can_bridge_and_controller_stay_ok(tmp_path: Path) -> None:
    """CAN bridge (virtual rack) + controller as shipped: every status OK through the transition."""
    expected = [
        "lca_hil/controller",
        "lca_hil/can_bridge",
        *(f"lca_hil/can_bridge/{joint}" for joint in JOINTS),
    ]
    probe, alarms, codes = run_healthy(
        ("lca-can-bridge", "can_bridge.yaml"), BRIDGE_DOMAIN_ID, tmp_path, expected
    )
    assert_healthy(probe, alarms, codes, expected)


LIFT_STATUS = "lca_hil/simulator/lift"
END_STOP_DOMAIN_ID = 232


def test_a_lift_parked_on_its_stop_is_ok_and_one_driven_into_it_is_not() -> None:
    """Lift at 0 m (its lower stop): OK at rest; WARN pushing into it, and after a hit."""
    with ros_context_on(END_STOP_DOMAIN_ID) as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        sim = start_simulator(
            ctx, executor, LOCKSTEP_SIMULATOR, timing_mode="realtime", command_interface="voltage"
        )
        # parked on the stop it never moved into: no fault
        found = diagnostics.wait_for(LIFT_STATUS, DiagnosticStatus.OK, "resting on its lower", 60.0)
        assert found.message == "stop_hold: resting on its lower end stop"
        assert float(diagnostics.value(LIFT_STATUS, "position")) == 0.0
        volts = [0.0, 0.0, 0.0, 0.0]
        pub = diagnostics.node.create_publisher(Float64MultiArray, pc.VOLTAGE_COMMANDS, 10)
        diagnostics.node.create_timer(0.02, lambda: pub.publish(Float64MultiArray(data=volts)))
        # the motor pushing down into the stop
        volts[3] = -30.0
        diagnostics.clear()
        found = diagnostics.wait_for(LIFT_STATUS, DiagnosticStatus.WARN, "pushing into its lower")
        assert found.message == "lift pushing into its lower end stop"  # no hit: never moved
        # up off the stop, then driven back down into it: a hit with its speed
        volts[3] = 30.0
        spin_until(executor, lambda: float(sim.sim.state_array[0, 3]) > 0.002, "the lift up")
        volts[3] = 0.0
        diagnostics.clear()
        diagnostics.wait_for(LIFT_STATUS, DiagnosticStatus.OK, "stop_hold", 30.0)  # held off it
        volts[3] = -30.0
        diagnostics.clear()
        found = diagnostics.wait_for(LIFT_STATUS, DiagnosticStatus.WARN, "end stop hit at")
        speed_m_s = float(diagnostics.value(LIFT_STATUS, "end_stop_contact_speed"))
        assert 0.0 < speed_m_s < 0.1, speed_m_s  # m/s, below the URDF's 0.05 m/s limit x 2
        volts[3] = 0.0
        diagnostics.clear()
        found = diagnostics.wait_for(LIFT_STATUS, DiagnosticStatus.WARN, "end stop hit at")
        assert found.message.startswith("end stop hit at")  # at rest after the hit: still said
        # ~/reset parks it on the stop again: no fault
        assert sim.reset()[0]
        diagnostics.clear()
        diagnostics.wait_for(LIFT_STATUS, DiagnosticStatus.OK, "resting on its lower", 30.0)


SLOW_START_DOMAIN_ID = 229


def test_simulated_time_starts_at_the_first_tick_not_at_construction() -> None:
    """A realtime simulator that comes up slowly has no stall to report.

    Between construction and the first tick a node settles its heap and its executor comes
    up: 0.1-0.6 s on a 2-core host starting its peers. That gap counted as skipped time, a
    "stalled" WARN on the first diagnostics of a healthy start (seen in a fresh-clone run).
    Here the node waits 0.3 s before it first spins.
    """
    from lca_sim.ros.simulator_node import SimulatorNode

    with ros_context_on(SLOW_START_DOMAIN_ID) as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=parameters(timing_mode="realtime"))
        gap_end_s = time.monotonic() + 0.3
        wait_until(lambda: time.monotonic() > gap_end_s, "the start-up gap")
        first_tick_wall_s = time.time()
        executor.add_node(sim)
        try:
            spin_until(executor, lambda: sim.steps >= 250, "25 ms of simulated time")
            assert sim.pacing.overrun_steps == 0  # nothing skipped: the gap was before the clock
            # The first state is stamped at the first tick, not 0.3 s before it.
            assert sim.sim_time_s - sim.steps * 1e-4 >= first_tick_wall_s - 0.01
        finally:
            executor.remove_node(sim)
            sim.destroy_node()
