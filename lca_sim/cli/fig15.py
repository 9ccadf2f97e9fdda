"""`lca-hil fig15`: the closed-loop HIL run of the paper's Fig. 15 over ROS 2.

    lca-hil fig15 --out out/fig15

Starts the simulator (lockstep), the controller (the section 6 velocity PI replaying the
Fig. 15 ramp) and the recorder as separate ROS 2 processes, shows the simulated time while they
run, and writes the bag, its plots and a summary: where the pivot left motor driving (the paper
has 55 deg), the velocity tracking error and the closed-loop steps per second. It is the run
`lca-hil run fig15` computes without ROS, to the last bit (both read config/runs/fig15.yaml).
The simulator ends the run at `lockstep_end_s` = the duration and reports `ended` on
/diagnostics; this process waits for that (at most `END_WAIT_S + END_WAIT_PER_SIM_S * duration`
of wall time), then stops the recorder first, the controller and the simulator after it.
summary.json is strict JSON (a figure the run could not give is null, with its reason).
docs/tools.md ("lca-hil fig15") says why each step is done so.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from lca_control import contract as pc
from lca_sim.analysis.closed_loop import ClosedLoopConfig, replay_references, tracking_window
from lca_sim.analysis.metrics import VelocityTracking, velocity_tracking
from lca_sim.batch.closed_loop_config import load_config
from lca_sim.config.loader import load_robot
from lca_sim.config.paths import config_dir
from lca_sim.config.run_scenario import load_run_scenario
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_FAILED
from lca_sim.model.gantry import Gantry
from lca_sim.output import output_folder, write_json
from lca_sim.ros.bag_read import NS_PER_S, BagData, BagReadError, JointSeries, read_bag
from lca_sim.ros.dds_profile import use_shipped_profile
from lca_sim.ros.node_util import from_stamp, simulator_end_s

SCENARIO = "fig15"  # config/runs/fig15.yaml: the run `lca-hil run fig15` computes too
END_WAIT_S = 60.0  # wall time for start-up and shut-down, on top of ...
END_WAIT_PER_SIM_S = 20.0  # ... this much wall time per simulated second (a loaded machine)
# The recorder is stopped after the simulator ended the run: nothing more is published, so it
# takes what it already received until that falls quiet. The loop waits for the controller,
# not for it: on a loaded host it was 2.4 s of simulated time (3,500 messages) behind, more
# than lca-record's default half second of draining takes.
RECORDER_DRAIN_MAX_S = 10.0


@dataclass(frozen=True, slots=True)
class Fig15Run:
    """The Fig. 15 run as its closed-loop scenario defines it.

    Attributes:
        controller_yaml, simulator_yaml: the nodes' params files, passed to them unchanged.
        robot, faults: the scenario's robot and fault schedule files (None: the params
            file's).
        config: the run as `lca-hil run` computes it (validated: the same checks and words).
    """

    controller_yaml: Path
    simulator_yaml: Path
    robot: Path | None
    faults: Path | None
    config: ClosedLoopConfig


def fig15_run(duration_s: float) -> Fig15Run:
    """The scenario's files (config/runs/fig15.yaml; by default the shipped nodes' files).

    Raises:
        ConfigError: a bad scenario or params file, named with its key.
        ParameterError: a duration that is not > 0 s and a whole multiple of dt_s.
    """
    scenario = load_run_scenario(SCENARIO)
    ros = config_dir() / "ros"
    controller_yaml = scenario.controller or ros / "controller.yaml"
    simulator_yaml = scenario.simulator or ros / "simulator.yaml"
    robot = None if scenario.robot is None else load_robot(str(scenario.robot))
    config = load_config(controller_yaml, simulator_yaml, duration_s, robot=robot)
    return Fig15Run(controller_yaml, simulator_yaml, scenario.robot, scenario.faults, config)


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
            if simulator_end_s(status) is not None:
                self.ended, self.end_message = True, status.message

    def steps_per_s(self, control_period_s: float) -> float:
        """Closed-loop steps per wall second over the span this node saw (NaN: too short).

        It may match /clock after the loop has started (the simulator waits for the
        controller and the recorder, not for it), so the rate is of what it saw.
        """
        seen_wall_s = self.last_wall_s - self.first_wall_s
        if not seen_wall_s > 0.0:
            return math.nan
        return (self.t_s - self.first_t_s) / control_period_s / seen_wall_s


def _argvs(bag: Path, duration_s: float, run: Fig15Run) -> dict[str, list[str]]:
    """The three processes' command lines, in the order they start.

    The nodes get the scenario's params files unchanged; the simulator only its lockstep
    settings on top (the loop `lca-hil run` computes is the lockstep one), and the scenario's
    robot and faults when it names them, as `lca-hil run` takes them.
    """
    scenario_params = []
    if run.robot is not None:
        scenario_params += ["-p", f"robot:={run.robot}"]
    if run.faults is not None:
        scenario_params += ["-p", f"fault_schedule:={run.faults}"]
    return {
        "recorder": [
            _script("lca-record"), "-o", str(bag), "--wait-s", "30",
            "--drain-max-s", f"{RECORDER_DRAIN_MAX_S:g}",
            pc.JOINT_STATES, pc.MOTOR_STATES, pc.DRIVE_CHAIN_STATES, pc.VOLTAGE_COMMANDS,
            pc.CURRENT_COMMANDS, pc.VELOCITY_COMMANDS, pc.CLOCK,
            "--ros-args", "-p", "use_sim_time:=true",
        ],
        # No use_sim_time for the controller: it steps on the state stamps, and a /clock
        # subscription would cost it one more message per step.
        "controller": [
            _script("lca-controller"), "--ros-args",
            "--params-file", str(run.controller_yaml),
        ],
        "simulator": [
            _script("lca-simulator"), "--ros-args",
            "--params-file", str(run.simulator_yaml),
            "-p", "timing_mode:=lockstep",
            "-p", "lockstep_subscribers:=2",
            "-p", f"lockstep_end_s:={float(duration_s)!r}",
            *scenario_params,
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
    """Run the Fig. 15 loop for `duration_s` of simulated time; return the exit code.

    Raises:
        ConfigError, ParameterError: a bad scenario, params file or duration (one line, as
            `lca-hil run` words it), before anything starts or is written.
    """
    run = fig15_run(duration_s)
    output_folder(out)
    bag = out / "bag"
    if bag.exists():
        print(f"lca-hil: error: {bag} exists; choose another --out", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"lca-hil: Fig. 15 in lockstep, {duration_s:g} s of simulated time; logs in {out}")
    # This node first: it discovers the others while they start, so it sees /clock from early
    # on (the simulator starts the loop as soon as the controller and the recorder match).
    use_shipped_profile()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(_env()["ROS_DOMAIN_ID"]))
    node = Node("lca_hil_progress", context=ctx)
    progress = _Progress()
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Clock, pc.CLOCK, progress.on_clock, reliable)
    node.create_subscription(DiagnosticArray, pc.DIAGNOSTICS, progress.on_diagnostics, reliable)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for name, argv in _argvs(bag, duration_s, run).items():
            procs[name] = _start(argv, out / f"{name}.log")
        code = _wait_for_end(executor, progress, procs, out, duration_s)
    except KeyboardInterrupt:
        code = 130
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        # The recorder first, while the simulator's publishers still exist: it takes every
        # state the middleware holds before it closes the bag. The controller, idle meanwhile,
        # knows the run ended (the simulator's `ended` status), so a long drain is no alarm.
        _stop([procs[n] for n in ("recorder", "controller", "simulator") if n in procs])
    if code != 0:
        return code
    return _summarise(out, bag, run, progress.steps_per_s(run.config.control_period_s))


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


def _stamp_s(header_ns: int) -> float:
    """A header stamp as the controller read it (`from_stamp`: sec + 1e-9 * nanosec), s."""
    return float(header_ns // NS_PER_S) + 1e-9 * float(header_ns % NS_PER_S)


def recorded_tracking(data: BagData, run: Fig15Run) -> VelocityTracking:
    """The velocity tracking error of the recorded run, as `lca-hil run` computes its own.

    The references are the ones the controller core computes on the recorded states (the node
    ran the same core on the same float64 values); `velocity_commands` in the bag holds them
    too, but as arrays without a stamp, which the plots align and this must not.

    Raises:
        KeyError: the bag lacks one of the controller's joints.
    """
    controller = run.config.controller
    series = [data.joints[j] for j in controller.joints]
    stamps = series[0].header_ns
    keep = [k for k in range(len(stamps)) if k == 0 or stamps[k] != stamps[k - 1]]  # re-sends
    time_s = np.array([_stamp_s(stamps[k]) for k in keep])
    position = [[s.values["position"][k] for s in series] for k in keep]
    velocity = [[s.values["velocity"][k] for s in series] for k in keep]
    currents = None
    if controller.command_interface == "voltage":
        currents = [[data.motors[j].values["effort"][k] for j in controller.joints] for k in keep]
    reference = replay_references(controller, time_s.tolist(), position, velocity, currents)
    joint = controller.profile_joint
    j = controller.joints.index(joint)
    prismatic = _prismatic(run, joint)
    window = tracking_window(controller, float(time_s[-1]))
    measured = np.array([row[j] for row in velocity])
    return velocity_tracking(joint, prismatic, window, time_s, reference[:, j], measured)


def _prismatic(run: Fig15Run, joint: str) -> bool:
    """Whether the robot's `joint` is prismatic (its velocity in m/s), from its URDF."""
    robot = run.config.robot
    gantry = Gantry(robot.urdf_xml, robot.gravity_m_s2, robot.source)
    return next(j.prismatic for j in gantry.joints if j.name == joint)


