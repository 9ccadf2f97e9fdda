"""The plant contract on every backend: one closed-loop scenario, the same topics, keys, states.

Each backend in `BACKENDS` runs the same scenario in this process: the unchanged controller node
(current commands) takes the pivot from 45 deg up to 5 deg/s and holds that speed through the
motor-driving -> load-driving transition at 55 deg (where the centre of gravity passes over the
axis); the other joints hold still. A probe node subscribes to every state topic and checks each
message as it arrives against `lca_control.contract`; after the run the graph is read for the
topics, types and QoS of the plant node. The tests then hold every backend to the contract and
to the reference backend (the simulator): the same topic set and types, joint names and order,
`drive_chain/<joint>` key sets, vocabularies, ranges, and the same drive-state sequence of the
pivot, switching to load driving near the same angle.

A new backend is one entry in `BACKENDS`: a node name and a function that starts its node.

The backends:

* `simulator`: the simulator node in lockstep (simulated time, deterministic);
* `can_bridge`: the CAN bridge node with its default `interface: virtual`, which runs the
  virtual drive rack in this process on python-can's virtual bus, in lockstep (one SYNC per
  command, the rack advancing 0x1006 per SYNC), 250 Hz SYNC like the controller's 4 ms period,
  the shipped watchdogs;
* `can_bridge_remote`: the same bridge node with `interface: lca_remote`, the rack
  (`lca-virtual-drive --timing-mode lockstep`) and the relay (`lca-can-server`) each a process
  of its own on 127.0.0.1: the three-terminal set-up of the README, closed-loop through the
  controller.

Every backend runs on simulated time, so each run is the same on any host, however loaded;
the realtime CAN loop has its own test (test_can_realtime.py).

The position command: the same scenario with the controller on `command_interface: position`
(its ramp's position set-points on position_commands, every loop in the drive) and the pivot in
position mode (simulator `drive_modes`, bridge `modes: csp`), on `simulator` and `can_bridge`:
the same contract, and the pivot follows the set-points through the transition.
"""

from __future__ import annotations

import math
import os
import re
import select
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from support import wait_until

from lca_control import contract as pc
from lca_sim import load_robot
from lca_sim.canbus.master_state import AxisState, Snapshot
from lca_sim.config.paths import config_dir
from lca_sim.model.state_machine import MotionState, StopState
from lca_sim.ros.can_bridge_node import CanBridgeNode
from lca_sim.ros.can_drives import CycleValues
from lca_sim.ros.contract_cdr import ContractCdr
from lca_sim.ros.controller_node import ControllerNode
from lca_sim.ros.node_util import make_executor
from lca_sim.ros.simulator_node import SimulatorNode

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
PIVOT = JOINTS.index("pivot")
START_DEG = 45.0
SPEED_RAD_S = math.radians(5.0)
RAMP_START_S = 0.5
RAMP_S = 1.0
END_S = 4.2  # controller time: the pivot is at 61 deg, 6 deg past the transition
SWITCH_DEG = 55.0
# Every backend integrates the same plant at the same 0.1 ms step on simulated time, so the
# transition angle is set by gravity and differs only by what the CAN path adds by design:
# the quantisation of the encoder, torque and current, and the one cycle of transport delay
# (docs/can.md, "Lockstep"). Measured: 0.000 deg; the documented bound is 0.1 deg.
SWITCH_TOLERANCE_DEG = 0.1
# A state held for fewer messages than this is a flicker of the discrete state machine at a
# boundary (a sign change of a torque within one period), not a step of the sequence.
MIN_STATE_MESSAGES = 3
VOLTAGE_QUANTUM_V = 0.01  # 0x2016's count: the CAN backend may round up to it
LOAD_DRIVING = ("motor_and_load_driving", "load_driving")


def _overrides(**values: object) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _controller(ctx: Context, interface: str) -> ControllerNode:
    """The controller node as shipped, with this scenario's ramp-and-hold on the pivot."""
    with (config_dir() / "ros" / "controller.yaml").open() as f:
        values = yaml.safe_load(f)["controller"]["ros__parameters"]
    values.update(
        command_interface=interface,
        reference_source="ramp",
        profile_joint="pivot",
        ramp_start_s=RAMP_START_S,
        ramp_duration_s=RAMP_S,
        ramp_end_velocity=SPEED_RAD_S,
        ramp_hold_s=60.0,
    )
    return ControllerNode(context=ctx, parameter_overrides=_overrides(**values))


