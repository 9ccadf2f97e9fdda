"""Shared test support: repository paths, the one polling helper, and what several modules use.

tests/ is on sys.path through its conftest, so every test module imports this as `support`.
ROS 2 is imported only inside the helpers that need it, so modules without ROS import this too.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import can
import canopen
import pytest

from lca_control.contract import JOINT_STATE_TYPE, JOINT_STATES

if TYPE_CHECKING:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.context import Context
    from rclpy.executors import Executor, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from lca_sim.canbus.master import Cia402Master
    from lca_sim.canbus.master_params import BridgeParams
    from lca_sim.canbus.virtual_rack import VirtualDriveRack
    from lca_sim.model.params import RobotParams
    from lca_sim.ros.simulator_node import SimulatorNode

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"
BIN = Path(sys.executable).parent  # the console scripts sit next to the interpreter


def wait_until(
    condition: Callable[[], bool],
    what: str,
    timeout_s: float = 30.0,
    *,
    step: Callable[[], object] | None = None,
    check: Callable[[], None] | None = None,
) -> None:
    """Poll `condition()` until it holds; fail naming `what` after `timeout_s`.

    The one polling helper of the tests: no test sleeps a fixed time or waits without a
    deadline.

    Args:
        condition: what to wait for.
        what: said in the failure.
        timeout_s: the deadline, s (generous: the machines are shared 2-core ones).
        step: run between polls, e.g. one spin of an executor; default a 2 ms pause.
        check: run before each poll; it may fail the test early (a subprocess that exited).
    """
    deadline_s = time.monotonic() + timeout_s
    while True:
        if check is not None:
            check()
        if condition():
            return
        if time.monotonic() > deadline_s:
            pytest.fail(f"not within {timeout_s:g} s: {what}")
        if step is None:
            time.sleep(0.002)
        else:
            step()


def hold_stopped(
    proc: subprocess.Popen[Any], seconds: float, step: Callable[[], object] | None = None
) -> None:
    """SIGSTOP `proc` and keep it stopped for `seconds`, polling `step` meanwhile (not a sleep).

    The stimulus of a stall: the process gets no CPU at all, as on a paused host, under a
    debugger or a long swap-in. The caller sends SIGCONT once it has noted what it needs.
    """
    proc.send_signal(signal.SIGSTOP)
    stopped_at = time.monotonic()
    wait_until(
        lambda: time.monotonic() - stopped_at >= seconds,
        f"{seconds:g} s with the process stopped",
        seconds + 30.0,
        step=step,
    )


class ManualClock:
    """A `time.monotonic` stand-in, moved by hand (`now_s`), for monkeypatching."""

    def __init__(self, now_s: float) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        """The time set by hand."""
        return self.now_s


def spin_until(
    executor: Executor,
    condition: Callable[[], bool],
    what: str = "condition",
    timeout_s: float = 30.0,
) -> None:
    """Spin `executor` until `condition()` holds; fail naming `what` after `timeout_s`."""
    wait_until(condition, what, timeout_s, step=lambda: executor.spin_once(timeout_sec=0.05))


@contextmanager
def ros_context_on(domain_id: int) -> Iterator[tuple[Context, SingleThreadedExecutor]]:
    """A fresh rclpy Context and executor on `domain_id` (loopback only: conftest), torn down."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=ctx)
    try:
        yield ctx, executor
    finally:
        executor.shutdown()
        rclpy.shutdown(context=ctx)


def domain_contexts(
    first_domain_id: int, span: int
) -> Callable[[], AbstractContextManager[tuple[Context, SingleThreadedExecutor]]]:
    """A `ros_context()` for one test module, on its own range of domain ids.

    Each call gives a fresh rclpy Context and executor (`ros_context_on`) on the next domain id
    of `first_domain_id .. first_domain_id + span - 1`, torn down afterwards. Each module takes
    its own range, so modules that run one after another never see each
    other's late DDS traffic.
    """
    domains = itertools.count()

    def ros_context() -> AbstractContextManager[tuple[Context, SingleThreadedExecutor]]:
        return ros_context_on(first_domain_id + next(domains) % span)

    return ros_context


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """The environment of a ROS 2 subprocess: loopback-only DDS, on `domain_id` if given."""
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    return env


