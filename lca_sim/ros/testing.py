"""A pytest plugin for testing against the simulated robot: a lockstep closed loop per module.

Load it in your own tests (it is not registered as an entry point, so it never loads into other
pytest runs) with, in the test module or the root conftest.py::

    pytest_plugins = ["lca_sim.ros.testing"]

    def test_two_seconds_of_the_ramp(lca_hil_loop):
        lca_hil_loop.step(500)  # 2 s of simulated time, the controller in the loop
        assert lca_hil_loop.simulator.sim_time_s == pytest.approx(2.0)

`lca_hil_loop` starts a lockstep simulator in this process and a controller (`lca-controller`,
a child process) on their own ROS domain id once per test module, and resets them before each
test (paused at simulated time 0, the first command waiting). docs/simulation-control.md
("The pytest fixture") has the fixtures to override, the helpers and the services behind them.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from lca_sim.ros.dds_profile import use_shipped_profile
from lca_sim.ros.simulator_node import SimulatorNode

# A test harness stays on this machine unless told otherwise (read when a context starts).
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

DEFAULT_DOMAIN_ID = 42
SIMULATOR_DEFAULTS: dict[str, Any] = {
    "timing_mode": "lockstep",
    "command_interface": "current",
    "initial_position": [0.0, 0.6109, 0.0, 0.0],  # the pivot at 35 deg under load
    "lockstep_subscribers": 1,  # the controller
}
CONTROLLER_DEFAULTS: dict[str, Any] = {
    "reference_source": "ramp",
    "command_interface": "current",
    "use_sim_time": True,
}


def _ros_arg(value: Any) -> str:
    """A parameter value as `--ros-args -p name:=value` takes it (YAML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _parameters(values: Mapping[str, Any]) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]  # type: ignore[no-untyped-call]


