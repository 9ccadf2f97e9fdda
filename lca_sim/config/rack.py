"""The virtual drive rack's config (config/can/rack.yaml) and fault schedules, read and validated.

`load_rack_config` reads a rack file into a frozen `RackConfig`; `load_faults` swaps in the
`faults:` schedule of another file (`lca-virtual-drive --faults`). Every key is in docs/can.md,
"The virtual drive rack" and "Fault injection".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from lca_control.cascade import PAPER_VELOCITY_KP_A_PER_RAD_S, PAPER_VELOCITY_TI_S
from lca_control.drive_loops import DEFAULT_POSITION_KP_PER_S, DEFAULT_VELOCITY_LIMIT
from lca_sim.cia402 import objects as od
from lca_sim.config.paths import config_dir
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import ConfigError
from lca_sim.model.params import AXIS_NAMES
from lca_sim.model.schema import MappingReader

REALTIME, LOCKSTEP = "realtime", "lockstep"
TIMING_MODES = (REALTIME, LOCKSTEP)
# The simulator node's default (config/ros/simulator.yaml): the two plants hold eq. (2)'s terms
# alike, and the rack's cycle pays one compiled call per millisecond instead of one per step.
DEFAULT_RIGID_BODY_PERIOD_S = 1e-3
# The most of one stall of this process the watchdogs discount (rack.yaml
# max_stall_discount_s): above the 0.3 s stalls a shared CI machine showed, and short enough
# that a master silent for longer than it plus a deadline is still caught.
DEFAULT_MAX_STALL_DISCOUNT_S = 0.5


def eds_path() -> Path:
    """The shipped electronic data sheet of the drive (config/can/lca_drive.eds)."""
    return config_dir() / "can" / "lca_drive.eds"


def default_rack_path() -> Path:
    """The shipped rack config (config/can/rack.yaml)."""
    return config_dir() / "can" / "rack.yaml"


@dataclass(frozen=True, slots=True)
class AxisConfig:
    """One drive of the rack.

    Attributes:
        name: the robot axis it drives.
        node_id: its CANopen node id, 1-127.
        rated_current_a: motor rated current (0x6075, in mA on the bus).
        max_torque_permille: 0x6072 after boot, and the most a master may write there.
        initial_position: the axis's position when the rack is built, rad (m for the lift).
    """

    name: str
    node_id: int
    rated_current_a: float
    max_torque_permille: int
    initial_position: float


# Fault kinds of the `faults:` schedule and of `VirtualDriveRack.set_fault`, each the sub-index
# of the fault injection object 0x2030 it writes (docs/can.md, "Fault injection").
FAULT_KINDS: dict[str, int] = {
    "lost_tpdo": od.FAULT_LOST_TPDOS,
    "heartbeat_off": od.FAULT_HEARTBEAT_OFF,
    "emcy": od.FAULT_RAISE_EMCY,
    "drive_fault": od.FAULT_DRIVE_FAULT,
    "bus_off": od.FAULT_BUS_OFF,
}
# The value each kind may take while on (0 is "off" for every kind).
FAULT_VALUE_RANGE: dict[str, tuple[int, int]] = {
    "lost_tpdo": (1, 0xFF),  # the TPDO bit mask
    "heartbeat_off": (1, 1),
    "emcy": (1, 0xFFFF),  # the EMCY code
    "drive_fault": (1, 0xFFFF),  # the error code (0x603F)
    "bus_off": (1, 1),  # on; the schedule's end_s (or `set_fault(..., 0)`) ends it
}
_FAULT_DEFAULT_VALUE = {"lost_tpdo": 0x0F, "heartbeat_off": 1, "bus_off": 1}


@dataclass(frozen=True, slots=True)
class FaultEntry:
    """One scheduled fault (rack.yaml `faults:`), timed by the rack's plant time.

    Attributes:
        joint: the axis whose drive has it.
        kind: one of `FAULT_KINDS`.
        value: the TPDO mask (lost_tpdo), the code (emcy, drive_fault), 1 (the others).
        start_s: it goes on at the first SYNC at which the plant's time is >= this.
        end_s: it goes off likewise; None: it stays on.
    """

    joint: str
    kind: str
    value: int
    start_s: float
    end_s: float | None = None


@dataclass(frozen=True, slots=True)
class RackConfig:
    """A validated rack config (config/can/rack.yaml).

    Attributes:
        robot: robot config, a shipped name or a path.
        dt_s: plant integration step.
        rigid_body_period_s: eq. (2)'s A(q) and C qdot + Q evaluated this often and held between
            (a whole multiple of dt_s; the simulator node's `rigid_body_period_s` too).
        current_kp_v_per_a, current_ti_s: the in-drive current PI.
        velocity_kp_a_per_rad_s, velocity_ti_s: the in-drive velocity PI (CSV, PV, and under
            the position loop of PP, HM, CSP), on the joint's velocity, the paper's section 6
            gains by default (lca_control's).
        position_kp_per_s: the in-drive position loop's gain (PP, HM, CSP), 1/s.
        velocity_limit: the drive loops' |velocity setpoint| cap, joint rad/s (m/s for the
            lift): `lca_control.drive_loops`, as the simulator node's `drive_velocity_limit`.
        heartbeat_producer_ms: 0x1017 after boot-up.
        encoder_increments_per_rev: 0x608F sub 1, motor side.
        sync_loss_periods: SYNC loss after this many 0x1006 periods without a SYNC.
        max_stall_discount_s: the most of one stall of this process the watchdogs discount.
        eds_path: the EDS the nodes' object dictionaries are read from ("" = the shipped
            config/can/lca_drive.eds); it must declare the objects of `lca_sim.cia402.objects`.
        axes: the drives, in the robot's axis order.
        faults: the fault schedule (none by default: the rack then behaves exactly as without
            fault injection).
        timing_mode: "realtime" (watchdogs, heartbeats and event TPDOs on the wall clock) or
            "lockstep" (the rack's time is its plant's, 0x1006 per SYNC: every watchdog, heartbeat
            and event timer runs on it, so the master is the clock; docs/can.md, "Lockstep").
        source: the file it came from (for messages).
    """

    robot: str
    dt_s: float
    current_kp_v_per_a: float
    current_ti_s: float
    heartbeat_producer_ms: int
    encoder_increments_per_rev: int
    sync_loss_periods: float
    axes: tuple[AxisConfig, ...]
    max_stall_discount_s: float = DEFAULT_MAX_STALL_DISCOUNT_S
    eds_path: str = ""
    velocity_kp_a_per_rad_s: float = PAPER_VELOCITY_KP_A_PER_RAD_S
    velocity_ti_s: float = PAPER_VELOCITY_TI_S
    position_kp_per_s: float = DEFAULT_POSITION_KP_PER_S
    velocity_limit: float = DEFAULT_VELOCITY_LIMIT
    faults: tuple[FaultEntry, ...] = ()
    timing_mode: str = "realtime"
    rigid_body_period_s: float = DEFAULT_RIGID_BODY_PERIOD_S
    source: str = ""

    @property
    def rigid_body_update_steps(self) -> int:
        """Model steps per evaluation of the rigid-body terms."""
        return max(1, round(self.rigid_body_period_s / self.dt_s))

    @property
    def axis_names(self) -> tuple[str, ...]:
        """The axes of the rack, in order."""
        return tuple(a.name for a in self.axes)


def _integer(
    reader: MappingReader, key: str, min_value: int, max_value: int, default: int | None = None
) -> int:
    if default is not None and not reader.has(key):
        return default
    value = reader.raw(key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(
            reader.source, reader.key_path(key), f"expected an integer, got {value!r}"
        )
    if not min_value <= value <= max_value:
        raise ConfigError(
            reader.source,
            reader.key_path(key),
            f"expected an integer in [{min_value}, {max_value}], got {value}",
        )
    return value


def _fault_entry(item: object, source: str, path: str, joints: Sequence[str]) -> FaultEntry:
    """One entry of a `faults:` list; ConfigError names the bad key."""
    reader = MappingReader(item, source, path)
    joint = reader.string("joint", choices=tuple(joints))
    kind = reader.string("kind", choices=tuple(FAULT_KINDS))
    low, high = FAULT_VALUE_RANGE[kind]
    default = _FAULT_DEFAULT_VALUE.get(kind)
    value = _integer(reader, "value", low, high, default)
    start_s = reader.number("start_s", min_value=0.0)
    end_s = None
    if reader.has("end_s"):
        end_s = reader.number("end_s", min_value=start_s, min_exclusive=True)
    reader.finish()
    return FaultEntry(joint, kind, value, start_s, end_s)


def parse_faults(
    data: object, source: str, path: str, joints: Sequence[str]
) -> tuple[FaultEntry, ...]:
    """Validate a `faults:` list (rack.yaml, or the file of `lca-virtual-drive --faults`).

    Args:
        data: the parsed list.
        source: its file, for messages.
        path: the key it sits at ("faults").
        joints: the rack's axes (an entry must name one).

    Raises:
        ConfigError: one line naming the file, the entry's key and what was expected; also
            two entries of one joint and kind whose times overlap.
    """
    if not isinstance(data, list):
        raise ConfigError(source, path, f"expected a list of faults, got {type(data).__name__}")
    entries = [_fault_entry(item, source, f"{path}[{k}]", joints) for k, item in enumerate(data)]
    for k, a in enumerate(entries):
        for b in entries[k + 1 :]:
            if (a.joint, a.kind) != (b.joint, b.kind):
                continue
            a_end = math.inf if a.end_s is None else a.end_s
            b_end = math.inf if b.end_s is None else b.end_s
            if a.start_s < b_end and b.start_s < a_end:
                raise ConfigError(
                    source,
                    f"{path}[{entries.index(b)}]",
                    f"overlaps an earlier {b.kind} fault of {b.joint} ({a.start_s:g}-{a_end:g} s)",
                )
    return tuple(entries)


def _timing(top: MappingReader, dt_s: float, source: str) -> tuple[float, str]:
    """The rack's `rigid_body_period_s` (a whole multiple of dt_s) and `timing_mode`."""
    rigid_body_period_s = top.number(
        "rigid_body_period_s",
        default=DEFAULT_RIGID_BODY_PERIOD_S,
        min_value=0.0,
        max_value=0.01,
        min_exclusive=True,
    )
    steps = rigid_body_period_s / dt_s
    if abs(steps - round(steps)) > 1e-6 * steps or round(steps) < 1:
        raise ConfigError(
            source,
            "rigid_body_period_s",
            f"expected a whole multiple of dt_s = {dt_s:g}, got {rigid_body_period_s:g}",
        )
    timing_mode = top.string("timing_mode") if top.has("timing_mode") else REALTIME
    if timing_mode not in TIMING_MODES:
        raise ConfigError(
            source, "timing_mode", f"expected one of {', '.join(TIMING_MODES)}, got {timing_mode!r}"
        )
    return rigid_body_period_s, timing_mode


