"""Benchmark: the ROS 2 loop of the simulator and controller nodes against bare rclpy.

What it measures, in one run, with every ROS process a child of this script on its own domain
id (140..143) and DDS discovery limited to this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST):

1. Lockstep closed loop: ``lca-simulator`` (lockstep, current commands, 4 ms control period,
   pivot at 35 deg) and ``lca-controller`` (config/ros/controller.yaml; it steps on state
   stamps, no /clock) as two
   processes. The rate is read from the simulator's own ``/diagnostics`` (status
   ``lca_hil/simulator``, once per ``diagnostics_period_s``) at two instants a window apart:
   steps/s = delta(sim_time_s) / control_period_s / delta(stamp), the stamps being the wall
   time at which the simulator published them. The observer only takes /diagnostics, so it adds
   no load to the loop itself.
2. Bare rclpy ping-pong between two processes with the loop's message types and QoS (reliable,
   depth 100): ``ping`` publishes a JointState, ``pong`` answers each with a Float64MultiArray,
   ``ping`` publishes the next on the answer. Both spin a SingleThreadedExecutor as the nodes
   do. The figure is round trips per second over the same window; the target is a lockstep rate
   of at least 0.8x that. Phases 1 and 2 run in turn ``--pairs`` times (3 by default), so that the
   host's load drifting during a run does not land on one side of the ratio only; each pair
   gives a ratio, and the headline figure is their median.
3. Realtime mode: ``lca-simulator`` with ``timing_mode:=realtime`` at ``publish_rate_hz`` 250,
   then 1000 (separate runs, no controller), with an observer process that records the receive
   time (CLOCK_MONOTONIC) and header stamp of every joint_states message over the window. It
   reports the achieved rate (messages / wall s at the receiver) and the period jitter as p50 and
   p99 of |delta t - 1/rate|, headline figures from the receive times, the stamp deltas (the
   publisher's tick times, quantized to dt_s) alongside; and the simulator's ``overrun_steps``
   and ``realtime_factor`` from /diagnostics.

While a phase runs, the script samples the CPU time of each child (/proc/PID/stat) and reports
the CPU milliseconds each process spends per loop step or round trip over the window, which
shows what limits the lockstep rate. Targets are reported, never enforced: the exit status is 0
when every figure was measured, 1 when a phase failed. The last stdout line is one JSON object.

The simulator runs with config/ros/simulator.yaml, so Pinocchio's rigid-body terms are held
for its ``rigid_body_period_s`` (1 ms, 10 model steps); ``--rigid-body-period-s 1e-4``
evaluates them at every step, the exact scheme, for comparison.

Run from the repository root::

    .venv/bin/python bench/ros_loop.py            # 10 s windows, 3 pairs, about 2.5 min in all
    .venv/bin/python bench/ros_loop.py --quick    # 3 s windows, a fast check

Children stop on their own (every role has a deadline), and are ended by this script on exit,
on errors, on SIGINT/SIGTERM, and by the kernel (parent-death signal) if it is killed.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import functools
import itertools
import json
import math
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from lca_control.cascade import CONTROL_PERIOD_S

REPO_ROOT = Path(__file__).resolve().parent.parent
BIN_DIR = Path(sys.executable).parent
SIMULATOR_YAML = REPO_ROOT / "config" / "ros" / "simulator.yaml"
CONTROLLER_YAML = REPO_ROOT / "config" / "ros" / "controller.yaml"

DOMAIN_LOCKSTEP = 140
DOMAIN_PINGPONG = 141
DOMAIN_REALTIME = {250: 142, 1000: 143}
REALTIME_RATES_HZ = (250, 1000)
INITIAL_POSITION = "[0.0,0.6109,0.0,0.0]"
TARGET_RATIO_MIN = 0.8

DEFAULT_WINDOW_S = 10.0
QUICK_WINDOW_S = 3.0
DEFAULT_WARMUP_S = 2.0
DEFAULT_PAIRS = 3  # lockstep / ping-pong measured in turn this many times; the median ratio counts
QUICK_WARMUP_S = 1.0
STARTUP_TIMEOUT_S = 30.0  # first data from a freshly started node (numba cache, discovery)
STOP_TIMEOUT_S = 5.0  # SIGTERM -> exit, then SIGKILL
POLL_S = 0.1  # the parent's polling (and CPU sampling) period
SPIN_TIMEOUT_S = 0.1  # spin_once timeout, as in lca_sim.ros.node_util.run_node

SIMULATOR_STATUS = "lca_hil/simulator"
PING_TOPIC = "bench_ping"
PONG_TOPIC = "bench_pong"
PINGPONG_QOS_DEPTH = 100
PING_RESEND_S = 0.5  # before the endpoints have matched, a first ping can go nowhere
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
PR_SET_PDEATHSIG = 1
MACHINE = "_machine"  # key of the whole machine's busy CPU seconds in the CPU samples
BUSY_MACHINE_SHARE = 0.2  # other processes above this many cores: the figures are suspect
# /proc/stat's window within this share of the wall time times the CPUs (and its busy time no
# more than this share of the window below the measured processes'), or no "other" figure.
OTHER_LOAD_TOLERANCE = 0.05
MACHINE_ALL = "_machine_all"  # key of the machine's counted CPU seconds, busy or idle

JsonDict = dict[str, Any]


# --- small helpers --------------------------------------------------------------------------


def ros_env(domain_id: int) -> dict[str, str]:
    """The environment of a ROS process: loopback-only discovery on an explicit domain."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile with linear interpolation (numpy's default method)."""
    ordered = sorted(values)
    if not ordered:
        return math.nan
    pos = (len(ordered) - 1) * q / 100.0
    low = math.floor(pos)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (pos - low)