# The pivot in the drive's position mode, the others on current (0 A: the worm gears hold).
SIM_POSITION_MODES = ["current", "position", "current", "current"]
BRIDGE_POSITION_MODES = ["cst", "csp", "cst", "cst"]


def _start_simulator(ctx: Context, _tmp_path: Path, _stack: ExitStack, position: bool) -> Node:
    modes = {"drive_modes": SIM_POSITION_MODES} if position else {}
    return SimulatorNode(
        context=ctx,
        parameter_overrides=_overrides(
            timing_mode="lockstep",
            command_interface="current",
            initial_position=[0.0, math.radians(START_DEG), 0.0, 0.0],
            lockstep_subscribers=2,  # the controller and the probe
            **modes,
        ),
    )


def _rack_config(tmp_path: Path) -> Path:
    """The shipped rack with the pivot at START_DEG, watchdogs as shipped."""
    with (config_dir() / "can" / "rack.yaml").open() as f:
        rack = yaml.safe_load(f)
    rack["axes"]["pivot"]["initial_position"] = math.radians(START_DEG)
    rack_path = tmp_path / "rack.yaml"
    rack_path.write_text(yaml.safe_dump(rack))
    return rack_path


def _bridge(ctx: Context, tmp_path: Path, **values: object) -> CanBridgeNode:
    """The shipped bridge (config/ros/can_bridge.yaml) in lockstep at the controller's period.

    A name of its own per backend: the DDS graph of a new context may still list the node of
    the run before for a while.
    """
    with (config_dir() / "ros" / "can_bridge.yaml").open() as f:
        shipped = yaml.safe_load(f)["can_bridge"]["ros__parameters"]
    shipped.update(
        timing_mode="lockstep",
        cycle_hz=250.0,
        lockstep_subscribers=2,  # the controller and the probe
        **values,
    )
    return CanBridgeNode(
        f"can_bridge_{tmp_path.parent.name}", context=ctx, parameter_overrides=_overrides(**shipped)
    )


def _start_can_bridge(ctx: Context, tmp_path: Path, _stack: ExitStack, position: bool) -> Node:
    """The bridge with its in-process virtual rack (the shipped rack, pivot at START_DEG)."""
    modes = {"modes": BRIDGE_POSITION_MODES} if position else {}
    return _bridge(
        ctx,
        tmp_path,
        channel=f"test_plant_contract_{tmp_path.name}",
        rack_config=str(_rack_config(tmp_path)),
        **modes,
    )


