"""The efficiency state machine (Figs 6-8, Table 1), one transition at a time.

The lower level is checked through the compiled `classify`; the upper level (STOP, DIRECT,
REVERSE) and the stop sub-states through single steps of the kernel on a one-axis plant whose
inertia and load torque are set by hand, so every threshold is an exact number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim import RobotParams, Simulator
from lca_sim.model import kernel
from lca_sim.model.state_machine import MotionState


def _rule_name(robot: RobotParams, direction: int, tau_m: float, tau_l: float) -> str:
    model = Simulator(robot).model_array
    rule = kernel.classify(direction, tau_m, tau_l, model)
    return robot.state_machine.rules[rule].name


# (direction, tau_m, tau_l, state): tau_l is the torque the load demands (eq. 8), so a positive
# tau_l resists direct motion and drives reverse motion.
LOWER_LEVEL = [
    (+1, 0.5, 0.3, "motor_driving"),  # lifting: load resists
    (+1, 0.5, 0.0, "motor_driving"),  # no load: it resists nothing, motor alone drives
    (+1, 0.2, -0.3, "motor_and_load_driving_load_dominant"),
    (+1, 0.5, -0.3, "motor_and_load_driving_motor_dominant"),
    (+1, 0.3, -0.3, "motor_and_load_driving_motor_dominant"),  # |tau_m| = |tau_l|: motor side
    (+1, -0.1, -0.3, "load_driving"),  # motor brakes, gravity drives
    (+1, 0.0, -0.3, "load_driving"),  # zero motor torque counts as braking
    (+1, -0.1, 0.3, "coasting"),  # both resist: only inertia drives
    (-1, -0.5, -0.3, "motor_driving"),  # the mirror of every row above
    (-1, -0.5, 0.0, "motor_driving"),
    (-1, -0.2, 0.3, "motor_and_load_driving_load_dominant"),
    (-1, -0.5, 0.3, "motor_and_load_driving_motor_dominant"),
    (-1, -0.3, 0.3, "motor_and_load_driving_motor_dominant"),
    (-1, 0.1, 0.3, "load_driving"),
    (-1, 0.0, 0.3, "load_driving"),
    (-1, 0.1, -0.3, "coasting"),
]


@pytest.mark.parametrize(("direction", "tau_m", "tau_l", "state"), LOWER_LEVEL)
def test_lower_level_state(
    default_robot: RobotParams, direction: int, tau_m: float, tau_l: float, state: str
) -> None:
    """Fig. 8 and its mirror: each torque combination picks its state."""
    assert _rule_name(default_robot, direction, tau_m, tau_l) == state


@given(
    tau_m=st.floats(-5.0, 5.0),
    tau_l=st.floats(-5.0, 5.0),
)
def test_reverse_is_the_mirror_of_direct(tau_m: float, tau_l: float) -> None:
    """Section 4.1: reverse motion is direct motion with tau_m and tau_l negated."""
    from lca_sim import load_robot

    robot = load_robot("default")
    assert _rule_name(robot, -1, -tau_m, -tau_l) == _rule_name(robot, +1, tau_m, tau_l)


@given(
    direction=st.sampled_from([-1, 1]),
    tau_m=st.floats(-5.0, 5.0),
    tau_l=st.floats(-5.0, 5.0),
    speed_rad_s=st.floats(0.0, 500.0),
)
def test_gear_losses_never_negative(
    direction: int, tau_m: float, tau_l: float, speed_rad_s: float
) -> None:
    """Eq. (11): whatever the torques, the efficiencies only ever burn power."""
    from lca_sim import load_robot

    robot = load_robot("default")
    name = _rule_name(robot, direction, tau_m, tau_l)
    for axis in robot.axes:
        eff = axis.efficiency[(MotionState(direction), name)]
        w = direction * speed_rad_s
        loss_w = (1.0 - eff.eta_m) * tau_m * w + (eff.eta_l - 1.0) * tau_l * w
        assert loss_w >= -1e-12


def test_table1_defaults(default_robot: RobotParams) -> None:
    """The default robot carries Table 1 on the emitting torque (docs/model.md)."""
    pivot = default_robot.axes[1].efficiency
    expected = {
        ("motor_driving", MotionState.DIRECT): (0.9, 1.0),
        ("motor_driving", MotionState.REVERSE): (0.9, 1.0),
        ("motor_and_load_driving_load_dominant", MotionState.DIRECT): (1.0, 0.55),
        ("motor_and_load_driving_load_dominant", MotionState.REVERSE): (1.0, 0.16),
        ("motor_and_load_driving_motor_dominant", MotionState.DIRECT): (1.0, 0.45),
        ("motor_and_load_driving_motor_dominant", MotionState.REVERSE): (1.0, 0.06),
    }
    for (state, direction), (eta_m, eta_l) in expected.items():
        assert (pivot[(direction, state)].eta_m, pivot[(direction, state)].eta_l) == (eta_m, eta_l)


# --- one-axis plant driven through the kernel ---------------------------------------------------


@dataclass
class OneAxis:
    """A single drive chain with a hand-set load, stepped by the real kernel."""

    robot: RobotParams
    tau_l_nm: float
    inertia_kg_m2: float = 1e-3
    position: float = 0.0
    velocity_rad_s: float = 0.0
    current_a: float = 0.0
    motion: int = 0
    irreversible: bool = True
    q_min: float = -10.0
    q_max: float = 10.0

    def __post_init__(self) -> None:
        pivot = self.robot.axes[1]
        machine = self.robot.state_machine
        p = np.zeros((kernel.N_PARAMS, 1))
        p[kernel.P_GEAR_RATIO] = 1.0
        p[kernel.P_RESISTANCE_OHM] = pivot.motor.resistance_ohm
        p[kernel.P_INDUCTANCE_H] = pivot.motor.inductance_h
        p[kernel.P_TORQUE_CONSTANT] = pivot.motor.torque_constant_nm_per_a
        p[kernel.P_ROTOR_INERTIA] = 0.0
        p[kernel.P_VOLTAGE_LIMIT_V] = 100.0
        f = pivot.friction
        p[kernel.P_STATIC_DIRECT] = f.static_direct_nm
        p[kernel.P_STATIC_REVERSE] = f.static_reverse_nm
        p[kernel.P_COULOMB_DIRECT] = f.coulomb_direct_nm
        p[kernel.P_COULOMB_REVERSE] = f.coulomb_reverse_nm
        p[kernel.P_VISCOUS_DIRECT] = f.viscous_direct_nm_s_per_rad
        p[kernel.P_VISCOUS_REVERSE] = f.viscous_reverse_nm_s_per_rad
        p[kernel.P_POSITION_MIN] = self.q_min
        p[kernel.P_POSITION_MAX] = self.q_max
        p[kernel.P_VELOCITY_EPS] = machine.velocity_eps_rad_s
        p[kernel.P_TORQUE_EPS] = machine.motor_torque_eps_nm
        eta = np.ones((1, 2, len(machine.rules), 2))
        for k, direction in enumerate((MotionState.DIRECT, MotionState.REVERSE)):
            for r, rule in enumerate(machine.rules):
                entry = pivot.efficiency[(direction, rule.name)]
                eta[0, k, r] = (entry.eta_m, entry.eta_l)
        self.model = kernel.pack_model(p, machine.rule_codes(), eta, self.irreversible)
        self.work = np.zeros((kernel.work_rows(1), 1))
        self.work[kernel.X_POSITION] = self.position
        self.work[kernel.X_VELOCITY] = self.velocity_rad_s
        self.work[kernel.X_MOTION] = self.motion

    def step_with_torque(self, tau_m_nm: float, dt_s: float = 1e-4) -> None:
        """One step with the current (and so tau_m) held at the value given."""
        k_t = self.model[kernel.P_TORQUE_CONSTANT, 0]
        r_ohm = self.model[kernel.P_RESISTANCE_OHM, 0]
        self.work[kernel.X_CURRENT] = tau_m_nm / k_t
        # The voltage that keeps the current exactly where it is (steady state of L di/dt).
        volts = (
            r_ohm * tau_m_nm / k_t
            + k_t * self.model[kernel.P_GEAR_RATIO, 0] * self.work[kernel.X_VELOCITY, 0]
        )
        code = kernel.step(
            np.array([[self.inertia_kg_m2]]),
            np.array([self.tau_l_nm]),
            np.array([volts]),
            self.work,
            self.model,
            dt_s,
        )
        assert code == kernel.OK
        self.position = float(self.work[kernel.X_POSITION, 0])
        self.velocity_rad_s = float(self.work[kernel.X_VELOCITY, 0])
        self.current_a = float(self.work[kernel.X_CURRENT, 0])
        self.motion = int(self.work[kernel.X_MOTION, 0])

    def state_name(self) -> str:
        """The current drive state's name."""
        return self.robot.state_machine.state_names[int(self.work[kernel.X_DRIVE, 0])]

    def signal(self, row: int) -> float:
        """One signal of the last step (a `kernel.S_*` row)."""
        return float(self.work[row, 0])


