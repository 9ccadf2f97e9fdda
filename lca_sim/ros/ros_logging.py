"""Python `logging` records of a node's process on the ROS 2 log (rcutils, /rosout).

The layers below the node shells (lca_sim.canbus, lca_sim.model, canopen, python-can) log
with Python's `logging`, as libraries without ROS should. In a node process nothing was
configured for it, so Python's last-resort handler printed their warnings and errors bare on
stderr (no severity, no time, no node, not on /rosout) and dropped their INFO notes. A
`RosLogHandler` on the root logger hands each record to an rclpy logger instead: the node's
once it exists (so it reaches /rosout), the program's before.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from rclpy.logging import get_logger

# The project's own layers log their notes at INFO; other libraries from WARNING up, as before.
PROJECT_LOGGERS = ("lca_sim", "lca_control")


class RosLogHandler(logging.Handler):
    """Hands Python log records to an rclpy logger at the matching severity."""

    def __init__(self, ros_logger: Any) -> None:
        super().__init__(logging.DEBUG)
        self.ros_logger = ros_logger  # rclpy's RcutilsLogger (untyped)
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        """Log `record` (with its traceback, if any) on `ros_logger`; never raises."""
        try:
            log_at(self.ros_logger, record.levelno, self.format(record))
        except Exception:  # a log call must not break the thread that made it
            self.handleError(record)


def log_at(ros_logger: Any, level: int, text: str) -> None:
    """`text` on an rclpy logger at the severity of a Python logging `level`."""
    if level >= logging.CRITICAL:
        ros_logger.fatal(text)
    elif level >= logging.ERROR:
        ros_logger.error(text)
    elif level >= logging.WARNING:
        ros_logger.warning(text)
    elif level >= logging.INFO:
        ros_logger.info(text)
    else:
        ros_logger.debug(text)


@contextmanager
def python_logging_on_ros(program: str) -> Iterator[RosLogHandler]:
    """Route Python logging to the ROS log while the block runs; set `.ros_logger` to the node's.

    `program` names the rclpy logger used until then (a console script's name, with dashes
    made underscores as rcutils names want).
    """
    handler = RosLogHandler(get_logger(program.replace("-", "_")))
    root = logging.getLogger()
    levels = {name: logging.getLogger(name).level for name in PROJECT_LOGGERS}
    root.addHandler(handler)
    for name in PROJECT_LOGGERS:
        if logging.getLogger(name).getEffectiveLevel() > logging.INFO:
            logging.getLogger(name).setLevel(logging.INFO)
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)
