"""`lca-hil fig15`: the closed-loop HIL run of the paper's Fig. 15 over ROS 2.

    lca-hil fig15 --out out/fig15

Starts the simulator (lockstep, current loop in the drive), the controller (the section 6
velocity PI replaying the Fig. 15 ramp) and the recorder as separate ROS 2 processes, shows the
simulated time while they run, stops them when the run is over, and writes the bag, its plots
and a summary: where the pivot left motor driving (the paper has 55 deg), the velocity tracking
error and the closed-loop steps per second.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from lca_control import contract as ri
from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.profiles import RampProfile
from lca_sim.cli.bagplot import BagReadError, read_bag
from lca_sim.config.loader import config_dir
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_FAILED
from lca_sim.ros.node_util import from_stamp

PIVOT_START_DEG = 35.0


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


def _stop(procs: Sequence[subprocess.Popen[bytes]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in procs:
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_fig15(out: Path, duration_s: float) -> int:
    """Run the Fig. 15 loop for `duration_s` of simulated time; return the exit code."""
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "bag"
    if bag.exists():
        print(f"lca-hil: error: {bag} exists; choose another --out", file=sys.stderr)
        return EXIT_BAD_INPUT
    params = config_dir() / "ros"
    start_rad = math.radians(PIVOT_START_DEG)
    simulator = [
        _script("lca-simulator"), "--ros-args", "--params-file", str(params / "simulator.yaml"),
        "-p", "timing_mode:=lockstep", "-p", "command_interface:=current",
        "-p", f"control_period_s:={CONTROL_PERIOD_S}",
        "-p", f"initial_position:=[0.0,{start_rad!r},0.0,0.0]",
        "-p", "lockstep_subscribers:=2",
    ]  # fmt: skip
    # No use_sim_time for the controller: it steps on the state stamps, and a /clock
    # subscription would cost it one more message per step.
    controller = [
        _script("lca-controller"), "--ros-args", "--params-file", str(params / "controller.yaml"),
    ]  # fmt: skip
    recorder = [
        _script("lca-record"), "-o", str(bag), "--wait-s", "30",
        ri.JOINT_STATES, ri.MOTOR_STATES, ri.DRIVE_CHAIN_STATES, ri.VOLTAGE_COMMANDS,
        ri.CURRENT_COMMANDS, ri.CLOCK, "--ros-args", "-p", "use_sim_time:=true",
    ]  # fmt: skip
    print(f"lca-hil: Fig. 15 in lockstep, {duration_s:g} s of simulated time; logs in {out}")
    procs = [_start(recorder, out / "record.log")]
    procs.append(_start(controller, out / "controller.log"))
    procs.append(_start(simulator, out / "simulator.log"))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(_env()["ROS_DOMAIN_ID"]))
    node = Node("lca_hil_progress", context=ctx)
    # The loop's rate over the span this node saw of it: it may match /clock after the loop
    # has started (the simulator waits for the controller and the recorder, not for it).
    clock = {"t": 0.0, "first_t": math.nan, "first_wall": math.nan, "last_wall": math.nan}

    def on_clock(msg: Clock) -> None:
        now = time.monotonic()
        clock["t"] = from_stamp(msg.clock)
        if math.isnan(clock["first_wall"]):
            clock["first_wall"], clock["first_t"] = now, clock["t"]
        clock["last_wall"] = now

    node.create_subscription(
        Clock, ri.CLOCK, on_clock, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    deadline = time.monotonic() + 60.0 + 20.0 * duration_s
    shown = -1
    code = 0
    try:
        while clock["t"] < duration_s:
            executor.spin_once(timeout_sec=0.1)
            if any(p.poll() is not None for p in procs):
                print("lca-hil: error: a node exited early; see the logs", file=sys.stderr)
                code = EXIT_FAILED
                break
            if time.monotonic() > deadline:
                print("lca-hil: error: the loop did not finish in time", file=sys.stderr)
                code = EXIT_FAILED
                break
            if int(clock["t"]) != shown:
                shown = int(clock["t"])
                print(f"\r  simulated {clock['t']:6.2f} / {duration_s:g} s", end="", flush=True)
        seen_wall_s = clock["last_wall"] - clock["first_wall"]
        steps_per_s = (
            (clock["t"] - clock["first_t"]) / CONTROL_PERIOD_S / seen_wall_s
            if seen_wall_s > 0.0
            else math.nan
        )
        print()
    except KeyboardInterrupt:
        code = 130
        steps_per_s = math.nan
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        _stop(procs[::-1])  # simulator first, the recorder last
    if code != 0:
        return code
    return _summarise(out, bag, steps_per_s)


def _summarise(out: Path, bag: Path, steps_per_s: float) -> int:
    subprocess.run([_script("lca-plot"), str(bag), "--out", str(out)], env=_env(), check=False)
    try:
        data = read_bag(bag)
    except BagReadError as exc:
        print(f"lca-hil: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    joint = data.joints.get("pivot")
    drive = data.drives.get("pivot")
    if joint is None or drive is None or not drive.state:
        print("lca-hil: error: the bag has no pivot states", file=sys.stderr)
        return EXIT_FAILED
    positions = joint.values["position"]
    velocities = joint.values["velocity"]
    transition_deg = math.nan
    transition_t = math.nan
    transition_state = "none"
    seen_motor = False
    for k, state in enumerate(drive.state):
        seen_motor = seen_motor or state == "motor_driving"
        if seen_motor and state != "motor_driving":
            t = drive.time_s[k]
            j = min(range(len(joint.time_s)), key=lambda i: abs(joint.time_s[i] - t))
            transition_deg, transition_t = math.degrees(positions[j]), t
            transition_state = state
            break
    ramp = ramp_profile()
    errors = [
        abs(v - ramp(t)) for t, v in zip(joint.time_s, velocities, strict=True) if 2.0 < t < 10.9
    ]
    steps = len(joint.time_s)
    summary = {
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
        "states_recorded": steps,
        "closed_loop_steps_per_s": steps_per_s,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    print(
        f"motor driving -> {transition_state} at {transition_deg:.2f} deg (paper: 55 deg), "
        f"t = {transition_t:.3f} s\n"
        f"velocity tracking error: max {summary['max_velocity_error_deg_s']:.3f} deg/s, "
        f"rms {summary['rms_velocity_error_deg_s']:.4f} deg/s\n"
        f"pivot travel {summary['travel_deg']:.2f} deg; {steps} closed-loop steps at "
        f"{summary['closed_loop_steps_per_s']:.0f} steps/s\n"
        f"wrote {bag}, plots and {out / 'summary.json'} in {out}"
    )
    return 0


def ramp_profile() -> Callable[[float], float]:
    """The controller's Fig. 15 ramp, as config/ros/controller.yaml sets it."""
    return RampProfile(1.0, 10.0, math.radians(5.0), 0.0).velocity