def run_command(
    argv: list[str], *, domain_id: int | None = None, timeout_s: float = 300.0, cwd: Path = ROOT
) -> subprocess.CompletedProcess[str]:
    """Run a command to its end (`timeout_s` its deadline) in `ros_env`; its output."""
    return subprocess.run(
        argv,
        cwd=cwd,
        env=ros_env(domain_id),
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


def run_tool(
    script: str, *args: str, domain_id: int | None = None, timeout_s: float = 300.0
) -> subprocess.CompletedProcess[str]:
    """Run an installed console script to its end (`run_command`); its output."""
    return run_command([str(BIN / script), *args], domain_id=domain_id, timeout_s=timeout_s)


def _refuse_constant(name: str) -> float:
    """parse_constant for json.loads: NaN, Infinity and -Infinity are not JSON."""
    raise ValueError(f"not strict JSON: {name}")


def strict_loads(text: str) -> object:
    """json.loads that fails on the non-standard NaN / Infinity tokens."""
    return json.loads(text, parse_constant=_refuse_constant)


# --- lca-record: numbered joint states ------------------------------------------------------

RECORDED_TOPIC = f"/{JOINT_STATES}"


def numbered_joint_state(seq: int) -> Any:
    """A JointState whose stamp carries the sequence number `seq`."""
    from sensor_msgs.msg import JointState

    msg = JointState()
    msg.header.stamp.nanosec = seq
    msg.name = ["l_arm", "pivot", "c_arc", "lift"]
    msg.position = [float(seq), 0.5, -0.25, 0.1]
    msg.velocity = [0.0, 1.0, 0.0, 0.0]
    msg.effort = [0.0, 2.0, 0.0, 0.0]
    return msg


def recorded_sequences(bag: Path) -> list[int]:
    """The sequence numbers of the bag's /joint_states (`numbered_joint_state`), via rosbags."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == RECORDED_TOPIC]
        assert [c.msgtype for c in conns] == [JOINT_STATE_TYPE]
        msgs: list[Any] = [
            typestore.deserialize_cdr(raw, JOINT_STATE_TYPE)
            for _, _, raw in reader.messages(connections=conns)
        ]
    return [int(msg.header.stamp.nanosec) for msg in msgs]


# --- lca-hil identify: a record into an end stop ---------------------------------------------

# From -69 deg the pivot runs down at -30 V into its lower end stop (-2 rad), is pushed against
# it for 2 s, then driven back up. Just before the impact the load's torque falls and the pivot
# passes through the reverse motor-dominant state (eta_l = 0.06): 186 samples, the last ones
# within the differentiator's window of the impact.
INTO_END_STOP: dict[str, Any] = {
    "duration_s": 7.5,
    "dt_s": 1.0e-4,
    "record_period_s": 0.001,
    "initial": {"position": {"pivot": -1.2}},
    "inputs": {
        "pivot": {
            "time_s": [0.0, 0.2, 0.7, 4.0, 4.5, 7.0, 7.5],
            "voltage_v": [0.0, 0.0, -30.0, -30.0, 30.0, 30.0, 0.0],
        }
    },
}


# --- nodes in-process ------------------------------------------------------------------------

CONTROLLER_STATUS = "lca_hil/controller"

# A lockstep simulator paced by one controller on current commands, the pivot at 35 deg under
# load, quick to notice a missing peer: the runs in which a peer goes away or restarts.
LOCKSTEP_SIMULATOR: dict[str, Any] = {
    "timing_mode": "lockstep",
    "command_interface": "current",
    "initial_position": [0.0, math.radians(35.0), 0.0, 0.0],
    "lockstep_subscribers": 1,  # the controller
    "lockstep_resend_s": 0.3,
    "diagnostics_period_s": 0.2,
}


def parameters(**values: Any) -> list[Parameter]:
    """Parameter overrides of a node, one per keyword."""
    from rclpy.parameter import Parameter

    # rclpy leaves Parameter's constructor unannotated
    return [Parameter(name, value=value) for name, value in values.items()]  # type: ignore[no-untyped-call]


def start_simulator(
    ctx: Context,
    executor: SingleThreadedExecutor,
    base: Mapping[str, Any],
    name: str = "simulator",
    **overrides: Any,
) -> SimulatorNode:
    """A simulator node on `ctx` with `base` and then `overrides` as parameters, in `executor`."""
    from lca_sim.ros.simulator_node import SimulatorNode

    sim = SimulatorNode(name, context=ctx, parameter_overrides=parameters(**{**base, **overrides}))
    executor.add_node(sim)
    return sim


def kill(executor: SingleThreadedExecutor, node: Node) -> None:
    """A node "killed": out of the executor and destroyed (its peers see it gone)."""
    executor.remove_node(node)
    node.destroy_node()  # type: ignore[no-untyped-call]  # rclpy leaves it unannotated


class Diagnostics:
    """The latest /diagnostics status of each name, seen from a node of the test."""

    def __init__(self, ctx: Context, executor: SingleThreadedExecutor) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node

        self.node = Node("test_diagnostics", context=ctx)
        self.latest: dict[str, DiagnosticStatus] = {}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_array, 50)
        self.executor = executor
        executor.add_node(self.node)

    def _on_array(self, msg: DiagnosticArray) -> None:
        for item in msg.status:
            self.latest[item.name] = item

    def clear(self) -> None:
        """Forget what was seen, so a wait sees only reports from now on."""
        self.latest.clear()

    def shows(self, name: str, level: bytes, text: str) -> bool:
        """Whether the latest status of `name` has this level and its message contains `text`."""
        item = self.latest.get(name)
        return item is not None and item.level == level and text in item.message

    def wait_for(
        self, name: str, level: bytes, text: str, timeout_s: float = 30.0
    ) -> DiagnosticStatus:
        """Spin until the latest status of `name` `shows` `level` and `text`; that status."""
        what = f"{name} at level {ord(level)} with {text!r} in its message"
        spin_until(self.executor, lambda: self.shows(name, level, text), what, timeout_s)
        return self.latest[name]

    def value(self, name: str, key: str) -> str:
        """A value of the latest status of `name`."""
        values: dict[str, str] = {kv.key: kv.value for kv in self.latest[name].values}
        return values[key]


@dataclass
class NodeProcess:
    """A node's console script with its shipped params file, its output in `log`."""

    name: str
    proc: subprocess.Popen[bytes]
    log: Path

    def check_alive(self) -> None:
        """Fail with its log's tail if it exited."""
        if self.proc.poll() is not None:
            tail = self.log.read_text(encoding="utf-8", errors="replace")[-2000:]
            raise AssertionError(f"{self.name} exited {self.proc.returncode}: {tail}")

    def stop(self) -> int:
        """SIGINT as Ctrl-C would, then its exit code (killed after a bounded wait)."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
        try:
            return self.proc.wait(20.0)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            return self.proc.wait(20.0)


def start_shipped(
    script: str, params: str, domain_id: int, out: Path, *, unset: Sequence[str] = ()
) -> NodeProcess:
    """`script --ros-args --params-file config/ros/<params>` in its own session.

    `unset`: environment variables of this process the node does not get.
    """
    log = out / f"{script}.log"
    argv = [str(BIN / script), "--ros-args", "--params-file", str(CONFIG / "ros" / params)]
    env = {k: v for k, v in ros_env(domain_id).items() if k not in unset}
    proc = subprocess.Popen(
        argv,
        cwd=ROOT,
        env={**env, "PYTHONUNBUFFERED": "1"},
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    return NodeProcess(script, proc, log)


# --- CAN rigs: the shipped rack's drives, a frame probe, the bridge's parameters ---------------

CAN_JOINTS = ("l_arm", "pivot", "c_arc", "lift")
CAN_NODE_IDS = (1, 2, 3, 4)  # the shipped config/can/rack.yaml
# The bridge's watchdogs with room for a shared 2-core machine's stalls (a CI run saw a 0.3 s
# one): the drive-side watchdogs are not what most tests are about, and the tests of the
# watchdogs themselves still see them fire within their deadlines.
ROOMY_WATCHDOGS: Mapping[str, Any] = MappingProxyType(
    {"rpdo_deadline_ms": 500, "heartbeat_consumer_ms": 1000, "stale_timeout_s": 0.5}
)


def bridge_params(robot: RobotParams | None = None, **overrides: Any) -> BridgeParams:
    """The bridge's parameters for the shipped rack at 250 Hz, roomy watchdogs; `overrides` win.

    Args:
        robot: the robot whose motors and gears the drives have; None: the shipped default.
        overrides: BridgeParams fields to set otherwise.
    """
    from lca_sim.canbus.master_params import BridgeParams
    from lca_sim.config.loader import load_robot

    robot = load_robot("default") if robot is None else robot
    axes = {a.name: a for a in robot.axes}
    values: dict[str, Any] = {
        "joints": CAN_JOINTS,
        "node_ids": CAN_NODE_IDS,
        "torque_constants_nm_per_a": tuple(
            axes[j].motor.torque_constant_nm_per_a for j in CAN_JOINTS
        ),
        "gear_ratios": tuple(axes[j].gear_ratio for j in CAN_JOINTS),
        "drive_state_names": robot.state_machine.state_names,
        "cycle_hz": 250.0,
        **ROOMY_WATCHDOGS,
    }
    values.update(overrides)
    return BridgeParams(**values)


class Probe:
    """A raw bus on a virtual channel that records every frame and sends raw frames."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._notifier = can.Notifier(self.bus, [self._record], timeout=0.05)

    def _record(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append(msg)

    def mark(self) -> int:
        """The position of the next frame to arrive (for `wait` and `seen`)."""
        with self._lock:
            return len(self.frames)

    def seen(self, cob_id: int, since: int = 0) -> list[bytes]:
        """Data of the frames with this COB-ID received since `since`."""
        with self._lock:
            return [bytes(m.data) for m in self.frames[since:] if m.arbitration_id == cob_id]

    def wait(self, cob_id: int, since: int = 0, timeout_s: float = 5.0) -> bytes:
        """Wait for a frame with this COB-ID after `since`; return its data."""
        wait_until(lambda: bool(self.seen(cob_id, since)), f"a frame 0x{cob_id:03X}", timeout_s)
        return self.seen(cob_id, since)[0]

    def send(self, cob_id: int, data: bytes = b"") -> None:
        """Send one standard frame."""
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def close(self) -> None:
        """Stop recording and close the bus."""
        self._notifier.stop()
        self.bus.shutdown()


@dataclass
class RackAndMaster:
    """The shipped rack and the bridge's master (built, not initialised) on one channel."""

    channel: str
    rack: VirtualDriveRack
    network: canopen.Network
    bridge: Cia402Master

    def enable_all(self, timeout_s: float = 10.0) -> None:
        """Ask the master to enable; wait until every drive reports OPERATION ENABLED."""
        from lca_sim.cia402.device import PowerState

        assert self.bridge.enable(True) == "enabling"
        wait_until(
            lambda: all(
                self.bridge.axis_state(j).power_state is PowerState.OPERATION_ENABLED
                for j in self.bridge.joints
            ),
            "every drive enabled",
            timeout_s,
        )


def remote_node(network: canopen.Network, node_id: int) -> canopen.RemoteNode:
    """A remote node of a canopen master, with the drive's EDS and a patient SDO client."""
    node = canopen.RemoteNode(node_id, str(CONFIG / "can" / "lca_drive.eds"))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    return node


def rack_sync(rack: VirtualDriveRack, probe: Probe, count: int = 1) -> None:
    """Send `count` SYNCs and wait until the rack has processed them all."""
    done = rack.counters.syncs + count
    for _ in range(count):
        probe.send(0x080)
    wait_until(lambda: rack.counters.syncs >= done, f"{count} SYNC(s) processed")


def rack_nmt(rack: VirtualDriveRack, probe: Probe, command: int, node_id: int, state: str) -> None:
    """Send an NMT command and wait for the node's NMT state."""
    probe.send(0x000, bytes([command, node_id]))
    name = dict(zip(CAN_NODE_IDS, CAN_JOINTS, strict=True))[node_id]
    wait_until(lambda: rack.nmt_state(name) == state, f"node {node_id} in {state}")


def sdo_enable(node: canopen.RemoteNode) -> None:
    """Walk a drive to OPERATION ENABLED over SDO."""
    for controlword in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = controlword
    assert node.sdo[0x6041].raw & 0x6F == 0x27


def emcy_code(data: bytes) -> tuple[int, int]:
    """(error code, error register) of an EMCY frame."""
    code, register = struct.unpack_from("<HB", data)
    return code, register


def assert_lockstep_plant_clean(node: Any) -> None:
    """A lockstep plant node after its run: nothing latched, late or refused.

    The bridge: no latch, no late and no refused command; the simulator: no refused command.
    """
    from lca_sim.ros.can_bridge_node import CanBridgeNode
    from lca_sim.ros.simulator_node import SimulatorNode

    if isinstance(node, CanBridgeNode):
        assert node.bridge.latched_reason() == ""
        assert node.bridge.counters.commands_late == 0
        assert node.bridge.counters.commands_rejected == 0
    else:
        assert isinstance(node, SimulatorNode)
        assert node.plant.counters.rejected == 0
