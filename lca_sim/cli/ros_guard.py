"""The one check for the commands that run over ROS 2: a missing rclpy is one error line.

`lca-hil fig15` (and `lca-hil paper` with Fig. 15) need ROS 2; every other tool runs without it.
Where ROS 2 is not installed or not sourced, those two say so instead of ending in a traceback.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from lca_sim.errors import LcaHilError

# Top-level modules that only a ROS 2 installation provides (rclpy and the message packages).
ROS_MODULES = frozenset(
    {
        "rclpy",
        "rosidl_runtime_py",
        "rpyutils",
        "builtin_interfaces",
        "diagnostic_msgs",
        "rcl_interfaces",
        "rosgraph_msgs",
        "sensor_msgs",
        "std_msgs",
        "std_srvs",
    }
)


class RosMissingError(LcaHilError):
    """A command needs ROS 2, and this Python cannot import it."""


@contextmanager
def ros_required(what: str, hint: str = "") -> Iterator[None]:
    """Turn the failed import of a ROS 2 module inside the block into a RosMissingError.

    Args:
        what: what needs ROS 2, for the message ("Fig. 15").
        hint: appended to the message, e.g. a way to run without ROS 2.

    Raises:
        RosMissingError: a module of ROS_MODULES could not be imported. Any other missing
            module is a broken installation and propagates unchanged.
    """
    try:
        yield
    except ModuleNotFoundError as exc:
        if (exc.name or "").partition(".")[0] not in ROS_MODULES:
            raise
        raise RosMissingError(
            f"{what} runs over ROS 2, but module {exc.name!r} cannot be imported; source ROS 2 "
            f"Jazzy first (. /opt/ros/jazzy/setup.bash){hint}"
        ) from exc
