"""Python logging in a node's process goes to the ROS log (`lca_sim.ros.ros_logging`)."""

from __future__ import annotations

import logging

import pytest

from lca_sim.ros.ros_logging import RosLogHandler, python_logging_on_ros


def test_the_layers_records_reach_the_ros_log_with_their_severity(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """A canbus warning was printed bare by Python's last resort; now it is an rcutils line.

    The project's INFO notes come too (they were dropped); other libraries' INFO does not, and
    once the block ends nothing is left installed.
    """
    project = logging.getLogger("lca_sim.canbus.test_probe")
    other = logging.getLogger("canopen.test_probe")
    level_before = logging.getLogger("lca_sim").level
    with python_logging_on_ros("lca-test-prog") as handler:
        project.warning("drive %s is stale", "pivot")
        project.info("a note")
        project.debug("not shown")
        other.info("not shown either")
        other.error("a library's error")
        try:
            raise ValueError("boom")
        except ValueError:
            project.exception("handler failed")
        assert handler in logging.getLogger().handlers
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if "[lca_test_prog]" in line]
    assert [line.split("]")[0] for line in lines] == ["[WARN", "[INFO", "[ERROR", "[ERROR"]
    assert lines[0].endswith("[lca_test_prog]: drive pivot is stale")
    assert "ValueError: boom" in err  # the traceback goes along
    assert "not shown" not in err
    assert not any(isinstance(h, RosLogHandler) for h in logging.getLogger().handlers)
    assert logging.getLogger("lca_sim").level == level_before