def _spawn(stack: ExitStack, argv: list[str], ready: str, timeout_s: float = 120.0) -> str:
    """Start a console script of this venv; return the first stderr match of `ready`.

    The process is stopped (SIGTERM, then SIGKILL) when `stack` closes, and must exit 0 then.
    """
    proc = subprocess.Popen(
        [str(Path(sys.executable).parent / argv[0]), *argv[1:]],
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )

    def stop() -> None:
        proc.terminate()
        try:
            code = proc.wait(20.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait(20.0)
        assert code == 0, f"{argv[0]} exited {code}"

    stack.callback(stop)
    assert proc.stderr is not None
    seen = ""
    deadline_s = time.monotonic() + timeout_s
    while (left_s := deadline_s - time.monotonic()) > 0:
        if not select.select([proc.stderr], [], [], left_s)[0]:
            break
        line = proc.stderr.readline()
        if not line:
            break
        seen += line
        if match := re.search(ready, line):
            return match.group(0)
    pytest.fail(f"{argv[0]}: no {ready!r} within {timeout_s:g} s: {seen[-2000:]}")


def _start_can_bridge_remote(
    ctx: Context, tmp_path: Path, stack: ExitStack, position: bool
) -> Node:
    """Relay and rack as processes of their own on 127.0.0.1, the bridge on `lca_remote`."""
    assert not position  # the position command runs on the in-process backends
    url = _spawn(stack, ["lca-can-server", "--port", "0"], r"ws://127\.0\.0\.1:\d+/")
    rack = ["lca-virtual-drive", "--interface", "lca_remote", "--channel", url]
    rack += ["--timing-mode", "lockstep"]
    _spawn(stack, [*rack, "--config", str(_rack_config(tmp_path))], r"nodes ")
    return _bridge(ctx, tmp_path, interface="lca_remote", channel=url)


@dataclass(frozen=True)
class Backend:
    """A plant backend: its node's name in the graph and how to start it in-process."""

    node_name: str
    start: Callable[[Context, Path, ExitStack, bool], Node]  # bool: the pivot in position mode


BACKENDS: dict[str, Backend] = {
    "simulator": Backend("simulator", _start_simulator),
    "can_bridge": Backend("can_bridge", _start_can_bridge),
    "can_bridge_remote": Backend("can_bridge", _start_can_bridge_remote),
}
REFERENCE = "simulator"
POSITION_BACKENDS = ("simulator", "can_bridge")  # the position command's run


@dataclass
class ContractRun:
    """What a probe saw of one backend over the scenario."""

    backend: str
    state_names: tuple[str, ...]
    voltage_limit_v: dict[str, float]  # status name: the axis's amplifier limit (robot config)
    counts: dict[str, int] = field(default_factory=dict)
    publishes: dict[str, tuple[str, ...]] = field(default_factory=dict)
    subscribes: dict[str, tuple[str, ...]] = field(default_factory=dict)
    qos: dict[str, tuple[int, str]] = field(default_factory=dict)  # topic: (depth, reliability)
    joint_names: set[tuple[str, ...]] = field(default_factory=set)
    motor_names: set[tuple[str, ...]] = field(default_factory=set)
    status_names: set[tuple[str, ...]] = field(default_factory=set)
    key_sets: set[tuple[str, ...]] = field(default_factory=set)
    motion_states: set[str] = field(default_factory=set)
    drive_states: set[str] = field(default_factory=set)
    eta_while_stopped: set[str] = field(default_factory=set)
    problems: list[str] = field(default_factory=list)
    unknown_after_known: int = 0
    pivot_position: dict[int, float] = field(default_factory=dict)  # stamp ns: rad
    pivot_states: list[tuple[int, str]] = field(default_factory=list)  # (stamp ns, state)
    pivot_messages: list[int] = field(default_factory=list)  # messages in each pivot state
    latched_reason: str = ""
    commands_late: int = 0  # CAN: cycles that resent the previous command (lockstep: none)
    pivot_setpoints: list[float] = field(default_factory=list)  # position_commands, in order

    def note(self, problem: str) -> None:
        """Keep a problem (the first few of them: one bad key repeats every message)."""
        if len(self.problems) < 20:
            self.problems.append(problem)


class _Probe:
    """Subscribes to every state topic and checks each message against the contract."""

    def __init__(self, node: Node, run: ContractRun) -> None:
        self.run = run
        self._known: set[str] = set()  # joints whose drive state has been reported
        for topic, kind, handler in (
            (pc.JOINT_STATES, JointState, self._on_joint),
            (pc.MOTOR_STATES, JointState, self._on_motor),
            (pc.DRIVE_CHAIN_STATES, DiagnosticArray, self._on_drive),
            (pc.CLOCK, Clock, self._on_clock),
        ):
            node.create_subscription(kind, topic, handler, pc.STATE_QOS_DEPTH)
        node.create_subscription(
            Float64MultiArray, pc.POSITION_COMMANDS, self._on_position, pc.STATE_QOS_DEPTH
        )

    def _on_position(self, msg: Float64MultiArray) -> None:
        self.run.pivot_setpoints.append(msg.data[PIVOT])

    def _count(self, topic: str) -> None:
        self.run.counts[topic] = self.run.counts.get(topic, 0) + 1

    def _check_finite(self, topic: str, msg: JointState) -> None:
        n = len(msg.name)
        for key in ("position", "velocity", "effort"):
            values = getattr(msg, key)
            if len(values) != n or not all(math.isfinite(v) for v in values):
                self.run.note(f"{topic}.{key} {list(values)} for {list(msg.name)}")

    def _on_joint(self, msg: JointState) -> None:
        self._count(pc.JOINT_STATES)
        self.run.joint_names.add(tuple(msg.name))
        self._check_finite(pc.JOINT_STATES, msg)
        stamp = msg.header.stamp
        self.run.pivot_position[stamp.sec * 1_000_000_000 + stamp.nanosec] = msg.position[PIVOT]

    def _on_motor(self, msg: JointState) -> None:
        self._count(pc.MOTOR_STATES)
        self.run.motor_names.add(tuple(msg.name))
        self._check_finite(pc.MOTOR_STATES, msg)

    def _on_clock(self, _msg: Clock) -> None:
        self._count(pc.CLOCK)

    def _on_drive(self, msg: DiagnosticArray) -> None:
        run = self.run
        self._count(pc.DRIVE_CHAIN_STATES)
        run.status_names.add(tuple(s.name for s in msg.status))
        stamp = msg.header.stamp
        stamp_ns = stamp.sec * 1_000_000_000 + stamp.nanosec
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            run.key_sets.add(tuple(kv.key for kv in status.values))
            for problem in pc.drive_value_problems(values, run.state_names):
                run.note(f"{status.name}: {problem}")
            voltage_v = float(values.get("voltage_v", "nan"))
            if abs(voltage_v) > run.voltage_limit_v[status.name] + VOLTAGE_QUANTUM_V:
                run.note(f"{status.name}: voltage_v {voltage_v} beyond the amplifier's limit")
            drive_state = values.get("drive_state", "")
            motion_state = values.get("motion_state", "")
            if status.message != drive_state:
                run.note(f"{status.name}: message {status.message!r}, drive_state {drive_state!r}")
            run.motion_states.add(motion_state)
            run.drive_states.add(drive_state)
            if motion_state == "stop":
                run.eta_while_stopped.update((values.get("eta_m", ""), values.get("eta_l", "")))
            if pc.UNKNOWN in (drive_state, motion_state):
                run.unknown_after_known += status.name in self._known
            else:
                self._known.add(status.name)
            if status.name == pc.DRIVE_STATUS_PREFIX + "pivot":
                if not run.pivot_states or run.pivot_states[-1][1] != drive_state:
                    run.pivot_states.append((stamp_ns, drive_state))
                    run.pivot_messages.append(0)
                run.pivot_messages[-1] += 1


def _read_graph(probe: Node, plant: Node, node_name: str, run: ContractRun) -> None:
    """The plant node's topics and types as the graph shows them, and its endpoints' QoS.

    DDS does not carry a writer's history depth, so the QoS comes from the node's own
    publishers and subscriptions, the types from the graph (what a subscriber sees).
    """
    # rcl's own topics, and a managed node's (the CAN bridge's lifecycle transition events)
    infra = {"rosout", "parameter_events", f"{node_name}/transition_event"}
    wanted = {t.name.lstrip("/") for t in pc.PLANT_PUBLISHES if t.required}

    def topics(pairs: list[tuple[str, list[str]]]) -> dict[str, tuple[str, ...]]:
        return {n.lstrip("/"): tuple(t) for n, t in pairs if n.lstrip("/") not in infra}

    wait_until(
        lambda: wanted <= set(topics(probe.get_publisher_names_and_types_by_node(node_name, "/"))),
        f"{node_name}'s publishers in the graph",
    )
    run.publishes = topics(probe.get_publisher_names_and_types_by_node(node_name, "/"))
    run.subscribes = topics(probe.get_subscriber_names_and_types_by_node(node_name, "/"))
    endpoints = [(p.topic_name, p.qos_profile) for p in plant.publishers]
    endpoints += [(s.topic_name, s.qos_profile) for s in plant.subscriptions]
    for topic, qos in endpoints:
        reliable = qos.reliability == ReliabilityPolicy.RELIABLE
        run.qos[topic.lstrip("/")] = (qos.depth, pc.RELIABLE if reliable else pc.BEST_EFFORT)


def _run_backend(backend: str, tmp_path: Path, position: bool = False) -> ContractRun:
    """The scenario on one backend, in a fresh context, everything torn down afterwards.

    `position`: the controller on the position interface, the pivot in position mode.
    """
    tmp_path.mkdir(parents=True)
    spec = BACKENDS[backend]
    robot = load_robot("default")
    run = ContractRun(
        backend,
        robot.state_machine.state_names,
        {pc.DRIVE_STATUS_PREFIX + a.name: a.motor.voltage_limit_v for a in robot.axes},
    )
    ctx = Context()
    rclpy.init(context=ctx)  # ROS_DOMAIN_ID from the environment (conftest: loopback only)
    executor = make_executor(ctx)  # the executor the nodes spin in production (run_node)
    nodes: list[Node] = []
    stack = ExitStack()  # the backend's processes, stopped after its node
    try:
        # The controller and the probe first: building them cannot stall a wall-clock plant.
        ctl = _controller(ctx, "position" if position else "current")
        probe = Node("contract_probe", context=ctx)
        nodes += [ctl, probe]
        _Probe(probe, run)
        plant = spec.start(ctx, tmp_path, stack, position)
        nodes.append(plant)
        for node in nodes:
            executor.add_node(node)
        wait_until(
            lambda: ctl.core.elapsed_s >= END_S,
            f"{END_S} s of the scenario on {backend}",
            timeout_s=90.0,
            step=lambda: executor.spin_once(timeout_sec=0.05),
        )
        if isinstance(plant, CanBridgeNode):
            run.latched_reason = plant.bridge.latched_reason()
            run.commands_late = plant.bridge.counters.commands_late
        _read_graph(probe, plant, plant.get_name(), run)
        return run
    finally:
        for node in reversed(nodes):
            node.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=ctx)
        stack.close()