def recording_problems(
    time_s: Sequence[float], duration_s: float, control_period_s: float
) -> list[str]:
    """What the recorded states of a lockstep run lack: its end, or states in between.

    The run publishes a state at 0 and after every control period up to `duration_s`; nothing
    paces it to the recorder, so a recorder behind by more than its depth loses the oldest
    and one stopped while behind misses the last.
    """
    problems = []
    last_s = time_s[-1]
    if abs(last_s - duration_s) > 1e-9:
        problems.append(
            f"the bag's last state is at {last_s:.6f} s, not at the end of the run "
            f"({duration_s:g} s): the recorder missed the last states"
        )
    expected = round(last_s / control_period_s) + 1
    if len(time_s) < expected:
        problems.append(
            f"the bag holds {len(time_s)} states up to {last_s:g} s of the {expected} the run "
            "published: the recorder fell behind and lost some"
        )
    return problems


def _summarise(out: Path, bag: Path, run: Fig15Run, steps_per_s: float) -> int:
    duration_s = run.config.duration_s
    subprocess.run([_script("lca-plot"), str(bag), "--out", str(out)], env=_env(), check=False)
    try:
        data = read_bag(bag)
    except BagReadError as exc:
        print(f"lca-hil: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    joint = data.joints.get("pivot")
    drive = data.drives.get("pivot")
    missing = [j for j in run.config.controller.joints if j not in data.joints]
    if joint is None or drive is None or not drive.state or not joint.time_s or missing:
        print("lca-hil: error: the bag has no pivot states", file=sys.stderr)
        return EXIT_FAILED
    positions = joint.values["position"]
    transition_deg, transition_t, transition_state = _transition(joint, drive.time_s, drive.state)
    tracking = recorded_tracking(data, run)
    last_state_s = joint.time_s[-1]
    for problem in recording_problems(joint.time_s, duration_s, run.config.control_period_s):
        print(f"lca-hil: warning: {problem}", file=sys.stderr)
    summary: dict[str, Any] = {
        "transition_from_motor_driving_deg": transition_deg,
        "transition_time_s": transition_t,
        "paper_transition_deg": 55.0,
        "tracking_joint": tracking.joint,
        "tracking_window_s": [tracking.from_s, tracking.to_s],
        **tracking.figures(),
        # the same figures in deg/s, the paper's unit (lca-hil paper's Fig. 15 reads them)
        "max_velocity_error_deg_s": math.degrees(tracking.max),
        "rms_velocity_error_deg_s": math.degrees(tracking.rms),
        "travel_deg": math.degrees(positions[-1] - positions[0]),
        "states_recorded": len(joint.time_s),
        "duration_s": duration_s,
        "last_state_s": last_state_s,
        "closed_loop_steps_per_s": steps_per_s,
    }
    write_json(out / "summary.json", summary, _null_reasons(duration_s, tracking))
    print(
        f"motor driving -> {transition_state} at {transition_deg:.2f} deg (paper: 55 deg), "
        f"t = {transition_t:.3f} s\n"
        f"{tracking.describe()} ({summary['max_velocity_error_deg_s']:.3f} deg/s max)\n"
        f"pivot travel {summary['travel_deg']:.2f} deg; {len(joint.time_s)} closed-loop steps "
        f"at {steps_per_s:.0f} steps/s; last state at {last_state_s:.3f} s\n"
        f"wrote {bag}, plots and {out / 'summary.json'} in {out}"
    )
    return 0


def _null_reasons(duration_s: float, tracking: VelocityTracking) -> dict[str, str]:
    """Why a summary figure may be null (summary.json is strict JSON: no NaN)."""
    no_transition = f"the pivot did not leave motor driving within the {duration_s:g} s run"
    no_window = (
        f"no state between {tracking.from_s:g} s and {tracking.to_s:.6g} s of simulated time "
        "(the reference profile's span)"
    )
    return {
        "transition_from_motor_driving_deg": no_transition,
        "transition_time_s": no_transition,
        **dict.fromkeys(tracking.figures(), no_window),
        "max_velocity_error_deg_s": no_window,
        "rms_velocity_error_deg_s": no_window,
        "closed_loop_steps_per_s": "this process saw fewer than two /clock samples",
    }


def ramp_profile() -> Callable[[float], float]:
    """The controller's Fig. 15 reference profile, as the scenario's controller file sets it.

    Raises:
        ConfigError: a bad scenario or controller file.
    """
    run = fig15_run(13.0)
    profile = run.config.controller.profile
    if profile is None:
        return lambda _t_s: 0.0
    return profile.velocity
