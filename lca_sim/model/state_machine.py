"""The two-level efficiency state machine of the paper (section 4.1, Figs 6-8, Table 1).

Upper level (Fig. 6): the motion state, from the sign of the motor velocity with the stop
threshold V_eps: STOP, DIRECT, REVERSE.

Lower level: the drive state.

* In STOP (Fig. 7) the gear is irreversible: the load alone cannot start motion. The sub-states
  only say what the motor is doing while the axis is held (`stop_hold` when |tau_m| <= T_m_eps,
  `stop_motor_direct` / `stop_motor_reverse` while the motor pushes below breakaway, and
  `stop_end_stop` against a joint end stop). They carry no efficiency: the axis is locked.
* In DIRECT and REVERSE motion (Fig. 8 and its mirror) the drive state is chosen by a table of
  rules read from the robot YAML. Each rule names a state and the conditions under which it holds,
  written *along the motion direction*, so one table serves both directions (the paper's "replace
  tau_m and tau_l by -tau_m and -tau_l"):

  ======================================  ======  =========  =========
  state (default table)                   motor   load       dominant
  ======================================  ======  =========  =========
  motor_driving                           drives  resists    any
  motor_and_load_driving_load_dominant    drives  drives     load
  motor_and_load_driving_motor_dominant   drives  drives     motor
  load_driving                            brakes  drives     any
  coasting                                brakes  resists    any
  ======================================  ======  =========  =========

  "motor drives" means d * tau_m > 0, "load drives" means -d * tau_l > 0, with d = +1 in DIRECT
  and -1 in REVERSE and tau_l the torque the load *demands* (eq. 8, tau_l = N^-1 (C qdot + Q)).
  "load dominant" means |tau_m| < |tau_l|. Table 1 writes these conditions with the load torque
  the load *applies* (-tau_l), which is why its "motor driving" row reads tau_m * tau_l < 0.

  The load's sign is read through a band (`load_torque_band_nm`): a |tau_l| within a few thousand
  rounding units of the axis's torque scale is taken as exactly zero, so an axis without a
  gravity load (the L-arm) is not thrown between Fig. 8's states by Pinocchio's rounding noise.
  A zero load neither drives nor dominates: the motor alone drives (`motor_driving`) or, braking,
  the axis coasts.

Each state carries eta_m and eta_l per direction (eq. 10). See docs/model.md for why each
coefficient applies to the torque of the element that emits power (eq. 11).
"""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from lca_sim.errors import ConfigError
from lca_sim.model.schema import MappingReader


class MotionState(enum.IntEnum):
    """Upper level of the state machine (Fig. 6). The value is the direction sign d."""

    STOP = 0
    DIRECT = 1
    REVERSE = -1


class StopState(enum.IntEnum):
    """Lower level inside STOP (Fig. 7). Indices 0-3 of the drive-state numbering."""

    STOP_HOLD = 0
    STOP_MOTOR_DIRECT = 1
    STOP_MOTOR_REVERSE = 2
    STOP_END_STOP = 3


# Index of the first moving drive state; moving states follow the stop states in config order.
FIRST_MOVING_STATE = len(StopState)


class MotorCondition(enum.IntEnum):
    """What the motor torque does along the motion direction."""

    ANY = 0
    DRIVES = 1  # d * tau_m > 0: the motor emits power into the gear
    BRAKES = 2  # d * tau_m <= 0: the motor absorbs power (or none)


class LoadCondition(enum.IntEnum):
    """What the load torque does along the motion direction (tau_l after the sign band)."""

    ANY = 0
    DRIVES = 1  # -d * tau_l > band: the load emits power into the gear
    RESISTS = 2  # -d * tau_l <= band: the load absorbs power (or none)


# Width of the load's sign band in units of machine epsilon times the axis's torque scale: 2**12,
# see `load_torque_band_nm`.
LOAD_SIGN_BAND_EPS = 4096.0


