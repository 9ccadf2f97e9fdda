"""The Fast DDS profile lca_hil's processes start with: shared-memory ports that answer soon.

Fast DDS reads its default XML profile from the file `FASTRTPS_DEFAULT_PROFILES_FILE` names
when a process creates its first participant (Fast DDS 2.x, the one ROS 2 Jazzy ships). Every
lca_hil node and tool points it at the shipped config/dds/fastdds.xml before `rclpy.init`,
unless the user named a profile of their own: theirs is kept and said once in the log.

Why: when a participant matches a new remote reader, Fast DDS 2.14 opens that reader's
shared-memory port while holding the writer's lock, and the port's health check can sleep one
listener period of the port's maker (`healthy_check_timeout_ms` / 3, 333 ms by default) before
it sees the remote listener alive. A `publish` on that writer waits for the lock with the GIL
held (rclpy does not release it), so the whole process stands still: the CAN bridge's cycle
thread and its in-process drives, or the controller, for about 330 ms, 2-3 s after a third
participant (a test probe, a recorder, the benchmark) joined. The profile's shared-memory
transport has `healthy_check_timeout_ms` 150: the ports a process makes with it have a 50 ms
listener period. Shared memory cannot be left out: for ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
rmw_fastrtps appends its own shared-memory and UDP transports to the profile's. The stacks
and the measurements: docs/can-transport.md, "The eighth round".
"""

from __future__ import annotations

import os
from pathlib import Path

from lca_sim.config.paths import config_dir

PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"


def shipped_profile() -> Path:
    """The shipped Fast DDS profile (config/dds/fastdds.xml)."""
    return config_dir() / "dds" / "fastdds.xml"


def use_shipped_profile() -> str | None:
    """Point Fast DDS at the shipped profile unless a profile is already chosen.

    Call before the process's first `rclpy.init`. Returns the user's own profile when one was
    set (kept as it is), else None (the shipped one is in force, also when a parent process
    chose it already).
    """
    shipped = str(shipped_profile())
    own = os.environ.get(PROFILE_ENV)
    if own and own != shipped:
        return own
    os.environ[PROFILE_ENV] = shipped
    return None
