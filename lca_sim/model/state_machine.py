"""The two-level efficiency state machine of the paper (section 4.1, Figs 6-8, Table 1).

Upper level (Fig. 6): the motion state STOP, DIRECT or REVERSE, from the sign of the motor
velocity with the stop threshold V_eps. Lower level: the drive state. In STOP (Fig. 7) the gear
is irreversible and the sub-states only say what the motor does while the axis is held
(`stop_hold`, `stop_motor_direct` / `stop_motor_reverse`, `stop_end_stop`). In motion (Fig. 8
and its mirror) a table of rules from the robot YAML, written along the motion direction,
picks the state from the signs of tau_m and tau_l (the load's read through
`load_torque_band_nm`); each state carries eta_m and eta_l per direction (eq. 10).
The table, the sign conventions and the power-flow rule (eq. 11): docs/model.md, section 4.
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

    Fig. 8's states do not meet at tau_l = 0, and an axis without a gravity load (the L-arm)
    gets a rounding residue of random sign from Pinocchio, which flipped its state every few
    steps. The residue is a few ulps of the torques the joint carries, of the order of the
    drive's stall torque; 2**12 eps of it stays far below the paper's T_m_eps and any physical
    crossing. The figures: docs/model.md, section 4, "A zero load: the sign band".

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
