"""The CAN bridge's SDO services: `~/sdo_read` and `~/sdo_write` (docs/can.md).

SDO access to the drives for diagnosis, with rcl_interfaces types (an ament_python package
cannot define its own): `~/sdo_read` is a GetParameters, `~/sdo_write` a SetParameters, both
with names `<joint>/<index>[/<subindex>]` (`pivot/0x6041`, `lift/0x1400/5`). A value that
cannot be read comes back as the string "error: ..."; a write that fails, as an unsuccessful
result with the reason.
"""

from __future__ import annotations

from collections.abc import Callable

import canopen
from rcl_interfaces.msg import ParameterType, ParameterValue, SetParametersResult
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.node import Node

from lca_sim.canbus.master import Cia402Master
from lca_sim.errors import InvalidValueError

SDO_ERRORS = (ValueError, KeyError, canopen.SdoAbortedError, canopen.SdoCommunicationError)


def parse_object_name(name: str) -> tuple[str, int, int]:
    """`pivot/0x6041` or `lift/0x1400/5` -> (joint, index, subindex)."""
    parts = name.split("/")
    if len(parts) not in (2, 3):
        raise InvalidValueError(f"expected <joint>/<index>[/<subindex>], got {name!r}")
    index = int(parts[1], 0)
    subindex = int(parts[2], 0) if len(parts) == 3 else 0
    if not (0 <= index <= 0xFFFF and 0 <= subindex <= 0xFF):
        raise InvalidValueError(f"index or subindex out of range in {name!r}")
    return parts[0], index, subindex


def parameter_value(raw: object) -> ParameterValue:
    """An SDO value (or an error text) as an rcl_interfaces ParameterValue."""
    if isinstance(raw, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=raw)
    if isinstance(raw, int):
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=raw)
    if isinstance(raw, float):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=raw)
    return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=str(raw))


class SdoServices:
    """`~/sdo_read` and `~/sdo_write` on a node, reaching the drives through its master.

    Args:
        node: the bridge node; the services are created on it.
        master: the CANopen master while the node is configured, else None.
        lifecycle_state: the node's lifecycle state, named when there is no master.
    """

    def __init__(
        self,
        node: Node,
        master: Callable[[], Cia402Master | None],
        lifecycle_state: Callable[[], str],
    ) -> None:
        self._master = master
        self._lifecycle_state = lifecycle_state
        node.create_service(GetParameters, "~/sdo_read", self._read)
        node.create_service(SetParameters, "~/sdo_write", self._write)

    def _configured(self) -> Cia402Master:
        """The master; ValueError (an SDO error to the caller) while unconfigured."""
        master = self._master()
        if master is None:
            raise InvalidValueError(
                f"node {self._lifecycle_state()}: configure it first (lifecycle)"
            )
        return master

    def _read(
        self, req: GetParameters.Request, res: GetParameters.Response
    ) -> GetParameters.Response:
        for name in req.names:
            try:
                joint, index, subindex = parse_object_name(name)
                raw = self._configured().sdo_read(joint, index, subindex)
            except SDO_ERRORS as exc:
                raw = f"error: {exc}"
            res.values.append(parameter_value(raw))
        return res

    def _write(
        self, req: SetParameters.Request, res: SetParameters.Response
    ) -> SetParameters.Response:
        for param in req.parameters:
            result = SetParametersResult(successful=True)
            try:
                joint, index, subindex = parse_object_name(param.name)
                v = param.value
                if v.type == ParameterType.PARAMETER_INTEGER:
                    self._configured().sdo_write(joint, index, subindex, int(v.integer_value))
                elif v.type == ParameterType.PARAMETER_DOUBLE:
                    self._configured().sdo_write(joint, index, subindex, float(v.double_value))
                else:
                    raise InvalidValueError("only integer or double values can be written")
            except SDO_ERRORS as exc:
                result = SetParametersResult(successful=False, reason=str(exc))
            res.results.append(result)
        return res
