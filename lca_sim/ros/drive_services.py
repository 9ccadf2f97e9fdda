"""The CAN bridge's drive services (std_srvs/Trigger, named like ros2_canopen's CiA 402 driver).

`~/init` configures the drives over SDO and starts the cycle, `~/enable` and `~/disable` walk
the CiA 402 state machine, `~/halt` stops with zero torque, `~/recover` clears the latches and
resets faults, `~/cyclic_torque_mode` writes 0x6060 = 10 to every drive. A service that needs
the drives says so while the node is not configured (docs/can.md).
"""

from __future__ import annotations

from collections.abc import Callable

import canopen
from rclpy.node import Node
from std_srvs.srv import Trigger

from lca_sim.canbus.master import Cia402Master
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import MODE_CST
from lca_sim.ros.can_drives import CanDrives


class DriveServices:
    """The Trigger services of the bridge's drives.

    Args:
        node: the bridge node; the services are created on it.
        drives: the node's drives (the master while configured).
        active: the node is lifecycle ACTIVE (only then does `~/enable` run the drives).
        lifecycle_state: the lifecycle state's label, for the replies.
    """

    def __init__(
        self,
        node: Node,
        drives: CanDrives,
        active: Callable[[], bool],
        lifecycle_state: Callable[[], str],
    ) -> None:
        self._drives = drives
        self._active = active
        self._lifecycle_state = lifecycle_state
        for name, handler in (
            ("init", self._init),
            ("enable", self._enable),
            ("disable", self._disable),
            ("halt", self._halt),
            ("recover", self._recover),
            ("cyclic_torque_mode", self._cst),
        ):
            node.create_service(Trigger, f"~/{name}", handler)

    def _need_master(self, res: Trigger.Response) -> Cia402Master | None:
        """The master, or None with the response saying the node is not configured."""
        master = self._drives.master
        if master is None:
            res.success = False
            res.message = f"node {self._lifecycle_state()}: configure it first (lifecycle)"
        return master

    def _init(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        if self._need_master(res) is None:
            return res
        message = self._drives.init()
        res.success = not message
        res.message = message or "drives configured and operational; call ~/enable"
        return res

    def _enable(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        master = self._need_master(res)
        if master is None:
            return res
        if not self._active():  # an inactive node does not run the drives
            res.success = False
            res.message = f"node {self._lifecycle_state()}: activate it (lifecycle) to enable"
            return res
        res.message = master.enable(True)
        res.success = res.message == "enabling"
        return res

    def _disable(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        master = self._need_master(res)
        if master is not None:
            res.message = master.enable(False)
            res.success = True
        return res

    def _halt(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        master = self._need_master(res)
        if master is not None:
            master.halt()
            res.success, res.message = True, "halted: zero torque until the next ~/enable"
        return res

    def _recover(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        master = self._need_master(res)
        if master is not None:
            master.recover()
            res.success, res.message = True, "latches cleared, faults reset; call ~/enable"
        return res

    def _cst(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        master = self._need_master(res)
        if master is None:
            return res
        try:
            for joint in self._drives.joints:
                master.sdo_write(joint, od.MODES_OF_OPERATION, 0, MODE_CST)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            res.success, res.message = False, f"mode {MODE_CST} refused: {exc}"
            return res
        res.success = True
        res.message = f"cyclic synchronous torque (mode {MODE_CST}) on every drive"
        return res
