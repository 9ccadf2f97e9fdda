"""The DDS profile lca_hil's processes start with: Fast DDS on loopback UDP, no shared memory.

Fast DDS reads its default XML profile from the file `FASTRTPS_DEFAULT_PROFILES_FILE` names
when a process creates its first participant (Fast DDS 2.x, the one ROS 2 Jazzy ships). Every
lca_hil node and tool points it at the shipped config/dds/fastdds.xml before `rclpy.init`,
unless the user named a profile of their own: theirs is kept and said once in the log.

Why not shared memory: when a participant matches a new remote reader, Fast DDS 2.14 opens
that reader's shared-memory port while holding the writer's lock, and the port's health check
can sleep one listener period (`healthy_check_timeout_ms` / 3, 333 ms by default) before it
sees the remote listener alive. A `publish` on that writer waits for the lock with the GIL held
(rclpy does not release it), so the whole process stands still: the CAN bridge's cycle thread,
its in-process drives, the controller, for about 330 ms, 2-3 s after a third participant (a
test probe, a recorder, the benchmark) joined. docs/can-transport.md shows the stacks. On
UDP there is no port to check; the interface white list keeps DDS on 127.0.0.1.
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
