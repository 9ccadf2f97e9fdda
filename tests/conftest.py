"""Shared test setup: DDS on loopback only, a private domain id, and the shipped robots."""

from __future__ import annotations

import os

# Set before anything can import rclpy: DDS traffic must never leave loopback.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", "58")

import pytest

from lca_sim import RobotParams, load_robot
from lca_sim.ros.dds_profile import use_shipped_profile

# The shipped Fast DDS profile for this process's participants (test probes) and the nodes it
# starts, as the nodes themselves use it: see lca_sim/ros/dds_profile.py.
use_shipped_profile()


@pytest.fixture(scope="session")
def default_robot() -> RobotParams:
    """The shipped robot with the paper's irreversible gears (Table 1)."""
    return load_robot("default")


@pytest.fixture(scope="session")
def reversible_robot() -> RobotParams:
    """The shipped velocity-friction-only baseline."""
    return load_robot("reversible")