def jitter_ms(deltas_s: Sequence[float], period_s: float) -> JsonDict:
    """p50, p99 and max of |delta - period| in ms, with the mean delta."""
    errors = [abs(d - period_s) * 1e3 for d in deltas_s]
    if not errors:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None, "mean_period_ms": None}
    return {
        "p50_ms": percentile(errors, 50.0),
        "p99_ms": percentile(errors, 99.0),
        "max_ms": max(errors),
        "mean_period_ms": sum(deltas_s) / len(deltas_s) * 1e3,
    }


def rounded(value: float | None, digits: int = 3) -> float | None:
    """A float rounded for the JSON line; None and non-finite values become None."""
    if value is None or not math.isfinite(value):
        return None
    return round(value, digits)


def fmt(value: float | None, spec: str = ".1f") -> str:
    """A number for humans, or n/a."""
    return "n/a" if value is None or not math.isfinite(value) else format(value, spec)


# --- roles: the child processes of the ping-pong and the observers --------------------------


class StopFlag:
    """Set by SIGTERM or SIGINT; the role loops end at the next spin."""

    def __init__(self) -> None:
        self.requested = False
        signal.signal(signal.SIGTERM, self._on_signal)
        signal.signal(signal.SIGINT, self._on_signal)

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        self.requested = True