class _Runs:
    """Each backend's run, made once per module and shared by its tests."""

    def __init__(self, tmp_path_factory: pytest.TempPathFactory) -> None:
        self._tmp = tmp_path_factory
        self._runs: dict[tuple[str, bool], ContractRun] = {}

    def __getitem__(self, backend: str) -> ContractRun:
        return self.get(backend)

    def get(self, backend: str, position: bool = False) -> ContractRun:
        """The backend's run; `position`: on the position command."""
        key = (backend, position)
        if key not in self._runs:
            name = f"{backend}_position" if position else backend
            self._runs[key] = _run_backend(backend, self._tmp.mktemp(name) / "run", position)
        return self._runs[key]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[_Runs]:
    yield _Runs(tmp_path_factory)


@pytest.fixture(params=list(BACKENDS))
def run(request: pytest.FixtureRequest, runs: _Runs) -> ContractRun:
    return runs[str(request.param)]


def _switch(run: ContractRun) -> tuple[str, float]:
    """The pivot's first load-driving state after motor driving, and its angle (deg)."""
    states = run.pivot_states
    names = [name for _, name in states]
    assert "motor_driving" in names, names
    first = names.index("motor_driving")
    stamp_ns, name = next(s for s in states[first:] if s[1].startswith(LOAD_DRIVING))
    return name, math.degrees(run.pivot_position[stamp_ns])


