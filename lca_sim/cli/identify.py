"""`lca-hil identify`: the efficiency of every drive state of one axis, from a recorded motion.

    lca-hil identify out/identify/result.csv                  # a result.csv of `lca-sim run`
    lca-hil identify out/run1 --axis pivot --out out/ident    # a bag folder of lca-record

The paper's section 7 procedure (`lca_sim.analysis.identify`). INPUT is a result.csv (columns
t_s, <axis>_position, <axis>_velocity, <axis>_current_a) or a rosbag2 folder (joint_states and
motor_states, aligned on the joint_states stamps). Prints a table of estimates with their
confidence intervals and the states not identified, and writes into --out (default: the CSV's
or the bag's folder) identified.yaml, a robot config `load_robot` and `lca-sim run --robot`
accept (`base:` the robot used, unidentified states keep their prior, marked so), and
identification.json. docs/tools.md ("lca-hil identify") has the procedure and what to record.

Exit codes: 0 success, 2 bad input (one line on stderr), 130 interrupted.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from lca_sim.analysis.identify import identify
from lca_sim.analysis.identify_types import (
    DIRECTIONS,
    EstimateStatus,
    FloatArray,
    IdentificationError,
    IdentificationResult,
    IdentifyOptions,
    MotionRecord,
    StateEstimate,
)
from lca_sim.config.loader import load_robot
from lca_sim.errors import (
    EXIT_OK,
    FILE_NOT_FOUND,
    LcaHilError,
    OutputError,
    UnknownNameError,
    run_guarded,
)
from lca_sim.model.params import AxisParams, RobotParams
from lca_sim.model.state_machine import Efficiency, MotionState
from lca_sim.output import atomic_path

PROG = "lca-hil identify"
YAML_NAME = "identified.yaml"
JSON_NAME = "identification.json"
# Digits written for a coefficient: well below any estimate's uncertainty.
DIGITS = 5


class InputFileError(LcaHilError):
    """The INPUT file or folder cannot be used (missing columns, not a number, no topic...)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `lca-hil identify`."""
    parser.add_argument("input", type=Path, help="result.csv of lca-sim or a bag folder")
    parser.add_argument("--robot", default="default", help="robot YAML path or shipped name")
    parser.add_argument("--axis", default="pivot", help="the axis to identify")
    parser.add_argument(
        "--out", type=Path, default=None, help="output folder (default: next to INPUT)"
    )
    parser.add_argument(
        "--namespace", default="/", help="namespace of the bag's topics (default /)"
    )
    parser.add_argument(
        "--min-samples",
        type=int,
        default=IdentifyOptions().min_samples,
        help="usable samples a state needs to be identified",
    )
    parser.add_argument(
        "--end-stop-margin-deg",
        type=float,
        default=math.degrees(IdentifyOptions().end_stop_margin_rad),
        help="leave out samples this close to a joint limit, deg (lift: the rad value, as m)",
    )


def run(args: argparse.Namespace) -> int:
    """Run `lca-hil identify` on parsed arguments; returns the exit code."""
    return run_guarded(PROG, lambda: _run(args))


def main(argv: Sequence[str] | None = None) -> int:
    """`lca-hil identify ...` on its own (lca-hil's registry, `lca_sim.cli.hil`, holds it too)."""
    parser = argparse.ArgumentParser(prog="lca-hil")
    sub = parser.add_subparsers(dest="command", required=True)
    add_arguments(sub.add_parser("identify"))
    return run(parser.parse_args(argv))


def _options(args: argparse.Namespace) -> IdentifyOptions:
    """The identification options of the command line, checked.

    Raises:
        InputFileError: --min-samples below 1 or a negative --end-stop-margin-deg.
    """
    if args.min_samples < 1:
        raise InputFileError(f"--min-samples: expected >= 1, got {args.min_samples}")
    if not args.end_stop_margin_deg >= 0.0:
        raise InputFileError(
            f"--end-stop-margin-deg: expected >= 0, got {args.end_stop_margin_deg}"
        )
    return IdentifyOptions(
        min_samples=args.min_samples, end_stop_margin_rad=math.radians(args.end_stop_margin_deg)
    )


def _run(args: argparse.Namespace) -> int:
    source: Path = args.input
    is_bag = source.is_dir()
    out: Path = args.out if args.out is not None else (source if is_bag else source.parent)
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out}: expected a folder, but it is a file")
    options = _options(args)
    robot = load_robot(args.robot)
    if args.axis not in robot.axis_names:
        raise UnknownNameError("axis", args.axis, robot.axis_names)

    if is_bag:
        record = read_bag_record(source, robot, args.axis, args.namespace)
    elif source.is_file():
        record = read_csv_record(source, robot, args.axis)
    else:
        raise InputFileError(f"{source}: {FILE_NOT_FOUND} (nor a folder)")
    try:
        result = identify(robot, args.axis, record, options)
    except IdentificationError as exc:
        raise InputFileError(f"{source}: {exc}") from None
    if result.n_moving == 0:
        raise InputFileError(f"{source}: the {args.axis} never moves; nothing to identify")

    print(_summary(result, robot, source))
    try:
        written = write_outputs(result, robot, source, out)
    except OSError as exc:
        raise OutputError(f"--out {out}: cannot write ({exc.strerror or exc})") from None
    for path in written:
        print(f"wrote {path}")
    return EXIT_OK


