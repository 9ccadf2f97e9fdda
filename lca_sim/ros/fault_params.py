"""Fault injection on a plant node: the `faults.<joint>.<kind>` parameters and the schedule.

Every fault kind of `lca_sim.model.faults` is a live parameter of the simulator node,
`faults.<joint>.<kind>` (`faults.link.<kind>` for the state link), off by default: a set takes
effect from the next model step or is refused with the reason. `fault_schedule` (read-only)
names a YAML file of timed entries (docs/faults.md), switched at simulated time. Active faults
show on /diagnostics (the joint's status goes WARN with them listed, ERROR for a trip) and in
`drive_chain_states` (the `faults` key), so a recorded bag keeps when each was on.
"""

from __future__ import annotations

from collections.abc import Sequence

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from lca_control.parameters import ParameterError, ParameterTable, ParamKind, ParamSpec
from lca_sim.config.loader import load_fault_schedule
from lca_sim.errors import USER_ERRORS
from lca_sim.model.fault_schedule import ScheduledFault
from lca_sim.model.faults import (
    FAULT_SCHEDULE,
    LINK,
    FaultInjector,
    fault_table,
    is_fault_parameter,
    parameter_name,
    split_name,
)
from lca_sim.ros.node_util import accepted, declare_table, rejected

DELAY = parameter_name(LINK, "state_delay_s")


__all__ = ["FAULT_SCHEDULE", "FaultParameters", "is_fault_parameter", "node_fault_table"]


def node_fault_table(joints: Sequence[str]) -> ParameterTable:
    """The fault parameters of a node with these joints, with `fault_schedule`."""
    schedule = ParamSpec(
        FAULT_SCHEDULE,
        ParamKind.STRING,
        "",
        "YAML file of timed faults (docs/faults.md): entries joint, kind, value, start_s, "
        "end_s in simulated time; empty: none",
        live=False,
    )
    return ParameterTable((*fault_table(joints), schedule))


class FaultParameters:
    """Declares a node's fault parameters and applies every set of them to `injector`."""

    def __init__(self, node: Node, injector: FaultInjector, *, lockstep: bool = False) -> None:
        self._node = node
        self.injector = injector
        self._lockstep = lockstep
        self.table = node_fault_table(injector.joints)
        values = declare_table(node, self.table)
        path = str(values.pop(FAULT_SCHEDULE))
        self.schedule: tuple[ScheduledFault, ...] = load_fault_schedule(path, injector.joints)
        for entry in self.schedule:
            self._check_mode(parameter_name(entry.owner, entry.kind), entry.value)
        injector.set_schedule(self.schedule)
        for name, value in values.items():
            owner, kind = split_name(name)
            if value != self.table[name].default:
                self._check_mode(name, value)
                injector.set(owner, kind, value)
        node.add_on_set_parameters_callback(self._on_set)

    def _check_mode(self, name: str, value: object) -> None:
        """Refuse what the timing mode cannot do.

        Raises:
            ParameterError: a state delay in lockstep. There the plant advances only on a
                command, and the controller commands only on a new state, so a state held
                back would stop the loop instead of delaying it (use realtime timing).
        """
        if self._lockstep and name == DELAY and value:
            raise ParameterError(name, "0 in lockstep (a late state stops the loop there)", value)

    @property
    def names(self) -> frozenset[str]:
        """Every parameter name this object owns."""
        return frozenset(self.table.names)

    def _on_set(self, changes: Sequence[Parameter]) -> SetParametersResult:
        mine = [c for c in changes if c.name in self.table]
        if not mine:
            return accepted()
        if any(c.name == FAULT_SCHEDULE for c in mine):
            return rejected(f"{FAULT_SCHEDULE}: read-only while running; restart the node")
        injector = self.injector
        try:
            checked = [(c.name, self.table[c.name].check(c.value)) for c in mine]
            for name, value in checked:
                self._check_mode(name, value)
        except ParameterError as exc:
            return rejected(str(exc))
        before = dict(injector.values)
        try:
            for name, value in checked:
                owner, kind = split_name(name)
                injector.set(owner, kind, value)
        except USER_ERRORS as exc:
            injector.values.clear()
            injector.values.update(before)
            injector.apply()
            return rejected(str(exc))
        self._node.get_logger().info(  # type: ignore[no-untyped-call]  # rclpy is untyped
            "faults: " + "; ".join(f"{name} = {value}" for name, value in checked)
        )
        return accepted()