def reliable_qos(depth: int) -> Any:
    """Reliable, keep-last `depth`: the QoS of the loop's state and command topics."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)  # type: ignore[no-untyped-call]


def spin_until(
    node: Any, done: Callable[[], bool], deadline: float, stop: StopFlag, executor_kind: str
) -> bool:
    """Spin `node` until done(); False on deadline.

    executor_kind: `single` (rclpy's default SingleThreadedExecutor, what `rclpy.spin` uses) or
    `events` (the C++ events executor the lca_hil nodes use when rclpy has it).
    """
    from lca_sim.ros.node_util import make_executor

    executor = make_executor(node.context, executor_kind)
    executor.add_node(node)
    try:
        while not done():
            if stop.requested or time.monotonic() > deadline:
                return False
            executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
        return True
    finally:
        executor.remove_node(node)


def run_role(role: str, args: argparse.Namespace) -> int:
    """Run one child role with its own rclpy context; print one JSON line; exit code."""
    import rclpy
    from rclpy.utilities import ok as rclpy_ok

    stop = StopFlag()
    deadline = time.monotonic() + args.timeout_s
    rclpy.init()
    try:
        if role == "pong":
            result = role_pong(deadline, stop, args.executor)
        elif role == "ping":
            result = role_ping(args.warmup_s, args.window_s, deadline, stop, args.executor)
        elif role == "observe-lockstep":
            result = role_observe_lockstep(args.warmup_s, args.window_s, deadline, stop)
        else:
            result = role_observe_realtime(
                args.rate_hz, args.warmup_s, args.window_s, deadline, stop
            )
    finally:
        if rclpy_ok():
            rclpy.shutdown()
    print(json.dumps(result), flush=True)
    return 0 if result.get("ok") else 1


def role_pong(deadline: float, stop: StopFlag, executor_kind: str) -> JsonDict:
    """Answer every JointState on PING_TOPIC with a Float64MultiArray on PONG_TOPIC."""
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    node = Node("bench_pong")
    qos = reliable_qos(PINGPONG_QOS_DEPTH)
    pub = node.create_publisher(Float64MultiArray, PONG_TOPIC, qos)
    answered = [0]

    def on_ping(msg: Any) -> None:
        # Echo the sequence number (in the stamp) and three values, as a 4-joint command.
        data = [float(msg.header.stamp.nanosec), *msg.position[:3]]
        pub.publish(Float64MultiArray(data=data))
        answered[0] += 1

    node.create_subscription(JointState, PING_TOPIC, on_ping, qos)
    spin_until(node, lambda: False, deadline, stop, executor_kind)  # until SIGTERM or the deadline
    node.destroy_node()  # type: ignore[no-untyped-call]
    return {"role": "pong", "ok": True, "answered": answered[0]}


class Pinger:
    """The ping side of ping-pong: one JointState out, the next when its answer is back.

    Round trips are counted on the answers' arrival times: the first answer starts the warm-up,
    the window opens `warmup_s` later and closes `window_s` after that (no next ping then).
    """

    def __init__(self, pub: Any, joint_state: type, warmup_s: float, window_s: float) -> None:
        self.pub = pub
        self.joint_state = joint_state
        self.warmup_s = warmup_s
        self.window_s = window_s
        self.seq = 0
        self.count = 0
        self.sent_at = 0.0
        self.resends = 0
        self.stale = 0
        self.marks: dict[str, float] = {}

    def send(self) -> None:
        """Publish the ping of the current sequence number (carried in the stamp)."""
        msg = self.joint_state()
        msg.header.stamp.nanosec = self.seq
        msg.name = list(JOINTS)
        msg.position = [float(self.seq), 0.6109, 0.0, 0.0]
        msg.velocity = [0.0, 0.01, 0.0, 0.0]
        msg.effort = [0.0, 1.0, 0.0, 0.0]
        self.pub.publish(msg)
        self.sent_at = time.monotonic()

    def on_pong(self, msg: Any) -> None:
        """Count an answer to the current ping and send the next; ignore stale answers."""
        now = time.monotonic()
        if not msg.data or int(msg.data[0]) != self.seq:
            self.stale += 1
            return
        self.count += 1
        if self.mark_window(now):
            return  # done: no next ping
        self.seq = (self.seq + 1) % 1_000_000_000
        self.send()

    def mark_window(self, now: float) -> bool:
        """Mark the warm-up start and the window's ends at `now`; True when the window closed."""
        marks = self.marks
        if "first_t" not in marks:
            marks["first_t"] = now
        elif "a_t" not in marks and now >= marks["first_t"] + self.warmup_s:
            marks["a_t"], marks["a_n"] = now, self.count
        elif "a_t" in marks and "b_t" not in marks and now >= marks["a_t"] + self.window_s:
            marks["b_t"], marks["b_n"] = now, self.count
            return True
        return False

    def done(self) -> bool:
        """True once the window closed; resends a ping whose answer is overdue."""
        if "b_t" in self.marks:
            return True
        if time.monotonic() - self.sent_at > PING_RESEND_S:
            self.resends += 1
            self.send()
        return False

    def result(self) -> JsonDict:
        """The JSON result of a closed window."""
        marks = self.marks
        round_trips = int(marks["b_n"] - marks["a_n"])
        wall_s = marks["b_t"] - marks["a_t"]
        return {
            "role": "ping",
            "ok": True,
            "round_trips": round_trips,
            "wall_s": wall_s,
            "round_trips_per_s": round_trips / wall_s,
            "t_start": marks["a_t"],
            "t_end": marks["b_t"],
            "resends": self.resends,
            "stale": self.stale,
        }


def role_ping(
    warmup_s: float, window_s: float, deadline: float, stop: StopFlag, executor_kind: str
) -> JsonDict:
    """Ping-pong: one JointState out, wait for the answer, the next; count round trips."""
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    node = Node("bench_ping")
    qos = reliable_qos(PINGPONG_QOS_DEPTH)
    pub = node.create_publisher(JointState, PING_TOPIC, qos)
    pinger = Pinger(pub, JointState, warmup_s, window_s)
    node.create_subscription(Float64MultiArray, PONG_TOPIC, pinger.on_pong, qos)
    matched = spin_until(
        node,
        lambda: node.count_subscribers(PING_TOPIC) >= 1 and node.count_publishers(PONG_TOPIC) >= 1,
        min(deadline, time.monotonic() + STARTUP_TIMEOUT_S),
        stop,
        executor_kind,
    )
    if not matched:
        node.destroy_node()  # type: ignore[no-untyped-call]
        return {"role": "ping", "ok": False, "error": "pong not discovered"}
    pinger.send()
    finished = spin_until(node, pinger.done, deadline, stop, executor_kind)
    node.destroy_node()  # type: ignore[no-untyped-call]
    if not finished:
        return {"role": "ping", "ok": False, "error": "no full window before the deadline"}
    return pinger.result()


@dataclass(slots=True)
class DiagSample:
    """One `lca_hil/simulator` status from /diagnostics, with its receive time."""

    recv_t: float  # CLOCK_MONOTONIC at the observer
    stamp_s: float  # the simulator's wall clock when it published
    values: dict[str, str]

    def number(self, key: str) -> float:
        """A numeric value (nan when absent)."""
        text = self.values.get(key)
        return float(text) if text is not None else math.nan

    def as_json(self) -> JsonDict:
        """For the parent: receive time, stamp and the numeric values it needs."""
        keys = ("sim_time_s", "steps", "states_published", "overrun_steps", "realtime_factor")
        return {
            "recv_t": self.recv_t,
            "stamp_s": self.stamp_s,
            **{k: self.number(k) for k in keys},
        }


def subscribe_diagnostics(node: Any, samples: list[DiagSample], timing_mode: str) -> None:
    """Append every simulator status of `timing_mode` on /diagnostics to `samples`."""
    from diagnostic_msgs.msg import DiagnosticArray

    from lca_control import contract as pc

    def on_diag(msg: Any) -> None:
        now = time.monotonic()
        stamp_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        for status in msg.status:
            if status.name == SIMULATOR_STATUS:
                values = {kv.key: kv.value for kv in status.values}
                if values.get("timing_mode") == timing_mode:
                    samples.append(DiagSample(now, stamp_s, values))

    node.create_subscription(DiagnosticArray, pc.DIAGNOSTICS, on_diag, 10)


def foreign_publishers(node: Any) -> str | None:
    """An error when joint_states has other publishers than our simulator (shared domain)."""
    from lca_control import contract as pc

    count = node.count_publishers(pc.JOINT_STATES)
    if count == 1:
        return None
    domain = os.environ.get("ROS_DOMAIN_ID")
    return f"{count} joint_states publishers on domain {domain} (expected 1: is it shared?)"


def role_observe_lockstep(
    warmup_s: float, window_s: float, deadline: float, stop: StopFlag
) -> JsonDict:
    """Two simulator /diagnostics samples `window_s` apart, after the loop has run `warmup_s`."""
    from rclpy.node import Node

    node = Node("bench_observe_lockstep")
    samples: list[DiagSample] = []
    subscribe_diagnostics(node, samples, "lockstep")
    picked: dict[str, DiagSample] = {}

    def done() -> bool:
        running = [s for s in samples if s.number("steps") > 0]
        if not running:
            return False
        start_s = running[0].stamp_s + warmup_s
        a = next((s for s in running if s.stamp_s >= start_s), None)
        if a is None:
            return False
        # Half a diagnostics period of slack: a timer firing late must not add a whole period.
        period_s = running[1].stamp_s - running[0].stamp_s if len(running) > 1 else 1.0
        b = next((s for s in running if s.stamp_s >= a.stamp_s + window_s - 0.5 * period_s), None)
        if b is None:
            return False
        picked["a"], picked["b"] = a, b
        return True

    finished = spin_until(node, done, deadline, stop, "single")
    foreign = foreign_publishers(node)
    node.destroy_node()  # type: ignore[no-untyped-call]
    if foreign:
        return {"role": "observe-lockstep", "ok": False, "error": foreign}
    if not finished:
        return {
            "role": "observe-lockstep",
            "ok": False,
            "error": f"no full window before the deadline ({len(samples)} diagnostics samples)",
        }
    return {
        "role": "observe-lockstep",
        "ok": True,
        "a": picked["a"].as_json(),
        "b": picked["b"].as_json(),
    }


def role_observe_realtime(
    rate_hz: float, warmup_s: float, window_s: float, deadline: float, stop: StopFlag
) -> JsonDict:
    """Receive times and stamps of joint_states over the window, and /diagnostics around it."""
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from lca_control import contract as pc

    node = Node("bench_observe_realtime")
    samples: list[DiagSample] = []
    subscribe_diagnostics(node, samples, "realtime")
    recv: list[float] = []
    stamps: list[float] = []
    window: dict[str, float] = {}

    def on_state(msg: Any) -> None:
        now = time.monotonic()
        if "start" not in window:
            window["start"] = now + warmup_s
            window["end"] = window["start"] + window_s
        if window["start"] <= now < window["end"]:
            recv.append(now)
            stamps.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)

    qos = reliable_qos(pc.STATE_QOS_DEPTH)
    node.create_subscription(JointState, pc.JOINT_STATES, on_state, qos)

    def diag_after(t: float) -> DiagSample | None:
        return next((s for s in samples if s.recv_t >= t), None)

    def done() -> bool:
        return "end" in window and diag_after(window["end"]) is not None

    finished = spin_until(node, done, deadline, stop, "single")
    foreign = foreign_publishers(node)
    node.destroy_node()  # type: ignore[no-untyped-call]
    if foreign:
        return {"role": "observe-realtime", "ok": False, "error": foreign}
    if not finished or len(recv) < 2:
        return {
            "role": "observe-realtime",
            "ok": False,
            "error": f"no full window before the deadline ({len(recv)} states received)",
        }
    period_s = 1.0 / rate_hz
    recv_deltas = [b - a for a, b in itertools.pairwise(recv)]
    stamp_deltas = [b - a for a, b in itertools.pairwise(stamps)]
    a = diag_after(window["start"])
    b = diag_after(window["end"])
    return {
        "role": "observe-realtime",
        "ok": True,
        "messages": len(recv),
        "wall_s": recv[-1] - recv[0],
        "rate_hz": (len(recv) - 1) / (recv[-1] - recv[0]),
        "stamp_rate_hz": (len(stamps) - 1) / (stamps[-1] - stamps[0]),
        "recv_jitter": jitter_ms(recv_deltas, period_s),
        "stamp_jitter": jitter_ms(stamp_deltas, period_s),
        "stamp_gaps_over_2_periods": sum(1 for d in stamp_deltas if d > 2.0 * period_s),
        "t_start": recv[0],
        "t_end": recv[-1],
        "a": a.as_json() if a else None,
        "b": b.as_json() if b else None,
    }