# --- reading -----------------------------------------------------------------------------------


def read_csv_record(path: Path, robot: RobotParams, axis: str) -> MotionRecord:
    """The motion of a result.csv of `lca-sim run` (all axes' positions and velocities).

    Raises:
        InputFileError: unreadable, not UTF-8, a missing column, a cell that is not a number.
    """
    wanted = ["t_s"]
    for name in robot.axis_names:
        wanted += [f"{name}_position", f"{name}_velocity"]
    wanted.append(f"{axis}_current_a")
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            if header is None:
                raise InputFileError(f"{path}: empty file, expected a result.csv header")
            missing = [c for c in wanted if c not in header]
            if missing:
                raise InputFileError(
                    f"{path}: missing column {missing[0]!r} (expected a result.csv of lca-sim "
                    "run or a bag folder)"
                )
            columns = [header.index(c) for c in wanted]
            rows: list[list[float]] = []
            for line, row in enumerate(reader, start=2):
                if len(row) != len(header):
                    raise InputFileError(
                        f"{path}: line {line}: expected {len(header)} cells, got {len(row)}"
                    )
                rows.append([_cell(path, line, wanted[k], row[c]) for k, c in enumerate(columns)])
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: expected UTF-8 text ({exc.reason})") from None
    except csv.Error as exc:
        raise InputFileError(f"{path}: not a CSV file ({exc})") from None
    if not rows:
        raise InputFileError(f"{path}: no samples after the header")
    table = np.asarray(rows, dtype=np.float64)
    n_axes = len(robot.axis_names)
    position = table[:, 1 : 1 + 2 * n_axes : 2]
    velocity = table[:, 2 : 2 + 2 * n_axes : 2]
    return MotionRecord(table[:, 0], position, velocity, table[:, -1])