class HilLoop:
    """A simulator and a controller in one executor, with helpers for a test.

    Attributes:
        context: the rclpy Context of both nodes (and of the helper node).
        executor: spins all three; the helpers spin it, a test needs not.
        simulator: the `SimulatorNode` (its plant: `simulator.sim`).
        controller: the controller's process (`lca-controller`).
        node: a helper node of the test, to add subscriptions or clients to.
    """

    def __init__(
        self,
        context: Context,
        domain_id: int,
        simulator_parameters: Mapping[str, Any],
        controller_parameters: Mapping[str, Any],
    ) -> None:
        self.context = context
        self.executor = SingleThreadedExecutor(context=context)
        self.simulator = SimulatorNode(
            context=context, parameter_overrides=_parameters(simulator_parameters)
        )
        self.node = Node("lca_hil_test", context=context)
        for node in (self.simulator, self.node):
            self.executor.add_node(node)
        self._clients = {
            name: self.node.create_client(Trigger, f"/{self.simulator.get_name()}/{name}")
            for name in ("pause", "resume", "step", "reset")
        }
        self.wait_for(
            lambda: all(c.service_is_ready() for c in self._clients.values()),
            "the simulator's services",
        )
        args = [f"{name}:={_ros_arg(value)}" for name, value in controller_parameters.items()]
        self.controller = subprocess.Popen(  # ended by close()
            [sys.executable, "-m", "lca_sim.ros.controller_node", "--ros-args"]
            + [item for arg in args for item in ("-p", arg)],
            env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
        )

    # --- waiting ---------------------------------------------------------------------------

    def wait_for(
        self, condition: Callable[[], bool], what: str = "condition", timeout_s: float = 60.0
    ) -> None:
        """Spin the nodes until `condition()` holds; fail the test naming `what` at the deadline.

        Args:
            condition: checked between spins.
            what: said in the failure.
            timeout_s: the deadline on the wall clock, s.
        """
        deadline_s = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline_s:
                pytest.fail(f"not within {timeout_s:g} s: {what}")
            code = self.controller.poll() if hasattr(self, "controller") else None
            if code is not None:
                pytest.fail(f"the controller exited ({code}) while waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def _settled(self) -> bool:
        """Paused, the controller's answer to the last state is in: none is on its way.

        In lockstep every state with a new stamp gets one command, and a running simulator
        publishes a new state for each command; so once paused, the answer to the last one is
        the only command still to come.
        """
        sim = self.simulator
        return sim.command_pending or sim.ended or not sim.lockstep_started

    # --- the simulator's services ----------------------------------------------------------

    def call(self, service: str) -> tuple[bool, str]:
        """Call one of the simulator's Trigger services (pause, resume, step, reset).

        Returns:
            The reply's success and message.
        """
        future = self._clients[service].call_async(Trigger.Request())
        self.wait_for(future.done, f"the reply of ~/{service}")
        reply = future.result()  # type: ignore[no-untyped-call]  # rclpy leaves it unannotated
        assert reply is not None
        return bool(reply.success), str(reply.message)

    def _call_ok(self, service: str) -> str:
        success, message = self.call(service)
        assert success, f"~/{service} refused: {message}"
        return message

    def pause(self) -> None:
        """Stop simulated time (`~/pause`) and let the controller's last command arrive."""
        self._call_ok("pause")
        self.wait_for(self._settled, "the controller's commands delivered")

    def resume(self) -> None:
        """Let the loop run free (`~/resume`)."""
        self._call_ok("resume")

    def step(self, periods: int = 1, timeout_s: float = 60.0) -> None:
        """Run exactly `periods` control periods of the closed loop (paused before and after).

        Sets the simulator's `step_periods`, calls `~/step` and waits until the periods have run
        and the controller has answered the last state.
        """
        sim = self.simulator
        self.set_parameters(sim, step_periods=periods)
        target = sim.steps + periods * sim.params.substeps_per_period
        end = sim.params.lockstep_end_steps
        if end is not None:
            target = min(target, end)
        self._call_ok("step")
        self.wait_for(
            lambda: sim.steps >= target and (sim.ended or sim.command_pending),
            f"{periods} control periods",
            timeout_s,
        )

    def reset(self) -> None:
        """Both nodes back to the start: paused at simulated time 0, the first command waiting.

        The simulator goes back to `initial_position` and time 0; the controller sees its
        plant's time go back and restarts its loops and reference. A run after it repeats a
        run after start-up bit for bit.
        """
        sim = self.simulator
        self.pause()
        self._call_ok("reset")
        self.wait_for(lambda: sim.command_pending, "the controller's first command")

    # --- parameters ------------------------------------------------------------------------

    def set_parameters(self, node: Node, *, check: bool = True, **values: Any) -> str:
        """Set parameters of `node` as one set; it takes effect or is refused as a whole.

        Args:
            node: `simulator`, `controller` or another node of the test.
            check: fail the test if the set is refused (else return the reason).
            values: parameter names and values.

        Returns:
            "" if the set took effect, else the node's reason for refusing it.
        """
        result = node.set_parameters_atomically(_parameters(values))
        if check:
            assert result.successful, f"{node.get_name()} refused {values}: {result.reason}"
        return "" if result.successful else str(result.reason)

    def inject(self, node: Node, **values: Any) -> str:
        """Switch something on or off in a running loop: parameters of the node that owns it.

        A fault is a parameter of the node that owns it (`faults.<joint>.<kind>`,
        `faults.link.<kind>` on the simulator; docs/faults.md), so injecting one is a live set
        on that node, refused with the reason if the value is not one it takes:
        `inject(loop.simulator, **{"faults.pivot.jam": True})`. Any other live parameter goes
        through it too (`enabled`, gains, limits). Returns "" or the reason (no check).
        """
        return self.set_parameters(node, check=False, **values)

    def close(self) -> None:
        """Stop the controller; destroy the nodes and the executor (the context is the caller's)."""
        self.controller.terminate()
        try:
            self.controller.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self.controller.kill()
            self.controller.wait()
        self.executor.shutdown()
        for node in (self.node, self.simulator):
            node.destroy_node()  # type: ignore[no-untyped-call]


@pytest.fixture(scope="module")
def lca_hil_domain_id() -> int:
    """The ROS domain id of the loop: `LCA_HIL_DOMAIN_ID`, else `DEFAULT_DOMAIN_ID`."""
    return int(os.environ.get("LCA_HIL_DOMAIN_ID", DEFAULT_DOMAIN_ID))


@pytest.fixture(scope="module")
def lca_hil_simulator_parameters() -> dict[str, Any]:
    """The simulator's parameters (`SIMULATOR_DEFAULTS`: lockstep, current commands)."""
    return dict(SIMULATOR_DEFAULTS)


@pytest.fixture(scope="module")
def lca_hil_controller_parameters() -> dict[str, Any]:
    """The controller's parameters (`CONTROLLER_DEFAULTS`: the ramp of Fig. 15)."""
    return dict(CONTROLLER_DEFAULTS)


@pytest.fixture(scope="module")
def lca_hil_running_loop(
    lca_hil_domain_id: int,
    lca_hil_simulator_parameters: dict[str, Any],
    lca_hil_controller_parameters: dict[str, Any],
) -> Iterator[HilLoop]:
    """The loop of a test module, started once and torn down after the module."""
    use_shipped_profile()
    context = Context()
    rclpy.init(context=context, domain_id=lca_hil_domain_id)
    loop: HilLoop | None = None
    try:
        loop = HilLoop(
            context, lca_hil_domain_id, lca_hil_simulator_parameters, lca_hil_controller_parameters
        )
        yield loop
    finally:
        if loop is not None:
            loop.close()
        rclpy.shutdown(context=context)


@pytest.fixture
def lca_hil_loop(lca_hil_running_loop: HilLoop) -> HilLoop:
    """The module's loop, reset: paused at simulated time 0, the controller's first command in.

    The simulator's parameters a test changed stay changed (set them back, or set them in
    `lca_hil_simulator_parameters`); the plant, its time and the controller start afresh.
    """
    loop = lca_hil_running_loop
    loop.reset()
    return loop