# --- the parent: children, CPU sampling, phases ---------------------------------------------


def _parent_death_signal() -> Callable[[], None]:
    """A preexec_fn: the child gets SIGTERM when this script dies, even by SIGKILL."""
    libc = ctypes.CDLL(None, use_errno=True)
    parent_pid = os.getpid()

    def preexec() -> None:
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:  # the parent died before prctl took effect
            os.kill(os.getpid(), signal.SIGTERM)

    return preexec


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process (all its threads), from /proc; None when gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text(encoding="ascii")
    except OSError:
        return None
    fields = text[text.rindex(")") + 2 :].split()  # after "pid (comm) "
    ticks = int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of stat)
    return ticks / os.sysconf("SC_CLK_TCK")


def machine_cpu_seconds() -> tuple[float, float]:
    """(busy, all) CPU seconds this machine has counted since boot, summed over CPUs."""
    with Path("/proc/stat").open(encoding="ascii") as stat:
        fields = [int(x) for x in stat.readline().split()[1:]]
    user, nice, system, idle, iowait, irq, softirq, steal = fields[:8]
    busy = user + nice + system + irq + softirq + steal
    tick = os.sysconf("SC_CLK_TCK")
    return busy / tick, (busy + idle + iowait) / tick


def other_processes_share(
    busy_s: float, all_s: float, ours_s: float, wall_s: float
) -> tuple[float | None, str]:
    """The share of a core the rest of the machine used over a window, or None and why not.

    From /proc/stat's counts over the window minus the measured processes' CPU. On the
    project's virtual machines /proc/stat counts some windows short or long: 160 instead of
    200 ticks a second on 2 CPUs, or busy time below what the measured processes alone used
    (their own counts, /proc/PID/stat, agree with py-spy and `time.thread_time`). Such a
    window gives no figure rather than a wrong one (which read as "another load kept half a
    core busy" where there was none).
    """
    expected_s = wall_s * (os.cpu_count() or 1)
    if abs(all_s - expected_s) > OTHER_LOAD_TOLERANCE * expected_s:
        return None, (
            f"not measurable: /proc/stat counted {all_s:.1f} s of CPU time in a window of "
            f"{expected_s:.1f} CPU seconds"
        )
    if busy_s < ours_s - OTHER_LOAD_TOLERANCE * wall_s:
        return None, (
            f"not measurable: /proc/stat's busy time ({busy_s:.2f} s) is less than the "
            f"measured processes' own ({ours_s:.2f} s)"
        )
    return max(0.0, busy_s - ours_s) / wall_s, ""


def other_processes_note(figures: JsonDict, what: str) -> str:
    """A line for humans when the rest of the machine was busy or cannot be told ('' if neither)."""
    other = figures["cpu_share"]
    if other is None:
        return f"  other processes: {figures.get('why', 'not measured')}"
    if other > BUSY_MACHINE_SHARE:
        return (
            f"  WARNING: other processes kept {100 * other:.0f} % of a core busy during the "
            f"window: the figures of this {what} are low"
        )
    return ""


@dataclass(slots=True)
class Child:
    """A child process with its stdout and stderr in files."""

    name: str
    proc: subprocess.Popen[bytes]
    stdout: Path
    stderr: Path

    def last_json(self) -> JsonDict | None:
        """The last stdout line as JSON (the roles' result), or None."""
        lines = self.stdout.read_text(encoding="utf-8", errors="replace").strip().splitlines()
        if not lines:
            return None
        try:
            value = json.loads(lines[-1])
        except json.JSONDecodeError:
            return None
        return value if isinstance(value, dict) else None

    def log_tail(self, lines: int = 8) -> str:
        """The end of its stderr, indented, for error messages."""
        text = self.stderr.read_text(encoding="utf-8", errors="replace").strip().splitlines()
        return "\n".join("      " + line for line in text[-lines:])