def _sequence(run: ContractRun) -> list[str]:
    """The pivot's drive states from its first motor driving on, flickers dropped, merged.

    Before it the pivot breaks away from rest: stop states only (test_can_swap saw the axis
    stick and slip there over CAN's wall-clock timing, as a worm gear does, so their order is
    not compared), or `unknown` before the first report.
    """
    names = [name for _, name in run.pivot_states]
    first = names.index("motor_driving")
    stop_states = {s.name.lower() for s in StopState}
    assert set(names[:first]) <= stop_states | {pc.UNKNOWN}, names
    kept = [
        name
        for name, n in zip(names[first:], run.pivot_messages[first:], strict=True)
        if n >= MIN_STATE_MESSAGES
    ]
    return [name for i, name in enumerate(kept) if i == 0 or kept[i - 1] != name]


# ------------------------------------------------------------------ every backend: the contract


def test_the_run_went_through(run: ContractRun) -> None:
    """The scenario ran: every state topic arrived, no safety stop, the pivot passed 55 deg."""
    for topic in (pc.JOINT_STATES, pc.MOTOR_STATES, pc.DRIVE_CHAIN_STATES):
        assert run.counts.get(topic, 0) > 500, run.counts  # 4.2 s at 250 Hz: about 1050
    assert run.latched_reason == ""
    assert run.commands_late == 0  # lockstep: every command answers the state before it
    # Every backend runs on simulated time and publishes it: one /clock per state.
    assert run.counts.get(pc.CLOCK, 0) >= run.counts[pc.JOINT_STATES] - 1, run.counts
    reached_deg = math.degrees(max(run.pivot_position.values()))
    assert reached_deg > SWITCH_DEG + 3.0