def _breakaway_torque(robot: RobotParams, direction: int, tau_l: float) -> float:
    """The motor torque at which a stopped pivot starts (Fig. 7), from Table 1 and eq. (3)."""
    pivot = robot.axes[1]
    name = _rule_name(robot, direction, direction * 1.0, tau_l)  # provisional; refined below
    for _ in range(3):
        eff = pivot.efficiency[(MotionState(direction), name)]
        static = (
            pivot.friction.static_direct_nm if direction > 0 else pivot.friction.static_reverse_nm
        )
        # d (eta_m tau_m - eta_l tau_l) = static
        tau = (direction * static + eff.eta_l * tau_l) / eff.eta_m
        name = _rule_name(robot, direction, tau, tau_l)
    return tau


@pytest.mark.parametrize(
    ("direction", "tau_l"),
    [(+1, 0.4), (+1, -0.05), (-1, 0.4), (-1, -0.4), (+1, 0.0), (-1, 0.0)],
    ids=["direct-lifting", "direct-load-helps", "reverse-load-helps", "reverse-lifting",
         "direct-unloaded", "reverse-unloaded"],
)  # fmt: skip
def test_breakaway_threshold(default_robot: RobotParams, direction: int, tau_l: float) -> None:
    """STOP -> DIRECT/REVERSE exactly when eta_m tau_m - eta_l tau_l beats the static friction."""
    threshold = _breakaway_torque(default_robot, direction, tau_l)
    assert direction * threshold > 0.0
    below = OneAxis(default_robot, tau_l_nm=tau_l)
    below.step_with_torque(threshold * 0.999)
    assert below.motion == 0
    assert below.position == 0.0
    assert below.state_name() == ("stop_motor_direct" if threshold > 0 else "stop_motor_reverse")
    above = OneAxis(default_robot, tau_l_nm=tau_l)
    above.step_with_torque(threshold * 1.001)
    assert above.motion == direction
    assert direction * above.velocity_rad_s > 0.0


