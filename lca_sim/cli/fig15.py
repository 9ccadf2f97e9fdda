"""`lca-hil fig15`: the closed-loop HIL run of the paper's Fig. 15 over ROS 2.

    lca-hil fig15 --out out/fig15

Starts the simulator (lockstep, current loop in the drive), the controller (the section 6
velocity PI replaying the Fig. 15 ramp) and the recorder as separate ROS 2 processes, shows the
simulated time while they run, and writes the bag, its plots and a summary: where the pivot
left motor driving (the paper has 55 deg), the velocity tracking error and the closed-loop
steps per second.

The end of the run is the simulator's: it is started with `lockstep_end_s` = the duration, so
its last state is stamped exactly the duration however slowly the machine runs, and it then
reports `ended` in its /diagnostics status (see `lca_sim.ros.simulator_node`). This process
waits for that report (its own /clock samples only drive the progress line and the rate), with
a deadline of `END_WAIT_S + END_WAIT_PER_SIM_S * duration` of wall time, and fails with the
node's name and log when a node exits before it. It then stops the recorder first, while the
simulator still runs, so the recorder takes every state the middleware holds, then the
controller and the simulator. summary.json is strict JSON: a figure the run could not give
(no transition within a short run) is null, and its "reasons" object says why.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from lca_control import contract as ri
from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.profiles import RampProfile
from lca_sim.cli.bagplot import BagReadError, JointSeries, read_bag
from lca_sim.cli.output import write_json
from lca_sim.config.loader import config_dir
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_FAILED
from lca_sim.ros.node_util import from_stamp
from lca_sim.ros.simulator_params import ENDED_KEY, SIMULATOR_STATUS

PIVOT_START_DEG = 35.0
END_WAIT_S = 60.0  # wall time for start-up and shut-down, on top of ...
END_WAIT_PER_SIM_S = 20.0  # ... this much wall time per simulated second (a loaded machine)
TRACKING_WINDOW_S = (2.0, 10.9)  # the ramp's steady part, where the tracking error is taken


def _script(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", "57")
    return env


def _start(argv: list[str], log: Path) -> subprocess.Popen[bytes]:
    handle = log.open("wb")
    return subprocess.Popen(argv, env=_env(), stdout=handle, stderr=subprocess.STDOUT)


class _Progress:
    """What this process sees of the loop: /clock for the progress line, the simulator's end."""

    def __init__(self) -> None:
        self.t_s = 0.0
        self.first_t_s = math.nan
        self.first_wall_s = math.nan
        self.last_wall_s = math.nan
        self.ended = False
        self.end_message = ""

    def on_clock(self, msg: Clock) -> None:
        now = time.monotonic()
        self.t_s = from_stamp(msg.clock)
        if math.isnan(self.first_wall_s):
            self.first_wall_s, self.first_t_s = now, self.t_s
        self.last_wall_s = now

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name != SIMULATOR_STATUS:
                continue
            values = {kv.key: kv.value for kv in status.values}
            if values.get(ENDED_KEY) == "True":
                self.ended, self.end_message = True, status.message

    def steps_per_s(self) -> float:
        """Closed-loop steps per wall second over the span this node saw (NaN: too short).

        It may match /clock after the loop has started (the simulator waits for the
        controller and the recorder, not for it), so the rate is of what it saw.
        """
        seen_wall_s = self.last_wall_s - self.first_wall_s
        if not seen_wall_s > 0.0:
            return math.nan
        return (self.t_s - self.first_t_s) / CONTROL_PERIOD_S / seen_wall_s