@dataclass(slots=True)
class Children:
    """Starts children, samples their CPU time, and ends them (SIGTERM, then SIGKILL)."""

    log_dir: Path
    running: list[Child] = field(default_factory=list)
    cpu: list[tuple[float, dict[str, float]]] = field(default_factory=list)

    def start(self, name: str, argv: list[str], domain_id: int) -> Child:
        """Start `argv` with a loopback-only ROS environment on `domain_id`."""
        stdout = self.log_dir / f"{name}.out"
        stderr = self.log_dir / f"{name}.err"
        with stdout.open("wb") as out, stderr.open("wb") as err:
            proc = subprocess.Popen(
                argv,
                cwd=REPO_ROOT,
                env=ros_env(domain_id),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=err,
                preexec_fn=_parent_death_signal(),  # noqa: PLW1509 (the parent has no threads)
            )
        child = Child(name, proc, stdout, stderr)
        self.running.append(child)
        return child

    def sample_cpu(self) -> None:
        """Record the CPU seconds of every live child now."""
        now = time.monotonic()
        values: dict[str, float] = {}
        for child in self.running:
            seconds = cpu_seconds(child.proc.pid) if child.proc.poll() is None else None
            if seconds is not None:
                values[child.name] = seconds
        values[MACHINE], values[MACHINE_ALL] = machine_cpu_seconds()
        self.cpu.append((now, values))

    def cpu_between(self, name: str, t0: float, t1: float) -> float | None:
        """CPU seconds `name` used between t0 and t1 (interpolated samples), or None."""
        series = [(t, v[name]) for t, v in self.cpu if name in v]

        def at(t: float) -> float | None:
            for (ta, va), (tb, vb) in itertools.pairwise(series):
                if ta <= t <= tb:
                    return va + (vb - va) * (t - ta) / (tb - ta) if tb > ta else va
            return None

        start, end = at(t0), at(t1)
        return None if start is None or end is None else end - start

    def stop_all(self) -> None:
        """SIGTERM every live child, wait, SIGKILL the stragglers; forget them all."""
        for child in self.running:
            if child.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    child.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for child in self.running:
            try:
                child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait()
        self.running.clear()
        self.cpu.clear()


class PhaseError(RuntimeError):
    """A phase could not measure: a child failed or a deadline passed."""


def wait_for(
    children: Children, result_of: Child, others: Sequence[Child], timeout_s: float
) -> JsonDict:
    """Sample CPU until `result_of` exits; its JSON result. Raises PhaseError on failures."""
    deadline = time.monotonic() + timeout_s
    while result_of.proc.poll() is None:
        children.sample_cpu()
        for child in others:
            if child.proc.poll() is not None:
                raise PhaseError(
                    f"{child.name} exited early (code {child.proc.returncode}):\n{child.log_tail()}"
                )
        if time.monotonic() > deadline:
            raise PhaseError(f"{result_of.name} gave no result within {timeout_s:g} s")
        time.sleep(POLL_S)
    result = result_of.last_json()
    if result is None or not result.get("ok"):
        error = result.get("error") if result else "no result line"
        raise PhaseError(f"{result_of.name}: {error}\n{result_of.log_tail()}")
    return result


def role_argv(
    role: str, timeout_s: float, warmup_s: float, window_s: float, executor: str = "single"
) -> list[str]:
    """The command line of this script in a child role."""
    return [
        sys.executable,
        str(Path(__file__).resolve()),
        "--role",
        role,
        "--timeout-s",
        f"{timeout_s:g}",
        "--warmup-s",
        f"{warmup_s:g}",
        "--window-s",
        f"{window_s:g}",
        "--executor",
        executor,
    ]


def simulator_yaml_value(name: str) -> Any:
    """One parameter of config/ros/simulator.yaml (what the simulator runs with by default)."""
    from lca_sim.config.yaml_files import read_yaml

    return read_yaml(SIMULATOR_YAML)["simulator"]["ros__parameters"][name]


def simulator_argv(*overrides: str) -> list[str]:
    """`lca-simulator` with config/ros/simulator.yaml and `-p` overrides."""
    argv = [str(BIN_DIR / "lca-simulator"), "--ros-args", "--params-file", str(SIMULATOR_YAML)]
    for override in overrides:
        argv += ["-p", override]
    return argv


def cpu_per_event_ms(
    children: Children, names: Sequence[str], t0: float, t1: float, events: float
) -> JsonDict:
    """Per process: CPU ms per event (step or round trip) and CPU share over [t0, t1]."""
    out: JsonDict = {}
    ours = 0.0
    for name in names:
        used = children.cpu_between(name, t0, t1)
        ours += used or 0.0
        out[name] = {
            "cpu_ms_per_event": rounded(used / events * 1e3, 4) if used is not None else None,
            "cpu_share": rounded(used / (t1 - t0), 3) if used is not None else None,
        }
    machine = children.cpu_between(MACHINE, t0, t1)
    machine_all = children.cpu_between(MACHINE_ALL, t0, t1)
    # Everything else on the machine (this script's polling included): a busy neighbour makes
    # every figure of the phase low.
    other, why = (
        other_processes_share(machine, machine_all, ours, t1 - t0)
        if machine is not None and machine_all is not None
        else (None, "not measured")
    )
    out["other_processes"] = {
        "cpu_ms_per_event": None,
        "cpu_share": rounded(other, 3) if other is not None else None,
        **({"why": why} if why else {}),
    }
    return out


def print_cpu(cpu: JsonDict, unit: str) -> None:
    """The per-process CPU figures for humans."""
    for name, figures in cpu.items():
        share = figures["cpu_share"]
        per_event = figures["cpu_ms_per_event"]
        print(
            f"  cpu {name:<18} "
            + (f"{fmt(per_event, '.3f')} ms/{unit}, " if name != "other_processes" else "")
            + f"{fmt(None if share is None else 100 * share)}% of a core"
        )
    note = other_processes_note(cpu["other_processes"], "phase")
    if note:
        print(note)