def load_torque_band_nm(torque_scale_nm: float) -> float:
    """The band |tau_l| <= this, N m at the motor, inside which a load torque counts as zero.

    Fig. 8 (and its mirror) decides on the sign of tau_l, and its states do not meet at
    tau_l = 0: with the motor driving, `motor_driving` (Table 1 row 1, eta_m = 0.9) and the
    motor-dominant motor-and-load state (row 3, eta_m = 1, eta_l = 0.45) differ in eq. (10) by
    0.1 tau_m however small tau_l is. An axis without a gravity load (the L-arm turns about the
    vertical) gets tau_l = N^-1 (C qdot + Q) from Pinocchio as a rounding residue of its sums,
    1e-20 to 1e-15 N m of random sign, and its state flipped between the two every few steps
    (24,886 changes in 12 s at 12 V) at a biased speed. Inside the band the load is taken as exactly
    zero, so the state is the one the table gives a zero load, deterministically.

    The residue is a few ulps of the largest torques Pinocchio sums for the joint (the weight and
    inertia of everything it carries), and a drive is sized so that those torques, at the motor
    shaft, are of the order of its torque scale: the stall torque k_t V_max / R. On the default
    robot the L-arm's residue is at most 0.98 eps times it (20,000 random poses). 2**12 eps
    leaves room for structures thousands of times heavier than their motors, and stays 1e5 times
    below the paper's own torque threshold (T_m_eps = 1e-5 N m, Fig. 7) and below the pivot's
    load change in one step as it crosses 55 deg (3e-6 N m in Fig. 9), so physical crossings
    switch on the same step as without a band. docs/model.md, section 4, gives the figures.

    Args:
        torque_scale_nm: the axis's torque scale, N m at the motor (`MotorParams.stall_torque_nm`).

    Returns:
        LOAD_SIGN_BAND_EPS * eps * torque_scale_nm, N m.

    """
    return LOAD_SIGN_BAND_EPS * sys.float_info.epsilon * torque_scale_nm


class Dominance(enum.IntEnum):
    """Which torque is larger in magnitude (the Table 1 split of states 2 and 3)."""

    ANY = 0
    MOTOR = 1  # |tau_m| >= |tau_l|
    LOAD = 2  # |tau_m| < |tau_l|


_MOTOR_WORDS = {
    "any": MotorCondition.ANY,
    "drives": MotorCondition.DRIVES,
    "brakes": MotorCondition.BRAKES,
}
_LOAD_WORDS = {
    "any": LoadCondition.ANY,
    "drives": LoadCondition.DRIVES,
    "resists": LoadCondition.RESISTS,
}
_DOMINANT_WORDS = {"any": Dominance.ANY, "motor": Dominance.MOTOR, "load": Dominance.LOAD}


@dataclass(frozen=True, slots=True)
class DriveStateRule:
    """One row of the moving-state table: a named state and when it holds."""

    name: str
    motor: MotorCondition
    load: LoadCondition
    dominant: Dominance


@dataclass(frozen=True, slots=True)
class Efficiency:
    """The eq. (10) coefficients of one state in one direction (unitless)."""

    eta_m: float
    eta_l: float