def test_publishes_the_contract_topics_types_and_qos(run: ContractRun) -> None:
    """Every required plant topic with its type and QoS; nothing outside the contract."""
    contract = {t.name.lstrip("/"): t for t in pc.PLANT_PUBLISHES}
    required = {name for name, t in contract.items() if t.required}
    assert required <= set(run.publishes), run.publishes
    assert set(run.publishes) <= set(contract), run.publishes
    for topic, types in run.publishes.items():
        spec = contract[topic]
        assert types == (spec.type,)
        assert run.qos[topic] == (spec.qos.depth, spec.qos.reliability), topic
    accepted = {t.name: (t.type,) for t in pc.PLANT_SUBSCRIBES}
    needed = {t.name: (t.type,) for t in pc.PLANT_SUBSCRIBES if t.required}
    taken = {k: v for k, v in run.subscribes.items() if k in accepted}
    assert needed.items() <= taken.items()
    assert all(accepted[k] == v for k, v in taken.items())
    for spec in pc.PLANT_SUBSCRIBES:
        if spec.name in taken:
            assert run.qos[spec.name] == (spec.qos.depth, spec.qos.reliability), spec.name


def test_joint_names_and_order(run: ContractRun) -> None:
    """joint_states, motor_states and the drive-chain statuses: the robot's axes, in order."""
    assert tuple(load_robot("default").axis_names) == JOINTS
    assert run.joint_names == {JOINTS}
    assert run.motor_names == {JOINTS}
    assert run.status_names == {tuple(pc.DRIVE_STATUS_PREFIX + j for j in JOINTS)}


def test_drive_chain_keys_are_the_contracts(run: ContractRun) -> None:
    """Every drive_chain/<joint> status has exactly the contract's keys, in its order."""
    assert run.key_sets == {pc.DRIVE_STATE_KEYS}


def test_vocabularies(run: ContractRun) -> None:
    """Motion states in stop/direct/reverse, drive states among the robot's state names.

    `unknown` is allowed only before a joint's first report (the virtual drive's first
    drive-chain PDO may come a cycle after its first position), never once it has reported.
    """
    assert run.motion_states - {pc.UNKNOWN} <= set(pc.MOTION_STATE_CODES)
    assert {"stop", "direct"} <= run.motion_states  # held joints, and the pivot going up
    assert run.drive_states - {pc.UNKNOWN} <= set(run.state_names)
    assert {"stop_hold", "motor_driving"} <= run.drive_states
    assert run.unknown_after_known == 0


def test_no_value_outside_its_documented_range(run: ContractRun) -> None:
    """Every key within its range or NaN where NaN is allowed; joint values finite."""
    assert run.problems == []


def test_efficiency_is_nan_while_stopped(run: ContractRun) -> None:
    """Eq. (10) has no efficiency while the gear is locked: 'nan', never a raw marker."""
    assert run.eta_while_stopped == {"nan"}


# ---------------------------------------------------------- every backend against the reference


@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != REFERENCE])
def test_same_drive_states_and_switch_angle_as_the_reference(backend: str, runs: _Runs) -> None:
    """The pivot's drive-state sequence and its switch to load driving match the simulator's."""
    reference, other = runs[REFERENCE], runs[backend]
    assert _sequence(other) == _sequence(reference)
    ref_state, ref_deg = _switch(reference)
    state, deg = _switch(other)
    assert state == ref_state
    assert ref_deg == pytest.approx(SWITCH_DEG, abs=1.0)
    assert deg == pytest.approx(ref_deg, abs=SWITCH_TOLERANCE_DEG)


# ------------------------------------------------------------------ the position command

# The pivot follows the controller's position set-points (a 5 deg/s ramp). The CAN path adds
# one cycle of transport delay (docs/can.md): its state k + 1 is where the simulator's state k
# is, so each backend is compared with the set-point of the state SETPOINT_DELAY before.
# Measured: 5.3e-5 rad on both (3.5e-4 rad, a period of the ramp, one state off).
SETPOINT_DELAY = {"simulator": 0, "can_bridge": 1}
SETPOINT_BOUND_RAD = 1e-4


@pytest.fixture(params=POSITION_BACKENDS)
def position_run(request: pytest.FixtureRequest, runs: _Runs) -> ContractRun:
    return runs.get(str(request.param), position=True)