def _argvs(bag: Path, duration_s: float) -> dict[str, list[str]]:
    """The three processes' command lines, in the order they start."""
    params = config_dir() / "ros"
    start_rad = math.radians(PIVOT_START_DEG)
    return {
        "recorder": [
            _script("lca-record"), "-o", str(bag), "--wait-s", "30",
            ri.JOINT_STATES, ri.MOTOR_STATES, ri.DRIVE_CHAIN_STATES, ri.VOLTAGE_COMMANDS,
            ri.CURRENT_COMMANDS, ri.CLOCK, "--ros-args", "-p", "use_sim_time:=true",
        ],
        # No use_sim_time for the controller: it steps on the state stamps, and a /clock
        # subscription would cost it one more message per step.
        "controller": [
            _script("lca-controller"), "--ros-args",
            "--params-file", str(params / "controller.yaml"),
        ],
        "simulator": [
            _script("lca-simulator"), "--ros-args",
            "--params-file", str(params / "simulator.yaml"),
            "-p", "timing_mode:=lockstep", "-p", "command_interface:=current",
            "-p", f"control_period_s:={CONTROL_PERIOD_S!r}",
            "-p", f"initial_position:=[0.0,{start_rad!r},0.0,0.0]",
            "-p", "lockstep_subscribers:=2",
            "-p", f"lockstep_end_s:={float(duration_s)!r}",
        ],
    }  # fmt: skip


def _wait_for_end(
    executor: SingleThreadedExecutor,
    progress: _Progress,
    procs: Mapping[str, subprocess.Popen[bytes]],
    out: Path,
    duration_s: float,
) -> int:
    """Spin until the simulator reports the end of the run; 0, or EXIT_FAILED and why."""
    deadline = time.monotonic() + END_WAIT_S + END_WAIT_PER_SIM_S * duration_s
    shown = -1
    while not progress.ended:
        executor.spin_once(timeout_sec=0.1)
        for name, proc in procs.items():
            if proc.poll() is not None and not progress.ended:
                print(
                    f"\nlca-hil: error: the {name} exited (code {proc.returncode}) before the "
                    f"simulator ended the run; see {out / (name + '.log')}",
                    file=sys.stderr,
                )
                return EXIT_FAILED
        if time.monotonic() > deadline:
            print(
                f"\nlca-hil: error: the simulator did not end the run within "
                f"{END_WAIT_S + END_WAIT_PER_SIM_S * duration_s:g} s of wall time "
                f"(simulated {progress.t_s:.3f} of {duration_s:g} s); logs in {out}",
                file=sys.stderr,
            )
            return EXIT_FAILED
        if int(progress.t_s) != shown:
            shown = int(progress.t_s)
            print(f"\r  simulated {progress.t_s:6.2f} / {duration_s:g} s", end="", flush=True)
    print(f"\r  simulated {duration_s:6.2f} / {duration_s:g} s: simulator {progress.end_message}")
    return 0


def _stop(procs: Sequence[subprocess.Popen[bytes]]) -> None:
    """SIGINT each process in turn and wait for it (killed after 15 s)."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_fig15(out: Path, duration_s: float) -> int:
    """Run the Fig. 15 loop for `duration_s` of simulated time; return the exit code."""
    if not (math.isfinite(duration_s) and duration_s > 0.0):
        print(f"lca-hil: error: --duration-s must be > 0, not {duration_s:g}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "bag"
    if bag.exists():
        print(f"lca-hil: error: {bag} exists; choose another --out", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"lca-hil: Fig. 15 in lockstep, {duration_s:g} s of simulated time; logs in {out}")
    # This node first: it discovers the others while they start, so it sees /clock from early
    # on (the simulator starts the loop as soon as the controller and the recorder match).
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(_env()["ROS_DOMAIN_ID"]))
    node = Node("lca_hil_progress", context=ctx)
    progress = _Progress()
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Clock, ri.CLOCK, progress.on_clock, reliable)
    node.create_subscription(DiagnosticArray, ri.DIAGNOSTICS, progress.on_diagnostics, reliable)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for name, argv in _argvs(bag, duration_s).items():
            procs[name] = _start(argv, out / f"{name}.log")
        code = _wait_for_end(executor, progress, procs, out, duration_s)
    except KeyboardInterrupt:
        code = 130
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        # The recorder first, while the simulator's publishers still exist: it takes every
        # state the middleware holds before it closes the bag.
        _stop([procs[n] for n in ("recorder", "controller", "simulator") if n in procs])
    if code != 0:
        return code
    return _summarise(out, bag, duration_s, progress.steps_per_s())


def _transition(
    joint: JointSeries, drive_time_s: Sequence[float], drive_state: Sequence[str]
) -> tuple[float, float, str]:
    """Where the pivot first left motor driving: position (deg), time (s), the next state.

    NaN, NaN, "none" when it never did.
    """
    seen_motor = False
    for k, state in enumerate(drive_state):
        seen_motor = seen_motor or state == "motor_driving"
        if seen_motor and state != "motor_driving":
            t = drive_time_s[k]
            j = min(range(len(joint.time_s)), key=lambda i: abs(joint.time_s[i] - t))
            return math.degrees(joint.values["position"][j]), t, state
    return math.nan, math.nan, "none"


def _tracking_errors(joint: JointSeries) -> list[float]:
    """|velocity - ramp| (rad/s) over the ramp's steady part (`TRACKING_WINDOW_S`)."""
    ramp = ramp_profile()
    low, high = TRACKING_WINDOW_S
    return [
        abs(v - ramp(t))
        for t, v in zip(joint.time_s, joint.values["velocity"], strict=True)
        if low < t < high
    ]