@pytest.mark.parametrize("tau_l", [0.3, -0.3, 5.0, -5.0])
def test_load_alone_cannot_start_an_irreversible_stop(
    default_robot: RobotParams, tau_l: float
) -> None:
    """Fig. 7: with |tau_m| <= T_m_eps the gear holds any load, for 1 s of steps."""
    axis = OneAxis(default_robot, tau_l_nm=tau_l)
    for _ in range(10_000):
        axis.step_with_torque(0.5 * default_robot.state_machine.motor_torque_eps_nm)
    assert (axis.motion, axis.position, axis.state_name()) == (0, 0.0, "stop_hold")


@pytest.mark.parametrize("tau_l", [0.3, -0.3])
def test_reversible_stop_lets_the_load_start(reversible_robot: RobotParams, tau_l: float) -> None:
    """Without irreversibility a load above static friction starts the axis its own way."""
    axis = OneAxis(reversible_robot, tau_l_nm=tau_l, irreversible=False)
    axis.step_with_torque(0.0)
    assert axis.motion == (-1 if tau_l > 0 else 1)


def test_stop_from_direct_when_velocity_reaches_zero(default_robot: RobotParams) -> None:
    """DIRECT -> STOP when the axis decelerates to zero; it then holds (no drift, no chatter)."""
    axis = OneAxis(default_robot, tau_l_nm=0.3, velocity_rad_s=2.0, motion=1)
    steps_to_stop = 0
    while axis.motion != 0:
        axis.step_with_torque(0.0)
        steps_to_stop += 1
        assert steps_to_stop < 10_000
    # Decelerated by load + Coulomb friction: v0 J / (tau_l + f_c), to within a step.
    friction = default_robot.axes[1].friction
    expected_steps = 2.0 * 1e-3 / (0.3 + friction.coulomb_direct_nm) / 1e-4
    assert abs(steps_to_stop - expected_steps) <= 1.0
    held_at = axis.position
    motions = set()
    for _ in range(5_000):
        axis.step_with_torque(0.0)
        motions.add(axis.motion)
    assert motions == {0}
    assert axis.position == held_at
    assert axis.velocity_rad_s == 0.0