def phase_lockstep(
    children: Children, warmup_s: float, window_s: float, sim_overrides: Sequence[str]
) -> JsonDict:
    """[1] The lockstep closed loop, rate from the simulator's /diagnostics."""
    timeout_s = STARTUP_TIMEOUT_S + warmup_s + window_s + 10.0
    sim = children.start(
        "simulator",
        simulator_argv(
            "timing_mode:=lockstep",
            "command_interface:=current",
            f"control_period_s:={CONTROL_PERIOD_S}",
            f"initial_position:={INITIAL_POSITION}",
            *sim_overrides,
        ),
        DOMAIN_LOCKSTEP,
    )
    ctl = children.start(
        "controller",
        [
            str(BIN_DIR / "lca-controller"),
            "--ros-args",
            "--params-file",
            str(CONTROLLER_YAML),
        ],
        DOMAIN_LOCKSTEP,
    )
    obs = children.start(
        "observer",
        role_argv("observe-lockstep", timeout_s, warmup_s, window_s),
        DOMAIN_LOCKSTEP,
    )
    result = wait_for(children, obs, [sim, ctl], timeout_s + 5.0)
    a, b = result["a"], result["b"]
    wall_s = b["stamp_s"] - a["stamp_s"]
    periods = (b["sim_time_s"] - a["sim_time_s"]) / CONTROL_PERIOD_S
    steps_per_s = periods / wall_s
    cpu = cpu_per_event_ms(
        children, ["simulator", "controller", "observer"], a["recv_t"], b["recv_t"], periods
    )
    print(f"  window {wall_s:.3f} s (simulator /diagnostics stamps), {periods:.0f} control periods")
    print(f"  lockstep steps/s       {steps_per_s:8.1f}  (= {steps_per_s * CONTROL_PERIOD_S:.3f}x")
    print(f"                                   real time at {CONTROL_PERIOD_S * 1e3:g} ms/step)")
    print(f"  model substeps/s       {(b['steps'] - a['steps']) / wall_s:8.0f}")
    print(f"  loop period            {1e3 / steps_per_s:8.3f} ms")
    print_cpu(cpu, "step")
    return {
        "steps_per_s": steps_per_s,
        "window_s": wall_s,
        "periods": periods,
        "model_substeps_per_s": (b["steps"] - a["steps"]) / wall_s,
        "states_published_per_s": (b["states_published"] - a["states_published"]) / wall_s,
        "cpu": cpu,
    }


def phase_pingpong(children: Children, warmup_s: float, window_s: float, executor: str) -> JsonDict:
    """[2] Bare rclpy ping-pong between two processes, spinning the given executor kind."""
    timeout_s = STARTUP_TIMEOUT_S + warmup_s + window_s + 10.0
    pong = children.start(
        "pong", role_argv("pong", timeout_s + 5.0, warmup_s, window_s, executor), DOMAIN_PINGPONG
    )
    ping = children.start(
        "ping", role_argv("ping", timeout_s, warmup_s, window_s, executor), DOMAIN_PINGPONG
    )
    result = wait_for(children, ping, [pong], timeout_s + 5.0)
    rate = float(result["round_trips_per_s"])
    cpu = cpu_per_event_ms(
        children, ["ping", "pong"], result["t_start"], result["t_end"], result["round_trips"]
    )
    print(
        f"  window {result['wall_s']:.3f} s, {result['round_trips']} round trips "
        f"({result['resends']} resends before matching)"
    )
    print(f"  round trips/s          {rate:8.1f}")
    print(f"  round-trip time        {1e3 / rate:8.3f} ms")
    print_cpu(cpu, "round trip")
    return {"round_trips_per_s": rate, "window_s": result["wall_s"], "cpu": cpu}


def phase_realtime(
    children: Children,
    rate_hz: int,
    warmup_s: float,
    window_s: float,
    sim_overrides: Sequence[str],
) -> JsonDict:
    """[3] Realtime mode at `rate_hz`: achieved rate, jitter, overruns."""
    timeout_s = STARTUP_TIMEOUT_S + warmup_s + window_s + 10.0
    domain_id = DOMAIN_REALTIME[rate_hz]
    sim = children.start(
        f"simulator_{rate_hz}",
        simulator_argv(
            "timing_mode:=realtime", f"publish_rate_hz:={float(rate_hz)}", *sim_overrides
        ),
        domain_id,
    )
    obs = children.start(
        f"observer_{rate_hz}",
        [*role_argv("observe-realtime", timeout_s, warmup_s, window_s), "--rate-hz", str(rate_hz)],
        domain_id,
    )
    r = wait_for(children, obs, [sim], timeout_s + 5.0)
    a, b = r["a"], r["b"]
    recv, stamp = r["recv_jitter"], r["stamp_jitter"]
    cpu = cpu_per_event_ms(
        children, [sim.name, obs.name], r["t_start"], r["t_end"], max(1, r["messages"] - 1)
    )
    overrun_window = b["overrun_steps"] - a["overrun_steps"] if a and b else None
    published_rate = (
        (b["states_published"] - a["states_published"]) / (b["stamp_s"] - a["stamp_s"])
        if a and b and b["stamp_s"] > a["stamp_s"]
        else None
    )
    print(
        f"  {r['messages']} joint_states in {r['wall_s']:.3f} s: {r['rate_hz']:.1f} Hz received "
        f"({fmt(published_rate)} Hz published per /diagnostics)"
    )
    print(
        f"  receive  |dt - {1e3 / rate_hz:g} ms|: p50 {fmt(recv['p50_ms'], '.3f')} ms, "
        f"p99 {fmt(recv['p99_ms'], '.3f')} ms, max {fmt(recv['max_ms'], '.3f')} ms "
        f"(mean period {fmt(recv['mean_period_ms'], '.3f')} ms)"
    )
    print(
        f"  stamps   |dt - {1e3 / rate_hz:g} ms|: p50 {fmt(stamp['p50_ms'], '.3f')} ms, "
        f"p99 {fmt(stamp['p99_ms'], '.3f')} ms, max {fmt(stamp['max_ms'], '.3f')} ms "
        f"(mean period {fmt(stamp['mean_period_ms'], '.3f')} ms)"
    )
    print(
        f"  simulator /diagnostics: overrun_steps {b['overrun_steps']:.0f} "
        f"({fmt(overrun_window, '.0f')} in the window), realtime_factor "
        f"{fmt(b['realtime_factor'], '.4f')}"
    )
    print_cpu(cpu, "state")
    return {
        "rate_hz": rounded(r["rate_hz"], 2),
        "jitter_p50_ms": rounded(recv["p50_ms"], 4),
        "jitter_p99_ms": rounded(recv["p99_ms"], 4),
        "jitter_max_ms": rounded(recv["max_ms"], 4),
        "stamp_jitter_p50_ms": rounded(stamp["p50_ms"], 4),
        "stamp_jitter_p99_ms": rounded(stamp["p99_ms"], 4),
        "stamp_jitter_max_ms": rounded(stamp["max_ms"], 4),
        "published_rate_hz": rounded(published_rate, 2),
        "messages": r["messages"],
        "stamp_gaps_over_2_periods": r["stamp_gaps_over_2_periods"],
        "overrun_steps": int(b["overrun_steps"]),
        "overrun_steps_in_window": None if overrun_window is None else int(overrun_window),
        "realtime_factor": rounded(b["realtime_factor"], 5),
        "cpu": cpu,
    }