def _summarise(out: Path, bag: Path, duration_s: float, steps_per_s: float) -> int:
    subprocess.run([_script("lca-plot"), str(bag), "--out", str(out)], env=_env(), check=False)
    try:
        data = read_bag(bag)
    except BagReadError as exc:
        print(f"lca-hil: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    joint = data.joints.get("pivot")
    drive = data.drives.get("pivot")
    if joint is None or drive is None or not drive.state or not joint.time_s:
        print("lca-hil: error: the bag has no pivot states", file=sys.stderr)
        return EXIT_FAILED
    positions = joint.values["position"]
    transition_deg, transition_t, transition_state = _transition(joint, drive.time_s, drive.state)
    errors = _tracking_errors(joint)
    last_state_s = joint.time_s[-1]
    if abs(last_state_s - duration_s) > 1e-9:
        print(
            f"lca-hil: warning: the bag's last state is at {last_state_s:.6f} s, not at the "
            f"end of the run ({duration_s:g} s): the recorder missed the last states",
            file=sys.stderr,
        )
    summary: dict[str, Any] = {
        "transition_from_motor_driving_deg": transition_deg,
        "transition_time_s": transition_t,
        "paper_transition_deg": 55.0,
        "max_velocity_error_deg_s": math.degrees(max(errors)) if errors else math.nan,
        "rms_velocity_error_deg_s": (
            math.degrees(math.sqrt(sum(e * e for e in errors) / len(errors)))
            if errors
            else math.nan
        ),
        "travel_deg": math.degrees(positions[-1] - positions[0]),
        "states_recorded": len(joint.time_s),
        "duration_s": duration_s,
        "last_state_s": last_state_s,
        "closed_loop_steps_per_s": steps_per_s,
    }
    write_json(out / "summary.json", summary, _null_reasons(duration_s))
    print(
        f"motor driving -> {transition_state} at {transition_deg:.2f} deg (paper: 55 deg), "
        f"t = {transition_t:.3f} s\n"
        f"velocity tracking error: max {summary['max_velocity_error_deg_s']:.3f} deg/s, "
        f"rms {summary['rms_velocity_error_deg_s']:.4f} deg/s\n"
        f"pivot travel {summary['travel_deg']:.2f} deg; {len(joint.time_s)} closed-loop steps "
        f"at {steps_per_s:.0f} steps/s; last state at {last_state_s:.3f} s\n"
        f"wrote {bag}, plots and {out / 'summary.json'} in {out}"
    )
    return 0


def _null_reasons(duration_s: float) -> dict[str, str]:
    """Why a summary figure may be null (summary.json is strict JSON: no NaN)."""
    no_transition = f"the pivot did not leave motor driving within the {duration_s:g} s run"
    low, high = TRACKING_WINDOW_S
    no_window = f"no state between {low:g} s and {high:g} s of simulated time (the ramp)"
    return {
        "transition_from_motor_driving_deg": no_transition,
        "transition_time_s": no_transition,
        "max_velocity_error_deg_s": no_window,
        "rms_velocity_error_deg_s": no_window,
        "closed_loop_steps_per_s": "this process saw fewer than two /clock samples",
    }


def ramp_profile() -> Callable[[float], float]:
    """The controller's Fig. 15 ramp, as config/ros/controller.yaml sets it."""
    return RampProfile(1.0, 10.0, math.radians(5.0), 0.0).velocity