def parse_rack_config(data: object, source: str, base_dir: Path | None = None) -> RackConfig:
    """Validate a parsed rack YAML document.

    Args:
        data: the parsed document.
        source: its file name, for messages.
        base_dir: where a relative robot path is resolved (the rack file's folder).

    Raises:
        ConfigError: one line naming the file, the key and what was expected.
    """
    top = MappingReader(data, source)
    robot = top.string("robot")
    if ("/" in robot or robot.endswith((".yaml", ".yml"))) and base_dir is not None:
        robot = str((base_dir / robot).resolve()) if not Path(robot).is_absolute() else robot
    dt_s = top.number("dt_s", min_value=0.0, max_value=0.01, min_exclusive=True)
    rigid_body_period_s, timing_mode = _timing(top, dt_s, source)
    kp = top.number("current_kp_v_per_a", min_value=0.0)
    ti_s = top.number("current_ti_s", min_value=0.0, min_exclusive=True)
    velocity_kp = top.number(
        "velocity_kp_a_per_rad_s", default=PAPER_VELOCITY_KP_A_PER_RAD_S, min_value=0.0
    )
    velocity_ti_s = top.number(
        "velocity_ti_s", default=PAPER_VELOCITY_TI_S, min_value=0.0, min_exclusive=True
    )
    position_kp = top.number(
        "position_kp_per_s", default=DEFAULT_POSITION_KP_PER_S, min_value=0.0, max_value=1000.0
    )
    velocity_limit = top.number(
        "velocity_limit", default=DEFAULT_VELOCITY_LIMIT, min_value=0.0, min_exclusive=True
    )
    heartbeat_ms = _integer(top, "heartbeat_producer_ms", 0, 0xFFFF)
    increments = _integer(top, "encoder_increments_per_rev", 1, 0xFFFFFFFF)
    sync_loss = top.number("sync_loss_periods", default=3.0, min_value=1.0)
    max_stall_discount_s = top.number(
        "max_stall_discount_s", default=DEFAULT_MAX_STALL_DISCOUNT_S, min_value=0.0, max_value=60.0
    )
    eds = top.string("eds_path") if top.has("eds_path") else ""
    if eds:
        eds_file = Path(eds) if Path(eds).is_absolute() or base_dir is None else base_dir / eds
        if not eds_file.is_file():
            raise ConfigError(source, "eds_path", f"expected an EDS file, {eds_file} is none")
        eds = str(eds_file.resolve())
    axes_reader = top.sub("axes")
    axes: list[AxisConfig] = []
    names = axes_reader.key_names()
    if not names:
        raise ConfigError(source, "axes", "expected at least one axis")
    for name in names:
        if name not in AXIS_NAMES:
            raise ConfigError(
                source, f"axes.{name}", f"unknown axis (valid: {', '.join(AXIS_NAMES)})"
            )
        axis = axes_reader.sub(name)
        axes.append(
            AxisConfig(
                name=name,
                node_id=_integer(axis, "node_id", 1, 127),
                rated_current_a=axis.number(
                    "rated_current_a", min_value=0.0, max_value=1e6, min_exclusive=True
                ),
                max_torque_permille=_integer(axis, "max_torque_permille", 1, 0x7FFF),
                initial_position=axis.number("initial_position"),
            )
        )
        axis.finish()
    axes_reader.finish()
    faults: tuple[FaultEntry, ...] = ()
    if top.has("faults"):
        faults = parse_faults(top.raw("faults"), source, "faults", [a.name for a in axes])
    top.finish()
    ids = [a.node_id for a in axes]
    duplicate = next((i for i in ids if ids.count(i) > 1), None)
    if duplicate is not None:
        raise ConfigError(source, "axes", f"expected distinct node ids, {duplicate} is repeated")
    order = sorted(axes, key=lambda a: AXIS_NAMES.index(a.name))
    return RackConfig(
        robot=robot,
        dt_s=dt_s,
        current_kp_v_per_a=kp,
        current_ti_s=ti_s,
        heartbeat_producer_ms=heartbeat_ms,
        encoder_increments_per_rev=increments,
        sync_loss_periods=sync_loss,
        axes=tuple(order),
        max_stall_discount_s=max_stall_discount_s,
        eds_path=eds,
        velocity_kp_a_per_rad_s=velocity_kp,
        velocity_ti_s=velocity_ti_s,
        position_kp_per_s=position_kp,
        velocity_limit=velocity_limit,
        faults=faults,
        timing_mode=timing_mode,
        rigid_body_period_s=rigid_body_period_s,
        source=source,
    )


def load_faults(path: str | Path, config: RackConfig) -> RackConfig:
    """`config` with the schedule of a faults file (a YAML mapping with one key, `faults:`).

    Raises:
        ConfigError: the file, the key and what was expected, in one line.
    """
    file = Path(path)
    if not file.is_file():
        raise ConfigError(str(file), "", "file not found")
    top = MappingReader(read_yaml(file), str(file))
    faults = parse_faults(top.raw("faults"), str(file), "faults", config.axis_names)
    top.finish()
    return replace(config, faults=faults)


def load_rack_config(path: str | Path | None = None) -> RackConfig:
    """Load and validate a rack config; None loads the shipped config/can/rack.yaml.

    Raises:
        ConfigError: the file, the key and what was expected, in one line.
    """
    file = default_rack_path() if path is None else Path(path)
    if not file.is_file():
        raise ConfigError(str(file), "", "file not found")
    return parse_rack_config(read_yaml(file), str(file), file.parent)