def test_direct_to_reverse_passes_through_stop(default_robot: RobotParams) -> None:
    """Fig. 6 has no DIRECT -> REVERSE edge: a reversal stops for one step, then breaks away."""
    axis = OneAxis(default_robot, tau_l_nm=0.0, velocity_rad_s=0.5, motion=1)
    seen: list[int] = []
    for _ in range(2_000):
        axis.step_with_torque(-0.5)
        if not seen or seen[-1] != axis.motion:
            seen.append(axis.motion)
    assert seen == [1, 0, -1]


def test_end_stop_blocks_motion_into_it(default_robot: RobotParams) -> None:
    """At an end stop the axis stays put while the motor pushes into it, and leaves it freely."""
    axis = OneAxis(default_robot, tau_l_nm=0.0, q_max=0.001)
    for _ in range(2_000):
        axis.step_with_torque(0.5)
    assert axis.position == 0.001
    assert axis.state_name() == "stop_end_stop"
    axis.step_with_torque(-0.5)
    assert axis.motion == -1


def test_stop_state_reports_eq3_static_friction(default_robot: RobotParams) -> None:
    """Eq. (3): a stopped axis shows min(tau_m, Gamma_sd) as its friction torque."""
    static = default_robot.axes[1].friction.static_direct_nm
    for tau_m in (0.5 * static, 0.9 * static):
        axis = OneAxis(default_robot, tau_l_nm=5.0)  # a heavy load keeps it stopped
        axis.step_with_torque(tau_m)
        assert axis.signal(kernel.S_FRICTION_TORQUE) == pytest.approx(tau_m)
    axis = OneAxis(default_robot, tau_l_nm=5.0)
    axis.step_with_torque(3.0 * static)
    assert axis.signal(kernel.S_FRICTION_TORQUE) == pytest.approx(static)
    assert math.isnan(axis.signal(kernel.S_ETA_M))


def test_state_names_cover_stop_and_moving_states(default_robot: RobotParams) -> None:
    """The drive-state numbering: the four stop sub-states, then the YAML's moving states."""
    sim = Simulator(default_robot)
    assert sim.state_names == (
        "stop_hold",
        "stop_motor_direct",
        "stop_motor_reverse",
        "stop_end_stop",
        "motor_driving",
        "motor_and_load_driving_load_dominant",
        "motor_and_load_driving_motor_dominant",
        "load_driving",
        "coasting",
    )