def _cell(path: Path, line: int, column: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise InputFileError(
            f"{path}: line {line}, column {column}: expected a number, got {text!r}"
        ) from None


def read_bag_record(path: Path, robot: RobotParams, axis: str, namespace: str) -> MotionRecord:
    """The motion in a rosbag2 folder: joint_states positions/velocities, motor_states current.

    The current (motor_states effort, A) is interpolated onto the joint_states stamps of the
    identified axis; both topics carry the same stamps when they come from the simulator node.
    A joint whose velocity is missing (NaN) gets the derivative of its position instead.

    Raises:
        InputFileError: not a bag, unreadable, or a needed topic or joint is missing.
    """
    if not (path / "metadata.yaml").is_file():
        raise InputFileError(f"{path}: a folder but not a rosbag2 bag (no metadata.yaml)")
    try:
        # rosbags comes with the ROS extra; only the bag path needs it.
        from lca_sim.ros.bag_read import BagReadError, read_bag  # noqa: PLC0415
    except ImportError as exc:
        raise InputFileError(f"{path}: reading a bag needs the rosbags package ({exc})") from None
    try:
        data = read_bag(path, namespace=namespace)
    except BagReadError as exc:
        raise InputFileError(str(exc)) from None
    missing = [name for name in robot.axis_names if name not in data.joints]
    if missing:
        raise InputFileError(
            f"{path}: joint_states has no joint {missing[0]!r} (found: "
            f"{', '.join(data.joints) or 'no joint_states'})"
        )
    if axis not in data.motors:
        raise InputFileError(
            f"{path}: motor_states has no joint {axis!r} (the armature current; found: "
            f"{', '.join(data.motors) or 'no motor_states'})"
        )
    # Each joint's stamps sorted once: (time, position, velocity).
    joints = {
        name: _series(
            data.joints[name].time_s,
            data.joints[name].values["position"],
            data.joints[name].values["velocity"],
        )
        for name in robot.axis_names
    }
    base_t = joints[axis][0]
    motor_t, current = _series(data.motors[axis].time_s, data.motors[axis].values["effort"])
    if len(motor_t) < 2:
        raise InputFileError(f"{path}: fewer than 2 motor_states samples of {axis!r}")
    # Only where both topics have samples: no extrapolated current.
    keep = (base_t >= motor_t[0]) & (base_t <= motor_t[-1])
    time_s = base_t[keep]
    n_axes = len(robot.axis_names)
    position = np.zeros((len(time_s), n_axes))
    velocity = np.zeros((len(time_s), n_axes))
    for b, name in enumerate(robot.axis_names):
        t_b, q_b, v_b = joints[name]
        if not np.all(np.isfinite(v_b)) and len(t_b) > 1:
            # A driver may leave JointState.velocity empty: differentiate the position.
            v_b = np.gradient(q_b, t_b)
        position[:, b] = np.interp(time_s, t_b, q_b)
        velocity[:, b] = np.interp(time_s, t_b, v_b)
    return MotionRecord(time_s, position, velocity, np.interp(time_s, motor_t, current))


def _series(time_s: Sequence[float], *values: Sequence[float]) -> tuple[FloatArray, ...]:
    """Samples sorted by time, one per stamp (the first of a repeated stamp).

    Returns the sorted stamps, then each of `values` (sampled at `time_s`) in the same order.
    """
    t = np.asarray(time_s, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    unique, first = np.unique(t[order], return_index=True)
    pick = order[first]
    return (unique, *(np.asarray(v, dtype=np.float64)[pick] for v in values))


# --- reporting ---------------------------------------------------------------------------------


def _summary(result: IdentificationResult, robot: RobotParams, source: Path) -> str:
    """The printed report: what was read, the table, what was not identified."""
    period_ms = result.sample_period_s * 1e3
    lines = [
        f"{PROG}: axis {result.axis} of {robot.name}, from {source}",
        f"  {result.n_samples} samples every {period_ms:.4g} ms; {result.n_moving} moving, "
        f"{result.n_used} used (stops, state changes and their guard, ambiguous samples out)",
        f"  {result.n_end_stop} samples left out at or near an end stop (within "
        f"{math.degrees(result.options.end_stop_margin_rad):.3g} deg of "
        f"[{result.position_limits[0]:.4g}, {result.position_limits[1]:.4g}], and the guard)",
        f"  current noise {result.current_noise_a:.3g} A; moving above "
        f"{result.moving_threshold_rad_s:.3g} rad/s at the motor",
        "",
        f"{'state':40s} {'direction':9s} {'coef':5s} {'estimate':>9s}  "
        f"{'95 % CI':19s} {'samples':>7s}  prior  judged",
    ]
    for e in result.estimates:
        lines.append(_row(e))
    missing = [e for e in result.not_identified if e.status is not EstimateStatus.FIXED]
    fixed = [e for e in result.not_identified if e.status is EstimateStatus.FIXED]
    lines.append("")
    if missing:
        lines.append("not identified, prior value kept in identified.yaml:")
        lines.extend(
            f"  {e.state} {e.direction.name.lower()}: {_reason(e, result.options)}" for e in missing
        )
    else:
        lines.append("every state with an emitter coefficient was identified")
    if fixed:
        names = ", ".join(f"{e.state} {e.direction.name.lower()}" for e in fixed)
        lines.append(f"fixed at 1 by eq. (11), no emitter but the inertia: {names}")
    return "\n".join(lines)


def _row(e: StateEstimate) -> str:
    coef = e.coefficient or "-"
    prior = _value(e.prior, e.coefficient)
    if e.status in (EstimateStatus.IDENTIFIED, EstimateStatus.NOT_IDENTIFIABLE):
        value = f"{e.estimate:9.4f}"
        interval = f"[{e.ci_low:.4f}, {e.ci_high:.4f}]"
    elif e.status is EstimateStatus.FIXED:
        value = f"{'fixed 1':>9s}"
        interval = f"res. {e.residual_mean_nm:+.1e} N m"
    else:
        value = f"{'-':>9s}"
        interval = e.status.value.replace("_", " ")
    flag = " (clipped)" if e.clipped else ""
    if e.status is EstimateStatus.NOT_IDENTIFIABLE:
        flag += " NOT IDENTIFIABLE"
    return (
        f"{e.state:40s} {e.direction.name.lower():9s} {coef:5s} {value}  {interval:19s} "
        f"{e.n_samples:7d}  {prior:g}  {_judged(e)}{flag}"
    )


def _judged(e: StateEstimate) -> str:
    """The criterion the interval was judged by: `relative: width <= 0.18`, or `-`."""
    if e.criterion is None:
        return "-"
    return f"{e.criterion.value}: width <= {e.ci_width_bound:.3g}"


def _reason(e: StateEstimate, options: IdentifyOptions) -> str:
    """Why a state kept its prior: `e.status` keeps the prior and is not FIXED."""
    if e.status is EstimateStatus.NOT_VISITED:
        return "not visited"
    if e.status is EstimateStatus.TOO_FEW_SAMPLES:
        return f"{e.n_samples} usable samples, fewer than {options.min_samples}"
    if e.status is EstimateStatus.NOT_IDENTIFIABLE:
        assert e.criterion is not None
        return (
            f"not identifiable: {options.confidence * 100:g} % CI [{e.ci_low:.4g}, "
            f"{e.ci_high:.4g}] is {e.ci_width:.3g} wide, wider than {e.ci_width_bound:.3g} "
            f"({e.criterion.value} criterion)"
        )
    assert e.status is EstimateStatus.WEAK_EXCITATION, e.status  # the last one keeping the prior
    return f"the {e.coefficient} torque ({e.regressor_rms_nm:.2g} N m rms) is within the noise"


def _value(efficiency: Efficiency, coefficient: str | None) -> float:
    """The coefficient's prior; eta_m (1 by eq. 11, the config loader checks it) for None."""
    return efficiency.eta_l if coefficient == "eta_l" else efficiency.eta_m


# --- writing -----------------------------------------------------------------------------------


def write_outputs(
    result: IdentificationResult, robot: RobotParams, source: Path, out: Path
) -> list[Path]:
    """Write identified.yaml and identification.json into `out`; the paths written.

    identified.yaml is checked by loading it: if the base robot gives the identified axis an
    `efficiency:` of its own (which a top-level table cannot override), the file lists the axes
    in full instead, every axis with its table.
    """
    yaml_path = out / YAML_NAME
    table = result.efficiency_table()
    for per_axis in (False, True):
        text = identified_yaml(result, robot, source, per_axis=per_axis)
        with atomic_path(yaml_path) as tmp:
            tmp.write_text(text, encoding="utf-8")
        reloaded = load_robot(str(yaml_path))
        axis = reloaded.axes[reloaded.axis_names.index(result.axis)]
        if _same_table(axis.efficiency, table):
            break
    else:  # pragma: no cover - the per-axis file always carries the table
        raise OutputError(f"{yaml_path}: the written table does not load back")
    json_path = out / JSON_NAME
    with atomic_path(json_path) as tmp:
        tmp.write_text(identification_json(result, robot, source), encoding="utf-8")
    return [yaml_path, json_path]


def _same_table(
    loaded: Mapping[tuple[MotionState, str], Efficiency],
    wanted: Mapping[tuple[MotionState, str], Efficiency],
) -> bool:
    """True when two efficiency tables agree to the digits written."""
    tolerance = 10.0**-DIGITS
    return loaded.keys() == wanted.keys() and all(
        abs(loaded[k].eta_m - wanted[k].eta_m) <= tolerance
        and abs(loaded[k].eta_l - wanted[k].eta_l) <= tolerance
        for k in wanted
    )


def identified_yaml(
    result: IdentificationResult, robot: RobotParams, source: Path, *, per_axis: bool = False
) -> str:
    """The identified robot config as YAML text, with a comment on every coefficient.

    Args:
        result: the identification.
        robot: the robot it started from (prior values); its file (`robot.source`) is written
            as `base:`, absolute.
        source: the input, for the header comment.
        per_axis: also write the `axes:` list in full, the identified axis with the new table
            (needed when the base gives that axis a table of its own).
    """
    lines = [
        f"# Written by `{PROG}` from {source} (axis {result.axis}).",
        "# Each coefficient sits on the torque of the element that emits power (eq. 11,",
        "# docs/model.md). A state that was not identified keeps the prior value of the base.",
        "# The top-level table is the default of every axis without an efficiency of its own.",
        f"base: {json.dumps(str(_robot_file(robot)))}",
        "robot:",
        f"  name: {json.dumps(robot.name + '_identified')}",
        "efficiency:",
    ]
    lines += _efficiency_lines(result, "  ")
    if per_axis:
        lines.append("axes:")
        for axis in robot.axes:
            lines += _axis_lines(axis, result)
    return "\n".join(lines) + "\n"


def _efficiency_lines(result: IdentificationResult, indent: str) -> list[str]:
    lines = []
    for name in result.state_names:
        lines.append(f"{indent}{name}:")
        for direction in DIRECTIONS:
            e = result.estimate(name, direction)
            key = f"{direction.name.lower()}:"
            entry = _entry(e.identified)
            lines.append(f"{indent}  {key:8s} {entry:32s} # {_comment(e, result.options)}")
    return lines


def _entry(efficiency: Efficiency) -> str:
    """One (state, direction) entry of an efficiency table, as a YAML flow mapping."""
    return f"{{eta_m: {_num(efficiency.eta_m)}, eta_l: {_num(efficiency.eta_l)}}}"


def _comment(e: StateEstimate, options: IdentifyOptions) -> str:
    level = f"{options.confidence * 100:g} %"
    if e.status is EstimateStatus.IDENTIFIED:
        clipped = f" (estimate {e.estimate:.5f}, clipped)" if e.clipped else ""
        return (
            f"{e.coefficient} identified{clipped}: {level} CI [{e.ci_low:.5f}, {e.ci_high:.5f}], "
            f"{e.n_samples} samples"
        )
    if e.status is EstimateStatus.FIXED:
        return f"fixed by eq. (11) (no emitter), {e.n_samples} samples"
    return f"prior kept: {_reason(e, options)}"


def _axis_lines(axis: AxisParams, result: IdentificationResult) -> list[str]:
    """One entry of the `axes:` list: the identified table for the identified axis, else its own."""
    m, f = axis.motor, axis.friction
    lines = [
        f"  - name: {json.dumps(axis.name)}",
        f"    gear_ratio: {_num(axis.gear_ratio)}",
        "    motor:",
        f"      resistance_ohm: {_num(m.resistance_ohm)}",
        f"      inductance_h: {_num(m.inductance_h)}",
        f"      torque_constant_nm_per_a: {_num(m.torque_constant_nm_per_a)}",
        f"      rotor_inertia_kg_m2: {_num(m.rotor_inertia_kg_m2)}",
        f"      voltage_limit_v: {_num(m.voltage_limit_v)}",
        "    friction:",
        f"      static_direct_nm: {_num(f.static_direct_nm)}",
        f"      static_reverse_nm: {_num(f.static_reverse_nm)}",
        f"      coulomb_direct_nm: {_num(f.coulomb_direct_nm)}",
        f"      coulomb_reverse_nm: {_num(f.coulomb_reverse_nm)}",
        f"      viscous_direct_nm_s_per_rad: {_num(f.viscous_direct_nm_s_per_rad)}",
        f"      viscous_reverse_nm_s_per_rad: {_num(f.viscous_reverse_nm_s_per_rad)}",
        "    efficiency:",
    ]
    if axis.name == result.axis:
        return lines + _efficiency_lines(result, "      ")
    for state in result.state_names:
        lines.append(f"      {state}:")
        for direction in DIRECTIONS:
            lines.append(
                f"        {direction.name.lower()}: {_entry(axis.efficiency[(direction, state)])}"
            )
    return lines


def _robot_file(robot: RobotParams) -> Path:
    """The robot's YAML file (the path `load_robot` resolved), absolute."""
    return Path(robot.source).resolve()


def _num(value: float) -> str:
    """A float YAML reads back as a float (1.0, not 1), rounded to DIGITS decimals."""
    return repr(float(round(value, DIGITS))) if abs(value) >= 1e-3 else repr(float(value))


def identification_json(result: IdentificationResult, robot: RobotParams, source: Path) -> str:
    """The identification as a JSON document (NaN written as null)."""
    doc = {
        "input": str(source),
        "robot": robot.name,
        "robot_file": str(_robot_file(robot)),
        "axis": result.axis,
        "sample_period_s": result.sample_period_s,
        "n_samples": result.n_samples,
        "n_moving": result.n_moving,
        "n_used": result.n_used,
        "current_noise_a": result.current_noise_a,
        "velocity_noise_rad_s": result.velocity_noise_rad_s,
        "moving_threshold_rad_s": result.moving_threshold_rad_s,
        "n_end_stop": result.n_end_stop,
        "position_limits": list(result.position_limits),
        "options": dataclasses.asdict(result.options),
        "estimates": [
            {
                "state": e.state,
                "direction": e.direction.name.lower(),
                "coefficient": e.coefficient,
                "status": e.status.value,
                "estimate": _finite(e.estimate),
                "ci_low": _finite(e.ci_low),
                "ci_high": _finite(e.ci_high),
                "n_samples": e.n_samples,
                "n_effective": _finite(e.n_effective),
                "bootstrap_block_samples": e.block_length,
                "prior": {"eta_m": e.prior.eta_m, "eta_l": e.prior.eta_l},
                "identified": {"eta_m": e.identified.eta_m, "eta_l": e.identified.eta_l},
                "prior_kept": e.status.keeps_prior,
                "clipped": e.clipped,
                "residual_mean_nm": _finite(e.residual_mean_nm),
                "residual_rms_nm": _finite(e.residual_rms_nm),
                "regressor_rms_nm": _finite(e.regressor_rms_nm),
                "criterion": e.criterion.value if e.criterion is not None else None,
                "ci_width": _finite(e.ci_width),
                "ci_width_bound": _finite(e.ci_width_bound),
                "reason": _json_reason(e, result.options),
            }
            for e in result.estimates
        ],
        "not_identified": [
            {
                "state": e.state,
                "direction": e.direction.name.lower(),
                "status": e.status.value,
                "reason": _json_reason(e, result.options),
            }
            for e in result.not_identified
        ],
    }
    return json.dumps(doc, indent=2, allow_nan=False) + "\n"


def _json_reason(e: StateEstimate, options: IdentifyOptions) -> str | None:
    """Why the prior was kept (and why a value may be null); None when identified."""
    if e.status is EstimateStatus.IDENTIFIED:
        return None
    if e.status is EstimateStatus.FIXED:
        return "fixed at 1 by eq. (11): no emitter coefficient"
    return _reason(e, options)


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


if __name__ == "__main__":
    raise SystemExit(main())