def test_position_command_keeps_the_contract(position_run: ContractRun) -> None:
    """On position_commands: every state topic, the contract's keys and ranges, no safety stop."""
    run = position_run
    for topic in (pc.JOINT_STATES, pc.MOTOR_STATES, pc.DRIVE_CHAIN_STATES):
        assert run.counts.get(topic, 0) > 500, run.counts
    assert run.latched_reason == ""
    assert run.commands_late == 0
    assert run.problems == []
    assert run.key_sets == {pc.DRIVE_STATE_KEYS}
    assert run.joint_names == {JOINTS}
    spec = next(t for t in pc.PLANT_SUBSCRIBES if t.name == pc.POSITION_COMMANDS)
    assert run.subscribes[spec.name] == (spec.type,)
    assert run.qos[spec.name] == (spec.qos.depth, spec.qos.reliability)
    assert math.degrees(max(run.pivot_position.values())) > SWITCH_DEG + 3.0


def test_position_command_is_followed(position_run: ContractRun) -> None:
    """The pivot (position mode / csp) follows the set-points through the 55 deg transition."""
    run = position_run
    q = [run.pivot_position[ns] for ns in sorted(run.pivot_position)]
    sp = run.pivot_setpoints
    n = min(len(q) - 2, len(sp))
    assert n > 900  # about 1050 states in 4.2 s
    assert sp[0] == pytest.approx(math.radians(START_DEG), abs=1e-6)  # from the pose held
    lags = [max(abs(q[k + d] - sp[k]) for k in range(n)) for d in (0, 1, 2)]
    print(f"{run.backend}: max |q[k + d] - setpoint[k]|, d = 0, 1, 2: {lags}")
    assert lags[SETPOINT_DELAY[run.backend]] <= SETPOINT_BOUND_RAD
    assert min(lags) == lags[SETPOINT_DELAY[run.backend]]
    assert sp[n - 1] - sp[0] > math.radians(SWITCH_DEG + 3.0 - START_DEG)  # it went up


def test_position_command_same_drive_states_as_the_simulator(runs: _Runs) -> None:
    """On csp the pivot's drive states and its switch to load driving are the simulator's."""
    reference, other = (runs.get(b, position=True) for b in POSITION_BACKENDS)
    assert _sequence(other) == _sequence(reference)
    ref_state, ref_deg = _switch(reference)
    state, deg = _switch(other)
    print(f"position command: switch {ref_deg:.4f} deg (simulator), {deg:.4f} deg (CAN)")
    assert state == ref_state
    assert ref_deg == pytest.approx(SWITCH_DEG, abs=1.0)
    assert deg == pytest.approx(ref_deg, abs=SWITCH_TOLERANCE_DEG)


# ------------------------------------------------------------------------- regressions


def test_bridge_says_stop_not_stopped(runs: _Runs) -> None:
    """The bridge's held axes are `stop` (the contract's spelling; it said `stopped`)."""
    run = runs["can_bridge"]
    assert "stop" in run.motion_states
    assert "stopped" not in run.motion_states


def test_bridge_key_set_is_the_contracts(runs: _Runs) -> None:
    """The bridge's keys: load/friction torque and voltage present, no gear_ratio."""
    assert runs["can_bridge"].key_sets == {pc.DRIVE_STATE_KEYS}


def test_bridge_efficiency_of_a_stopped_axis_is_nan(runs: _Runs) -> None:
    """0xFFFF (undefined) on the bus is 'nan' on the topic, not '65.535'."""
    assert runs["can_bridge"].eta_while_stopped == {"nan"}


# ----------------------------------------------------------- the builder and the bridge's map


def _snapshot(**axis: float) -> Snapshot:
    return Snapshot(12.5, 7, tuple(AxisState(**axis) for _ in JOINTS))  # type: ignore[arg-type]


def _map(snap: Snapshot, decoded: frozenset[str]) -> CycleValues:
    robot = load_robot("default")
    return CycleValues(
        snap,
        tuple(a.motor.torque_constant_nm_per_a for a in robot.axes),
        tuple(a.gear_ratio for a in robot.axes),
        robot.state_machine.state_names,
        decoded,
    )


def _drive_values(values: CycleValues) -> list[dict[str, str]]:
    cdr = ContractCdr(JOINTS).drive_chain(0, 0, values.drive_chain())
    array = deserialize_message(cdr, DiagnosticArray)
    assert [s.message for s in array.status] == [s.values[1].value for s in array.status]
    return [{kv.key: kv.value for kv in s.values} for s in array.status]


