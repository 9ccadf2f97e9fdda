"""Typed, frozen robot parameters, validated once where they enter (the robot YAML).

All quantities are SI. Drive-chain quantities are motor side, as in the paper's eq. (3)-(10):
torques in N m at the motor shaft, velocities in rad/s of the motor. For the prismatic lift the
gear ratio is in motor rad per metre of travel, so the same equations hold.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from lca_sim.errors import ConfigError
from lca_sim.model.schema import MappingReader, check_number
from lca_sim.model.state_machine import (
    Efficiency,
    MotionState,
    StateMachineParams,
    parse_efficiency,
    parse_state_machine,
)

AXIS_NAMES: tuple[str, ...] = ("l_arm", "pivot", "c_arc", "lift")


@dataclass(frozen=True, slots=True)
class MotorParams:
    """A permanent-magnet DC motor and its voltage amplifier.

    L di/dt = v - R i - k_t w_m and tau_m = k_t i: in SI the back-EMF constant (V s/rad) equals
    the torque constant (N m/A), which is what makes the electromechanical energy balance close.
    """

    resistance_ohm: float
    inductance_h: float
    torque_constant_nm_per_a: float
    rotor_inertia_kg_m2: float
    voltage_limit_v: float

    @property
    def stall_torque_nm(self) -> float:
        """k_t V_max / R, N m: the largest torque the amplifier can make the motor produce.

        The torque scale of the axis; the state machine's load-sign band is a few thousand
        rounding units of it (`state_machine.load_torque_band_nm`).
        """
        return self.torque_constant_nm_per_a * self.voltage_limit_v / self.resistance_ohm


@dataclass(frozen=True, slots=True)
class FrictionParams:
    """Velocity friction of one drive chain, motor side (eq. 3 and 4).

    The reverse values are magnitudes: the paper's Gamma_sr = -static_reverse_nm and the reverse
    Coulomb term is -coulomb_reverse_nm.
    """

    static_direct_nm: float
    static_reverse_nm: float
    coulomb_direct_nm: float
    coulomb_reverse_nm: float
    viscous_direct_nm_s_per_rad: float
    viscous_reverse_nm_s_per_rad: float


@dataclass(frozen=True, slots=True)
class AxisParams:
    """One drive chain: motor, gear, friction and the efficiency of every drive state."""

    name: str
    gear_ratio: float
    motor: MotorParams
    friction: FrictionParams
    efficiency: Mapping[tuple[MotionState, str], Efficiency]


@dataclass(frozen=True, slots=True)
class RobotParams:
    """A whole robot: the gantry URDF, the state machine and the four drive chains."""

    name: str
    source: str
    urdf_xml: str
    gravity_m_s2: tuple[float, float, float]
    state_machine: StateMachineParams
    axes: tuple[AxisParams, ...]

    @property
    def axis_names(self) -> tuple[str, ...]:
        """Axis names in model order."""
        return tuple(axis.name for axis in self.axes)


def parse_robot(data: object, source: str, urdf_xml: str) -> RobotParams:
    """Build `RobotParams` from a parsed robot YAML document.

    Args:
        data: the YAML document (after any `base:` merge), as plain Python data.
        source: the file name, for error messages.
        urdf_xml: the gantry URDF text the document refers to.

    Raises:
        ConfigError: on the first invalid, missing or unknown key.

    """
    top = MappingReader(data, source)
    robot = top.sub("robot")
    name = robot.string("name")
    robot.string("urdf")  # resolved by the loader; read here so it counts as a known key
    gravity_raw = robot.sequence("gravity_m_s2")
    if len(gravity_raw) != 3:
        raise ConfigError(source, robot.key_path("gravity_m_s2"), "expected a list of 3 numbers")
    gravity = tuple(
        check_number(g, source, f"{robot.key_path('gravity_m_s2')}[{i}]")
        for i, g in enumerate(gravity_raw)
    )
    robot.finish()

    machine = parse_state_machine(top.sub("state_machine"))
    default_efficiency = top.sub("efficiency")
    default_table = parse_efficiency(default_efficiency, machine)

    axes_raw = top.sequence("axes")
    axes = []
    for index, item in enumerate(axes_raw):
        axes.append(
            _parse_axis(MappingReader(item, source, f"axes[{index}]"), machine, default_table)
        )
    names = tuple(a.name for a in axes)
    if names != AXIS_NAMES:
        raise ConfigError(
            source, "axes", f"expected the axes {list(AXIS_NAMES)} in that order, got {list(names)}"
        )
    top.finish()
    return RobotParams(
        name=name,
        source=source,
        urdf_xml=urdf_xml,
        gravity_m_s2=(gravity[0], gravity[1], gravity[2]),
        state_machine=machine,
        axes=tuple(axes),
    )


def _parse_axis(
    reader: MappingReader,
    machine: StateMachineParams,
    default_table: Mapping[tuple[MotionState, str], Efficiency],
) -> AxisParams:
    name = reader.string("name")
    gear_ratio = reader.number("gear_ratio", min_value=0.0, min_exclusive=True)

    m = reader.sub("motor")
    motor = MotorParams(
        resistance_ohm=m.number("resistance_ohm", min_value=0.0, min_exclusive=True),
        inductance_h=m.number("inductance_h", min_value=0.0, min_exclusive=True),
        torque_constant_nm_per_a=m.number(
            "torque_constant_nm_per_a", min_value=0.0, min_exclusive=True
        ),
        rotor_inertia_kg_m2=m.number("rotor_inertia_kg_m2", min_value=0.0, min_exclusive=True),
        voltage_limit_v=m.number("voltage_limit_v", min_value=0.0, min_exclusive=True),
    )
    m.finish()

    f = reader.sub("friction")
    friction = FrictionParams(
        static_direct_nm=f.number("static_direct_nm", min_value=0.0),
        static_reverse_nm=f.number("static_reverse_nm", min_value=0.0),
        coulomb_direct_nm=f.number("coulomb_direct_nm", min_value=0.0),
        coulomb_reverse_nm=f.number("coulomb_reverse_nm", min_value=0.0),
        viscous_direct_nm_s_per_rad=f.number("viscous_direct_nm_s_per_rad", min_value=0.0),
        viscous_reverse_nm_s_per_rad=f.number("viscous_reverse_nm_s_per_rad", min_value=0.0),
    )
    # Breakaway below the sliding friction would let an axis start and stop on alternate steps.
    if friction.static_direct_nm < friction.coulomb_direct_nm:
        raise ConfigError(
            f.source,
            f.key_path("static_direct_nm"),
            "expected >= coulomb_direct_nm (eq. 3 vs eq. 4)",
        )
    if friction.static_reverse_nm < friction.coulomb_reverse_nm:
        raise ConfigError(
            f.source,
            f.key_path("static_reverse_nm"),
            "expected >= coulomb_reverse_nm (eq. 3 vs eq. 4)",
        )
    f.finish()

    table = default_table
    if reader.has("efficiency"):
        table = parse_efficiency(reader.sub("efficiency"), machine)
    reader.finish()
    return AxisParams(name, gear_ratio, motor, friction, table)
