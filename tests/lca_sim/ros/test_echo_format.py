"""lca-echo's YAML formatting: diagnostic levels by number and name, floats without denormals.

Pure: message objects are built and formatted, no rclpy context is started.

Before the fix a level printed as a one-item list (`level:` then `- 1`, from the `bytes` rclpy
gives an `octet`), and a subnormal float printed as itself (`- 5.0e-324`).
"""

from __future__ import annotations

import sys

import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from sensor_msgs.msg import JointState

from lca_sim.ros.echo import message_to_plain, message_to_yaml, plain_float

SUBNORMAL = 5e-324  # the smallest positive double, below sys.float_info.min
TINY_NORMAL = 1e-300


def diagnostic_array() -> DiagnosticArray:
    msg = DiagnosticArray()
    msg.status = [
        DiagnosticStatus(level=level, name=f"drive{index}")
        for index, level in enumerate(
            (
                DiagnosticStatus.OK,
                DiagnosticStatus.WARN,
                DiagnosticStatus.ERROR,
                DiagnosticStatus.STALE,
            )
        )
    ]
    return msg


def test_diagnostic_levels_print_as_number_and_name() -> None:
    text = message_to_yaml(diagnostic_array())
    levels = [line for line in text.splitlines() if line.startswith("- level:")]
    assert levels == [
        "- level: 0 (OK)",
        "- level: 1 (WARN)",
        "- level: 2 (ERROR)",
        "- level: 3 (STALE)",
    ], text
    parsed = yaml.safe_load(text)
    assert [status["level"] for status in parsed["status"]] == [
        "0 (OK)",
        "1 (WARN)",
        "2 (ERROR)",
        "3 (STALE)",
    ]
    assert [status["name"] for status in parsed["status"]] == [f"drive{i}" for i in range(4)]


def test_unknown_diagnostic_level_keeps_its_number() -> None:
    assert message_to_plain(DiagnosticStatus(level=b"\x07"))["level"] == "7 (unknown)"


def test_subnormal_floats_print_as_zero_and_tiny_normals_keep_their_value() -> None:
    assert sys.float_info.min > SUBNORMAL
    noisy = 1.0000000000000002e-19  # normal: real (if small) values are not rounded
    msg = JointState(
        name=["a", "b", "c", "d", "e"],
        position=[SUBNORMAL, -1e-310, TINY_NORMAL, noisy, 0.5],
        velocity=[1e-320],
    )
    text = message_to_yaml(msg)
    assert "e-3" not in text.replace("1.0e-300", ""), text  # no subnormal printed
    parsed = yaml.safe_load(text)
    assert parsed["position"] == [0.0, 0.0, TINY_NORMAL, noisy, 0.5]
    assert parsed["velocity"] == [0.0]
    assert parsed["name"] == ["a", "b", "c", "d", "e"]


def test_plain_float_rule() -> None:
    assert plain_float(SUBNORMAL) == 0.0
    assert plain_float(-SUBNORMAL) == 0.0
    assert plain_float(sys.float_info.min) == sys.float_info.min
    assert plain_float(TINY_NORMAL) == TINY_NORMAL
    assert plain_float(float("inf")) == float("inf")
    assert type(plain_float(0.25)) is float