VIRTUAL_DRIVE_FIELDS = frozenset(AxisState.__slots__) - {"statusword"}


def test_motion_state_names_are_the_models() -> None:
    """The contract's motion vocabulary is MotionState's names, lower case, with its codes."""
    assert {m.name.lower(): int(m) for m in MotionState} == pc.MOTION_STATE_CODES
    assert [pc.motion_state_name(float(m)) for m in MotionState] == [
        m.name.lower() for m in MotionState
    ]
    assert pc.motion_state_name(math.nan) == pc.UNKNOWN
    assert pc.motion_state_code("stop") == 0
    with pytest.raises(pc.UnknownStateError, match="valid: stop, direct, reverse"):
        pc.motion_state_code("stopped")


def test_bridge_map_of_a_stopped_virtual_drive() -> None:
    """A stopped axis from the virtual drive: `stop`, its stop state, NaN efficiencies."""
    snap = _map(
        _snapshot(current_a=2.0, motion_state=0, drive_state=0, load_torque_nm=0.25),
        VIRTUAL_DRIVE_FIELDS,
    )
    robot = load_robot("default")
    pivot = robot.axes[PIVOT]
    k_t = pivot.motor.torque_constant_nm_per_a
    assert snap.joint[2][PIVOT] == pytest.approx(2.0 * k_t * pivot.gear_ratio)  # effort
    assert snap.motor[2][PIVOT] == 2.0  # motor_states' effort: the current
    values = _drive_values(snap)[PIVOT]
    assert float(values["motor_torque_nm"]) == pytest.approx(2.0 * k_t)
    assert tuple(values) == pc.DRIVE_STATE_KEYS
    assert values["motion_state"] == "stop"
    assert values["drive_state"] == StopState.STOP_HOLD.name.lower()
    assert values["eta_m"] == values["eta_l"] == "nan"
    assert values["load_torque_nm"] == "0.25"
    assert values["current_a"] == "2.0"
    assert pc.drive_value_problems(values, robot.state_machine.state_names) == []


def test_bridge_map_before_the_first_drive_chain_pdo() -> None:
    """Drive-state code -1 (no TPDO3 yet): both states unknown, not `stop`."""
    values = _drive_values(_map(_snapshot(drive_state=-1), VIRTUAL_DRIVE_FIELDS))[PIVOT]
    assert values["motion_state"] == values["drive_state"] == pc.UNKNOWN


def test_bridge_map_of_a_real_cia402_drive() -> None:
    """A drive mapping only CiA 402 objects: the drive chain unknown and NaN, not 0."""
    # What 0x6041, 0x6064, 0x606C and 0x6078 fill (the master's REQUIRED_TPDO_OBJECTS).
    decoded = frozenset(
        ("statusword", "position", "motor_position_rad", "velocity", "motor_velocity_rad_s")
    ) | {"current_a"}
    values = _drive_values(_map(_snapshot(current_a=1.0), decoded))[PIVOT]
    assert values["motion_state"] == values["drive_state"] == pc.UNKNOWN
    for key in ("eta_m", "eta_l", "load_torque_nm", "friction_torque_nm", "voltage_v"):
        assert values[key] == "nan", key
    assert float(values["motor_torque_nm"]) > 0.0
    robot = load_robot("default")
    assert pc.drive_value_problems(values, robot.state_machine.state_names) == []
    assert pc.drive_value_problems(values, robot.state_machine.state_names, allow_unknown=False)


def test_range_check_catches_a_raw_undefined_marker() -> None:
    """The check the suite applies: 65.535 for an efficiency, `stopped`, a missing key."""
    names = load_robot("default").state_machine.state_names
    good = _drive_values(_map(_snapshot(drive_state=0), VIRTUAL_DRIVE_FIELDS))[PIVOT]
    assert pc.drive_value_problems(good, names) == []
    assert pc.drive_value_problems({**good, "eta_m": "65.535"}, names) == [
        "eta_m 65.535 outside [0, 1] 1"
    ]
    assert pc.drive_value_problems({**good, "motion_state": "stopped"}, names) == [
        "motion_state 'stopped' not in ['stop', 'direct', 'reverse']"
    ]
    assert pc.drive_value_problems({**good, "current_a": "nan"}, names) == [
        "current_a is NaN, which it must never be"
    ]
    del good["voltage_v"]
    assert pc.drive_value_problems(good, names)