def run_phase(
    title: str, children: Children, errors: dict[str, str], key: str, body: Callable[[], JsonDict]
) -> JsonDict | None:
    """Print the title, run one phase, always end its children; None (and an error) on failure."""
    print(f"\n{title}", flush=True)
    try:
        return body()
    except PhaseError as exc:
        errors[key] = str(exc).splitlines()[0]
        print(f"  FAILED: {exc}")
        return None
    finally:
        children.stop_all()
        sys.stdout.flush()


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line: --window-s, --quick (and the internal --role of the children)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument(
        "--window-s",
        type=positive_float,
        default=None,
        help=f"measurement window per phase, s (default {DEFAULT_WINDOW_S:g}; "
        f"{QUICK_WINDOW_S:g} with --quick)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"short windows ({QUICK_WINDOW_S:g} s) and warm-ups ({QUICK_WARMUP_S:g} s), one pair",
    )
    parser.add_argument(
        "--pairs",
        type=positive_int,
        default=None,
        help="lockstep and ping-pong phases run in turn this many times; the headline ratio is "
        f"the median of the pairs' ratios (default {DEFAULT_PAIRS}; 1 with --quick)",
    )
    parser.add_argument(
        "--rigid-body-period-s",
        type=positive_float,
        default=None,
        help="the simulator's rigid_body_period_s (default: config/ros/simulator.yaml's); "
        "1e-4 evaluates Pinocchio's terms at every 0.1 ms step",
    )
    # Internal: this script as one of its own child processes.
    parser.add_argument(
        "--role",
        choices=("ping", "pong", "observe-lockstep", "observe-realtime"),
        help=argparse.SUPPRESS,
    )
    parser.add_argument("--warmup-s", type=float, default=DEFAULT_WARMUP_S, help=argparse.SUPPRESS)
    parser.add_argument("--timeout-s", type=float, default=60.0, help=argparse.SUPPRESS)
    parser.add_argument("--rate-hz", type=float, default=250.0, help=argparse.SUPPRESS)
    parser.add_argument(
        "--executor", choices=("single", "events"), default="single", help=argparse.SUPPRESS
    )
    return parser.parse_args(argv)


def positive_float(text: str) -> float:
    """Argparse type: a finite number > 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def positive_int(text: str) -> int:
    """Argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def median(values: Sequence[float]) -> float | None:
    """The median of `values`, None for none."""
    return statistics.median(values) if values else None


def _raise_on_sigterm(signum: int, _frame: FrameType | None) -> None:
    raise SystemExit(128 + signum)  # so the finally blocks end the children


