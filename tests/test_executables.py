"""The console scripts as subprocesses: ROS graph smoke tests, bad parameters, a colcon build.

Every subprocess gets loopback-only DDS and a domain id of its own (100..130). Nothing sleeps a
fixed time: each wait polls a condition with a deadline, either the ROS graph and messages seen
by an observer node spun in this process (own Context, same domain id) or the subprocess output.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node, NodeNameNonExistentError
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from support import ROOT, wait_until

from lca_control import contract as pc
from lca_sim.config.loader import shipped_names

BIN = Path(sys.executable).parent  # the console scripts sit next to the interpreter
SIMULATOR_PARAMS = ROOT / "config" / "ros" / "simulator.yaml"
CONTROLLER_PARAMS = ROOT / "config" / "ros" / "controller.yaml"
CAN_BRIDGE_PARAMS = ROOT / "config" / "ros" / "can_bridge.yaml"
JOINTS = ["l_arm", "pivot", "c_arc", "lift"]
SIM_PUBLISHES = frozenset({"/joint_states", "/motor_states", "/drive_chain_states", "/diagnostics"})
START_TIMEOUT_S = 60.0  # imports (numba, pinocchio) and DDS discovery on a loaded machine
EXIT_TIMEOUT_S = 15.0
COLCON_TIMEOUT_S = 300.0


def ros_env(domain_id: int, **extra: str) -> dict[str, str]:
    """The environment of a subprocess: loopback-only DDS on the given domain."""
    assert 100 <= domain_id <= 130
    env = {k: v for k, v in os.environ.items() if k != "ROS_STATIC_PEERS"}
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain_id), **extra)
    return env


@dataclass
class Running:
    """A started subprocess with its output going to files (no pipe can fill up)."""

    proc: subprocess.Popen[bytes]
    stdout_path: Path
    stderr_path: Path

    def stderr(self) -> str:
        """Everything written to stderr so far."""
        return self.stderr_path.read_text(encoding="utf-8", errors="replace")

    def output(self) -> str:
        """Everything written to stdout and stderr so far."""
        text = self.stdout_path.read_text(encoding="utf-8", errors="replace")
        return text + self.stderr()


@contextmanager
def running(command: Sequence[str], domain_id: int, workdir: Path, label: str) -> Iterator[Running]:
    """Start a subprocess; kill it on the way out if the test left it running."""
    stdout_path = workdir / f"{label}.stdout"
    stderr_path = workdir / f"{label}.stderr"
    with stdout_path.open("wb") as out, stderr_path.open("wb") as err:
        proc = subprocess.Popen(
            list(command), cwd=workdir, env=ros_env(domain_id), stdout=out, stderr=err
        )
        try:
            yield Running(proc, stdout_path, stderr_path)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=EXIT_TIMEOUT_S)


def stop(run: Running, signum: signal.Signals) -> tuple[int, str]:
    """Send `signum`, wait for the exit within the deadline; the exit code and all output."""
    run.proc.send_signal(signum)
    try:
        code = run.proc.wait(timeout=EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        run.proc.kill()
        run.proc.wait(timeout=EXIT_TIMEOUT_S)
        pytest.fail(f"no exit within {EXIT_TIMEOUT_S:g} s of {signum.name}:\n{run.output()}")
    return code, run.output()


@dataclass
class Observer:
    """An in-process node on a subprocess's domain: graph queries and the messages it got."""

    node: Node
    executor: SingleThreadedExecutor
    joint_states: list[JointState] = field(default_factory=list)
    diagnostics: list[DiagnosticArray] = field(default_factory=list)

    def endpoints(self, node_name: str) -> tuple[set[str], set[str]]:
        """The topics `node_name` publishes and subscribes (empty while it is not in the graph)."""
        if node_name not in self.node.get_node_names():
            return set(), set()
        try:
            pubs = self.node.get_publisher_names_and_types_by_node(node_name, "/")
            subs = self.node.get_subscriber_names_and_types_by_node(node_name, "/")
        except NodeNameNonExistentError:
            return set(), set()
        return {name for name, _ in pubs}, {name for name, _ in subs}

    def diagnostic_value(self, status_name: str, key: str) -> str | None:
        """The latest value of `key` in the diagnostic status `status_name`, if one came."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name == status_name:
                    return next((kv.value for kv in status.values if kv.key == key), None)
        return None

    def spin_until(self, done: Callable[[], bool], run: Running, what: str) -> None:
        """Spin until `done()`; fail at the deadline or if the subprocess exits first."""

        def still_running() -> None:
            if run.proc.poll() is not None:
                pytest.fail(f"exited ({run.proc.returncode}) before {what}:\n{run.output()}")

        wait_until(
            done,
            what,
            START_TIMEOUT_S,
            step=lambda: self.executor.spin_once(timeout_sec=0.05),
            check=still_running,
        )


@contextmanager
def observer(domain_id: int) -> Iterator[Observer]:
    """An observer node in a fresh rclpy Context on `domain_id`, torn down afterwards."""
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"  # set by conftest
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = Node("executables_test_observer", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    obs = Observer(node, executor)
    state_qos = QoSProfile(depth=pc.STATE_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(JointState, pc.JOINT_STATES, obs.joint_states.append, state_qos)
    node.create_subscription(DiagnosticArray, pc.DIAGNOSTICS, obs.diagnostics.append, 10)
    try:
        yield obs
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)


@dataclass(frozen=True)
class NodeCase:
    """One long-running node executable and what the graph must show once it is up."""

    exe: str
    args: tuple[str, ...]
    domain_id: int
    node_name: str
    publishes: frozenset[str]
    subscribes: frozenset[str]
    not_published: frozenset[str]
    status_name: str  # its /diagnostics status, and a key/value the parameters decide
    status_key: str
    status_value: str
    signum: signal.Signals = signal.SIGINT


def _simulator(
    exe: str, args: tuple[str, ...], domain_id: int, interface: str, signum: signal.Signals
) -> NodeCase:
    return NodeCase(
        exe=exe,
        args=args,
        domain_id=domain_id,
        node_name="simulator",
        publishes=SIM_PUBLISHES,
        subscribes=frozenset({f"/{interface}_commands"}),
        not_published=frozenset({"/voltage_commands", "/current_commands", "/clock"}),
        status_name="lca_hil/simulator",
        status_key="command_interface",
        status_value=interface,
        signum=signum,
    )


def _controller(exe: str, domain_id: int, interface: str = "current") -> NodeCase:
    # Only with voltage commands does the controller run the current loop, needing motor_states.
    states = {"/joint_states", "/motor_states"} if interface == "voltage" else {"/joint_states"}
    other = "current" if interface == "voltage" else "voltage"
    return NodeCase(
        exe=exe,
        args=(
            "--ros-args",
            "--params-file",
            str(CONTROLLER_PARAMS),
            "-p",
            f"command_interface:={interface}",
        ),
        domain_id=domain_id,
        node_name="controller",
        publishes=frozenset({f"/{interface}_commands", "/diagnostics"}),
        subscribes=frozenset({*states, "/velocity_reference"}),
        not_published=frozenset({f"/{other}_commands"}),
        status_name="lca_hil/controller",
        status_key="reference_source",
        status_value="ramp",
    )


def _can_bridge(exe: str, domain_id: int) -> NodeCase:
    # The shipped params: the virtual rack in the bridge's process, on its own channel here.
    return NodeCase(
        exe=exe,
        args=(
            "--ros-args",
            "--params-file",
            str(CAN_BRIDGE_PARAMS),
            "-p",
            f"channel:=exe_test_{domain_id}",
        ),
        domain_id=domain_id,
        node_name="can_bridge",
        publishes=SIM_PUBLISHES,
        subscribes=frozenset({"/current_commands"}),
        not_published=frozenset({"/voltage_commands", "/current_commands", "/clock"}),
        status_name="lca_hil/can_bridge",
        status_key="interface",
        status_value="virtual",
    )


SIM_PARAMS_ARGS = ("--ros-args", "--params-file", str(SIMULATOR_PARAMS))
NODE_CASES = {
    "lca-simulator-defaults": _simulator("lca-simulator", (), 101, "voltage", signal.SIGINT),
    "lca-simulator-params-file": _simulator(
        "lca-simulator", SIM_PARAMS_ARGS, 102, "current", signal.SIGINT
    ),
    "lca-simulator-sigterm": _simulator("lca-simulator", (), 103, "voltage", signal.SIGTERM),
    "ros2-run-simulator": _simulator("simulator", SIM_PARAMS_ARGS, 104, "current", signal.SIGINT),
    "lca-controller-params-file": _controller("lca-controller", 105),
    "ros2-run-controller": _controller("controller", 106),
    "lca-controller-voltage": _controller("lca-controller", 109, "voltage"),
    "lca-can-bridge": _can_bridge("lca-can-bridge", 116),
    "ros2-run-can-bridge": _can_bridge("can_bridge", 117),
}


@pytest.mark.parametrize("case", NODE_CASES.values(), ids=NODE_CASES.keys())
def test_node_executable_starts_serves_and_stops_cleanly(case: NodeCase, tmp_path: Path) -> None:
    """The node appears with its topics, publishes, and exits 0 on the signal, no traceback."""
    with (
        observer(case.domain_id) as obs,
        running([str(BIN / case.exe), *case.args], case.domain_id, tmp_path, case.exe) as run,
    ):

        def up() -> bool:
            pubs, subs = obs.endpoints(case.node_name)
            return case.publishes <= pubs and case.subscribes <= subs

        obs.spin_until(up, run, f"{case.node_name} with its topics in the graph")
        assert case.node_name in obs.node.get_node_names()
        pubs, _ = obs.endpoints(case.node_name)
        assert not (pubs & case.not_published), pubs
        obs.spin_until(
            lambda: obs.diagnostic_value(case.status_name, case.status_key) is not None,
            run,
            f"a {case.status_name} status on /diagnostics",
        )
        assert obs.diagnostic_value(case.status_name, case.status_key) == case.status_value
        if case.node_name in ("simulator", "can_bridge"):
            obs.spin_until(lambda: bool(obs.joint_states), run, "a joint_states message")
            first = obs.joint_states[0]
            assert list(first.name) == JOINTS
            assert len(first.position) == len(first.velocity) == len(JOINTS)
        code, output = stop(run, case.signum)
    assert code == 0, output
    assert "Traceback" not in output


@pytest.mark.parametrize(
    ("exe", "domain_id"), [("lca-record", 107), ("record", 108)], ids=["lca-record", "record"]
)
def test_record_executable_records_and_stops_cleanly(
    exe: str, domain_id: int, tmp_path: Path
) -> None:
    """The recorder subscribes to the named topic, writes it and closes the bag on SIGINT."""
    bag = tmp_path / "bag"
    with observer(domain_id) as obs:
        probe = obs.node.create_publisher(String, "exe_probe", 10)
        command = [str(BIN / exe), "exe_probe", "-o", str(bag), "--wait-s", "30", "-v"]
        with running(command, domain_id, tmp_path, exe) as run:
            obs.spin_until(
                lambda: (
                    "lca_record" in obs.node.get_node_names()
                    and probe.get_subscription_count() >= 1
                ),
                run,
                "lca_record subscribed to /exe_probe",
            )

            def recorded() -> bool:
                probe.publish(String(data="probe"))
                counts = re.findall(r"/exe_probe (\d+)", run.stderr())
                return bool(counts) and int(counts[-1]) > 0

            obs.spin_until(recorded, run, "a progress line with /exe_probe messages")
            code, output = stop(run, signal.SIGINT)
    assert code == 0, output
    assert "Traceback" not in output
    assert "lca-record: stopped (SIGINT)" in output
    summary = re.search(r"^\s+/exe_probe\s+(\d+)$", output, re.MULTILINE)
    assert summary is not None, output
    assert int(summary.group(1)) > 0
    assert (bag / "metadata.yaml").is_file()
    assert list(bag.glob("*.mcap"))


@pytest.mark.parametrize(
    ("override", "domain_id", "named"),
    [
        ("timing_mode:=sideways", 110, ["timing_mode"]),
        ("robot:=nope", 111, ["nope", *shipped_names("robots")]),
    ],
    ids=["timing_mode", "robot"],
)
def test_simulator_bad_parameter_is_one_error_line_and_exit_2(
    override: str, domain_id: int, named: list[str], tmp_path: Path
) -> None:
    """A bad parameter value: exit 2 and one `lca-simulator: error:` line naming the problem."""
    error = one_error_line_and_exit_2(
        ["lca-simulator", "--ros-args", "-p", override], domain_id, tmp_path
    )
    for word in named:
        assert word in error


def one_error_line_and_exit_2(command: list[str], domain_id: int, cwd: Path) -> str:
    """Run a console script that must fail at start: exit 2, no traceback, one error line."""
    prog = command[0]
    proc = subprocess.run(
        [str(BIN / prog), *command[1:]],
        cwd=cwd,
        env=ros_env(domain_id),
        capture_output=True,
        text=True,
        timeout=START_TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith(f"{prog}: ")]
    assert len(errors) == 1, proc.stderr
    assert errors[0].startswith(f"{prog}: error:")
    return errors[0]


# SIGTERM while the node is still being built (rclpy.init done, run_node's own handlers not yet
# installed): rclpy's SIGTERM handler shuts the context down without raising, the construction
# goes on and fails on the dead context. The real start-up takes seconds (numba, pinocchio), so
# a `kill`/`docker stop`/launch shutdown in that window hits it; the subclass makes it certain.
_SIGNAL_DURING_BUILD = """
import os, signal, sys, time
import rclpy
from lca_sim.ros.simulator_node import SimulatorNode
from lca_sim.ros.node_util import run_node

