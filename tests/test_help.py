"""Which arguments of a node script are its own: `-h`/`--help` among them asks for the help.

The launchers read `-h`/`--help` only outside the ROS arguments, as rcl splits them. The
end-to-end check, every installed console script answering `--help` and `-h` with its usage
(a node's with its whole parameter table) without importing rclpy, is item 9 of the fault
matrix, tests/test_fault_matrix.py.
"""

from __future__ import annotations

import pytest

from lca_sim.cli.console import own_arguments, wants_help


@pytest.mark.parametrize(
    ("argv", "own", "helps"),
    [
        (["--help"], ["--help"], True),
        (["-h", "--ros-args", "-p", "a:=1"], ["-h"], True),
        (["--ros-args", "-p", "robot:=--help"], [], False),
        (["--ros-args", "-p", "a:=1", "--", "-h"], ["-h"], True),
        (["--ros-args", "--params-file", "f.yaml", "--ros-args", "-r", "x:=y"], [], False),
        ([], [], False),
    ],
)
def test_help_flag_is_read_outside_ros_arguments(
    argv: list[str], own: list[str], helps: bool
) -> None:
    """`-h`/`--help` counts only among the script's own arguments, as rcl splits them."""
    assert own_arguments(argv) == own
    assert wants_help(argv) is helps