def main(argv: Sequence[str] | None = None) -> int:
    """Run the phases, print the figures and end with one JSON line."""
    args = parse_args(argv)
    if args.role:
        return run_role(args.role, args)
    window_s = args.window_s or (QUICK_WINDOW_S if args.quick else DEFAULT_WINDOW_S)
    pairs = args.pairs or (1 if args.quick else DEFAULT_PAIRS)
    sim_overrides: tuple[str, ...] = ()
    if args.rigid_body_period_s is not None:
        sim_overrides = (f"rigid_body_period_s:={args.rigid_body_period_s!r}",)
    warmup_s = QUICK_WARMUP_S if args.quick else DEFAULT_WARMUP_S
    # This process starts no ROS context, but it runs under the same rules as its children.
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(DOMAIN_LOCKSTEP)
    signal.signal(signal.SIGTERM, _raise_on_sigterm)
    for script in ("lca-simulator", "lca-controller"):
        if not (BIN_DIR / script).exists():
            print(
                f"ros_loop: {script} is not installed next to {sys.executable} (pip install -e .)"
            )
            return 1
    print(
        f"ros_loop benchmark: {window_s:g} s windows after {warmup_s:g} s warm-up, "
        f"{os.cpu_count()} CPUs, python {platform.python_version()}, "
        f"{ros_env(0)['RMW_IMPLEMENTATION']}, domains {DOMAIN_LOCKSTEP}.."
        f"{max(DOMAIN_REALTIME.values())} on loopback"
    )
    started_s = time.monotonic()
    errors: dict[str, str] = {}
    pair_results: list[tuple[JsonDict | None, JsonDict | None]] = []
    with tempfile.TemporaryDirectory(prefix="ros_loop_") as tmp:
        children = Children(Path(tmp))
        try:
            # The host's load drifts over a run; measuring the two in turn, several times,
            # keeps a drift from landing on one side of the ratio only.
            for k in range(1, pairs + 1):
                tag = f" (pair {k} of {pairs})" if pairs > 1 else ""
                lockstep = run_phase(
                    "[1] lockstep closed loop: lca-simulator + lca-controller (current "
                    f"commands, {CONTROL_PERIOD_S * 1e3:g} ms period){tag}",
                    children,
                    errors,
                    f"lockstep_{k}",
                    lambda: phase_lockstep(children, warmup_s, window_s, sim_overrides),
                )
                pingpong = run_phase(
                    "[2] bare rclpy ping-pong: JointState -> Float64MultiArray, reliable depth "
                    f"{PINGPONG_QOS_DEPTH}, rclpy's default SingleThreadedExecutor{tag}",
                    children,
                    errors,
                    f"pingpong_{k}",
                    lambda: phase_pingpong(children, warmup_s, window_s, "single"),
                )
                pair_results.append((lockstep, pingpong))
            pingpong_events = run_phase(
                "[2b] the same ping-pong on the events executor the nodes spin",
                children,
                errors,
                "pingpong_events",
                lambda: phase_pingpong(children, warmup_s, window_s, "events"),
            )
            realtime: dict[str, JsonDict | None] = {}
            for rate_hz in REALTIME_RATES_HZ:
                realtime[str(rate_hz)] = run_phase(
                    f"[3] realtime mode at publish_rate_hz {rate_hz} (lca-simulator alone, "
                    "observer on joint_states)",
                    children,
                    errors,
                    f"realtime_{rate_hz}",
                    functools.partial(
                        phase_realtime, children, rate_hz, warmup_s, window_s, sim_overrides
                    ),
                )
        finally:
            children.stop_all()

    pair_figures = [
        {
            "lockstep_steps_per_s": rounded(lo["steps_per_s"], 2) if lo else None,
            "pingpong_round_trips_per_s": rounded(pp["round_trips_per_s"], 2) if pp else None,
            "ratio": rounded(lo["steps_per_s"] / pp["round_trips_per_s"], 4) if lo and pp else None,
        }
        for lo, pp in pair_results
    ]
    lock_rate = median([lo["steps_per_s"] for lo, _ in pair_results if lo])
    ping_rate = median([pp["round_trips_per_s"] for _, pp in pair_results if pp])
    ratio = median([f["ratio"] for f in pair_figures if f["ratio"] is not None])
    met = ratio >= TARGET_RATIO_MIN if ratio is not None else None
    lockstep = next((lo for lo, _ in reversed(pair_results) if lo), None)  # its CPU figures
    pingpong = next((pp for _, pp in reversed(pair_results) if pp), None)
    events_rate = pingpong_events["round_trips_per_s"] if pingpong_events else None
    events_ratio = lock_rate / events_rate if lock_rate is not None and events_rate else None
    print("\nsummary")
    for k, f in enumerate(pair_figures, start=1):
        print(
            f"  pair {k}: lockstep {fmt(f['lockstep_steps_per_s'])} steps/s, ping-pong "
            f"{fmt(f['pingpong_round_trips_per_s'])} round trips/s, ratio {fmt(f['ratio'], '.3f')}"
        )
    print(f"  lockstep steps/s               {fmt(lock_rate)}  (median of the pairs)")
    print(f"  ping-pong round trips/s        {fmt(ping_rate)}  (SingleThreadedExecutor)")
    print(f"  ping-pong round trips/s        {fmt(events_rate)}  (EventsExecutor)")
    print(
        f"  lockstep / ping-pong           {fmt(ratio, '.3f')}  (median of the pairs' ratios; "
        f"target >= {TARGET_RATIO_MIN}: "
        f"{'n/a' if met is None else 'MET' if met else 'NOT MET'})"
    )
    print(f"  lockstep / events ping-pong    {fmt(events_ratio, '.3f')}  (same executor as nodes)")
    for rate_key, figures in realtime.items():
        if figures is None:
            print(f"  realtime {rate_key:>4} Hz: n/a")
            continue
        print(
            f"  realtime {rate_key:>4} Hz: {fmt(figures['rate_hz'])} Hz achieved, receive jitter "
            f"p50 {fmt(figures['jitter_p50_ms'], '.3f')} ms / p99 "
            f"{fmt(figures['jitter_p99_ms'], '.3f')} ms, overrun_steps "
            f"{figures['overrun_steps']}, realtime_factor {fmt(figures['realtime_factor'], '.4f')}"
        )
    print(f"  total run time {time.monotonic() - started_s:.1f} s")

    record: JsonDict = {
        "bench": "ros_loop",
        "lockstep_steps_per_s": rounded(lock_rate, 2),
        "pingpong_round_trips_per_s": rounded(ping_rate, 2),
        "lockstep_to_pingpong_ratio": rounded(ratio, 4),
        "pairs": pair_figures,
        "pingpong_events_round_trips_per_s": rounded(events_rate, 2),
        "lockstep_to_events_pingpong_ratio": rounded(events_ratio, 4),
        "target_ratio_min": TARGET_RATIO_MIN,
        "meets_ratio_target": met,
        "realtime": realtime,
        "jitter": "p50/p99 of |delta t_receive - 1/rate| at a subscriber process; stamp_* from "
        "header stamp deltas",
        "lockstep_model_substeps_per_s": rounded(lockstep["model_substeps_per_s"], 1)
        if lockstep
        else None,
        "lockstep_cpu": lockstep["cpu"] if lockstep else None,
        "pingpong_cpu": pingpong["cpu"] if pingpong else None,
        "pingpong_events_cpu": pingpong_events["cpu"] if pingpong_events else None,
        "control_period_s": CONTROL_PERIOD_S,
        "rigid_body_period_s": args.rigid_body_period_s
        or simulator_yaml_value("rigid_body_period_s"),
        "window_s": window_s,
        "warmup_s": warmup_s,
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "rmw": ros_env(0)["RMW_IMPLEMENTATION"],
        "errors": errors or None,
    }
    from lca_sim.output import strict_json  # here: the roles do not load numpy

    print(strict_json(record, indent=None))  # strict: NaN/inf as null, with why
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