class SignalledWhileBuilding(SimulatorNode):
    def __init__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        deadline = time.monotonic() + 10.0
        while rclpy.ok() and time.monotonic() < deadline:
            time.sleep(0.01)
        super().__init__()

sys.exit(run_node("lca-simulator", SignalledWhileBuilding, sys.argv))
"""


def test_simulator_sigterm_during_startup_exits_0(tmp_path: Path) -> None:
    """SIGTERM before the node is built still ends the process cleanly (exit 0, no traceback)."""
    proc = subprocess.run(
        [sys.executable, "-c", _SIGNAL_DURING_BUILD],
        cwd=tmp_path,
        env=ros_env(112),
        capture_output=True,
        text=True,
        timeout=START_TIMEOUT_S,
        check=False,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 0, proc.stderr


def _tracked_files() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    return [name for name in listed if (ROOT / name).is_file()]


def test_colcon_build_installs_the_ros_package(tmp_path: Path) -> None:
    """`colcon build` of the tracked tree installs the ros2-run executables and share files."""
    colcon = BIN / "colcon"
    if not colcon.is_file():
        pytest.skip(f"no colcon next to {sys.executable}")
    ws = tmp_path / "ws"
    source = ws / "src" / "lca_hil"
    for name in _tracked_files():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    env = ros_env(115, COLCON_HOME=str(tmp_path / "colcon_home"))
    env["PATH"] = os.pathsep.join([str(BIN), env.get("PATH", "")])
    build = subprocess.run(
        [str(colcon), "build", "--base-paths", "src", "--build-base", str(ws / "build"),
         "--install-base", str(ws / "install"), "--event-handlers", "console_direct-"],
        cwd=ws, env=env, capture_output=True, text=True, timeout=COLCON_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout + build.stderr

    prefix = ws / "install" / "lca_hil"
    for exe in ("simulator", "controller", "record", "lca-simulator", "lca-controller", "lca-sim"):
        path = prefix / "lib" / "lca_hil" / exe
        assert path.is_file(), exe
        assert os.access(path, os.X_OK), exe
    share = prefix / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "lca_hil").is_file()
    assert (share / "lca_hil" / "package.xml").is_file()
    assert (share / "lca_hil" / "config" / "robots" / "default.yaml").is_file()

    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}"
    site /= "site-packages"
    assert (site / "lca_sim" / "__init__.py").is_file()
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(site), env.get("PYTHONPATH")]))
    where = subprocess.run(
        [sys.executable, "-c", "import lca_sim; print(lca_sim.__file__)"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60, check=True,
    )  # fmt: skip
    assert where.stdout.strip().startswith(str(site)), where.stdout  # the installed copy
    helped = subprocess.run(
        [str(prefix / "lib" / "lca_hil" / "lca-sim"), "--help"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert helped.returncode == 0, helped.stderr
    assert helped.stdout.startswith("usage: lca-sim")


@pytest.mark.parametrize(
    ("command", "domain_id"),
    [
        (["lca-can-bridge", "--ros-args", "-p", "interface:=socketcan", "-p", "channel:=nope0"],
         118),
        (["lca-virtual-drive", "--interface", "socketcan", "--channel", "nope0"], 119),
    ],
    ids=["can_bridge", "virtual_drive"],
)  # fmt: skip
def test_missing_socketcan_interface_is_one_error_line_and_exit_2(
    command: list[str], domain_id: int, tmp_path: Path
) -> None:
    """A SocketCAN interface that does not exist: a clear error naming it, no traceback."""
    error = one_error_line_and_exit_2(command, domain_id, tmp_path)
    assert "socketcan" in error and "nope0" in error