@dataclass(frozen=True, slots=True)
class StateMachineParams:
    """Thresholds and the state table of one robot (section 4.1).

    Attributes:
        velocity_eps_rad_s: V_eps, motor side: below it a decelerating axis is taken as stopped.
        motor_torque_eps_nm: T_m_eps (Fig. 7): below it the motor is taken as not pushing.
        irreversible_stop: True for the paper's gear (the load alone never starts motion). False
            gives a reversible chain whose load can break it away like the motor can.
        rules: the moving drive states, first match wins.

    """

    velocity_eps_rad_s: float
    motor_torque_eps_nm: float
    irreversible_stop: bool
    rules: tuple[DriveStateRule, ...]

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of all drive states, indexed by the drive-state number."""
        stop = tuple(s.name.lower() for s in StopState)
        return stop + tuple(r.name for r in self.rules)

    def rule_codes(self) -> npt.NDArray[np.int64]:
        """The rules as an int array [n_rules, 3] (motor, load, dominant) for the kernel."""
        return np.array(
            [[int(r.motor), int(r.load), int(r.dominant)] for r in self.rules], dtype=np.int64
        ).reshape(len(self.rules), 3)


def parse_state_machine(reader: MappingReader) -> StateMachineParams:
    """Parse and check the `state_machine` section of a robot YAML.

    The table must cover every combination of conditions, so that no moving axis is ever left
    without a state.
    """
    velocity_eps = reader.number("velocity_eps_rad_s", min_value=0.0, min_exclusive=True)
    torque_eps = reader.number("motor_torque_eps_nm", min_value=0.0, min_exclusive=True)
    irreversible = reader.boolean("irreversible_stop")
    rules: list[DriveStateRule] = []
    items = reader.sequence("states")
    for index, item in enumerate(items):
        row = MappingReader(item, reader.source, f"{reader.key_path('states')}[{index}]")
        name = row.string("name")
        if name in {r.name for r in rules} or name in {s.name.lower() for s in StopState}:
            raise ConfigError(
                row.source, row.key_path("name"), f"state name {name!r} is used twice"
            )
        rules.append(
            DriveStateRule(
                name=name,
                motor=_MOTOR_WORDS[row.string("motor", choices=tuple(_MOTOR_WORDS))],
                load=_LOAD_WORDS[row.string("load", choices=tuple(_LOAD_WORDS))],
                dominant=_DOMINANT_WORDS[row.string("dominant", choices=tuple(_DOMINANT_WORDS))],
            )
        )
        row.finish()
    if not rules:
        raise ConfigError(reader.source, reader.key_path("states"), "expected at least one state")
    for motor in (MotorCondition.DRIVES, MotorCondition.BRAKES):
        for load in (LoadCondition.DRIVES, LoadCondition.RESISTS):
            for dominant in (Dominance.MOTOR, Dominance.LOAD):
                if match_rule(rules, motor, load, dominant) is None:
                    raise ConfigError(
                        reader.source,
                        reader.key_path("states"),
                        "the states do not cover motor "
                        f"{motor.name.lower()}, load {load.name.lower()}, "
                        f"dominant {dominant.name.lower()}",
                    )
    reader.finish()
    return StateMachineParams(velocity_eps, torque_eps, irreversible, tuple(rules))


def match_rule(
    rules: list[DriveStateRule] | tuple[DriveStateRule, ...],
    motor: MotorCondition,
    load: LoadCondition,
    dominant: Dominance,
) -> DriveStateRule | None:
    """The first rule that holds for one combination of conditions, or None."""
    for rule in rules:
        if (
            rule.motor in (MotorCondition.ANY, motor)
            and rule.load in (LoadCondition.ANY, load)
            and rule.dominant in (Dominance.ANY, dominant)
        ):
            return rule
    return None


def parse_efficiency(
    reader: MappingReader, machine: StateMachineParams
) -> dict[tuple[MotionState, str], Efficiency]:
    """Parse a per-state, per-direction efficiency table (Table 1 form).

    Every state needs `eta_m` and `eta_l` for `direct` and `reverse`. Power-flow consistency
    (eq. 11) is enforced: a coefficient may be below 1 only on a torque whose element emits
    power in that state, otherwise the "losses" would create energy.
    """
    table: dict[tuple[MotionState, str], Efficiency] = {}
    for rule in machine.rules:
        state_reader = reader.sub(rule.name)
        for direction in (MotionState.DIRECT, MotionState.REVERSE):
            dir_reader = state_reader.sub(direction.name.lower())
            eta_m = dir_reader.number("eta_m", min_value=0.0, min_exclusive=True, max_value=1.0)
            eta_l = dir_reader.number("eta_l", min_value=0.0, max_value=1.0)
            if eta_m < 1.0 and rule.motor != MotorCondition.DRIVES:
                raise ConfigError(
                    dir_reader.source,
                    dir_reader.key_path("eta_m"),
                    "expected 1.0: eta_m < 1 is only allowed in states where the motor drives "
                    "(it emits the power the efficiency reduces, eq. 11)",
                )
            if eta_l < 1.0 and rule.load != LoadCondition.DRIVES:
                raise ConfigError(
                    dir_reader.source,
                    dir_reader.key_path("eta_l"),
                    "expected 1.0: eta_l < 1 is only allowed in states where the load drives "
                    "(it emits the power the efficiency reduces, eq. 11)",
                )
            dir_reader.finish()
            table[(direction, rule.name)] = Efficiency(eta_m, eta_l)
        state_reader.finish()
    reader.finish()
    return table
