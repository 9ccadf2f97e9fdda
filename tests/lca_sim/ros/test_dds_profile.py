"""The shipped Fast DDS profile: a node's shared-memory ports answer a health check in 50 ms.

Fast DDS 2.14 opens a newly matched reader's shared-memory port while holding the writer's
lock; its health check sleeps one listener period of the port (a third of the creator's
`healthy_check_timeout_ms`, 333 ms by default) when the listener has not shown life since the
last check. rclpy's `publish` waits for that lock with the GIL held, so the CAN bridge and its
in-process drives stood still for 330 ms when a third participant (a probe, a recorder, the
benchmark) joined: a CI run failed on it, and the relay set-up's drives raised EMCY 0x8700 and
0x8130 (docs/can-transport.md, "The 331 ms stall"). The listener period is written into the
port's segment in /dev/shm by the process that creates the port; these tests read it back from
the ports of a node started as a user starts it.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import pytest
from support import start_shipped, wait_until

from lca_sim.ros.dds_profile import PROFILE_ENV, shipped_profile, use_shipped_profile

DOMAIN_ID = 103
LISTENER_PERIOD_MAX_MS = 50  # the drives' RPDO deadline is 100 ms: half of it at most
U32 = struct.Struct("<I")
RTPS_PORT_BASE, RTPS_DOMAIN_GAIN = 7400, 250  # DDSI-RTPS 2.2, 9.6.1.1: the well-known ports


def shm_ports(pid: int) -> list[int]:
    """The domain's shared-memory ports a process listens on (its threads `dds.shm.<port>`).

    Those are the unicast ports of the RTPS port mapping (7400 + 250 x domain + offsets): the
    ones a peer's writer opens to send it data, where the stall was. Ports outside that range
    (7000 upwards) are shared by every domain: an existing segment of one is reused with the
    listener period of whichever process made it, so they say nothing about this node.
    """
    first = RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * DOMAIN_ID
    ports = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        name = (task / "comm").read_text(encoding="utf-8").strip()
        if name.startswith("dds.shm.") and name[8:].isdigit():
            port = int(name[8:])
            if first <= port < first + RTPS_DOMAIN_GAIN:
                ports.append(port)
    return sorted(ports)


def listener_period_ms(port: int) -> tuple[int, int]:
    """(healthy_check_timeout_ms, port_wait_timeout_ms) of a port, read from its segment.

    Fast DDS 2.14's `SharedMemGlobal::PortNode` has four consecutive uint32: port_id,
    num_listeners, healthy_check_timeout_ms, port_wait_timeout_ms (= the check timeout / 3).
    The record is the one that starts with this port's id and has that ratio.
    """
    data = (Path("/dev/shm") / f"fastrtps_port{port}").read_bytes()
    key = U32.pack(port)
    at = data.find(key)
    while at >= 0:
        check_ms, wait_ms = U32.unpack_from(data, at + 8)[0], U32.unpack_from(data, at + 12)[0]
        if check_ms and wait_ms == check_ms // 3:
            return check_ms, wait_ms
        at = data.find(key, at + 1)
    raise AssertionError(f"no PortNode for port {port} in its segment ({len(data)} bytes)")


def test_the_shipped_bridge_creates_ports_that_answer_a_health_check_within_50_ms(
    tmp_path: Path,
) -> None:
    """The shipped bridge, started without a profile of the user's: listener period <= 50 ms.

    Without the shipped profile the ports are made with Fast DDS's defaults (1000 ms, a 333 ms
    listener period: the stall). The node is started as a user starts it, without the profile
    this test process chose.
    """
    node = start_shipped(
        "lca-can-bridge", "can_bridge.yaml", DOMAIN_ID, tmp_path, unset=[PROFILE_ENV]
    )
    try:
        wait_until(
            lambda: len(shm_ports(node.proc.pid)) >= 1,
            "its shared-memory port in the domain's range",
            check=node.check_alive,
        )
        periods = {port: listener_period_ms(port) for port in shm_ports(node.proc.pid)}
    finally:
        assert node.stop() == 0
    print(f"ports (check timeout ms, listener period ms): {periods}")
    assert all(wait_ms <= LISTENER_PERIOD_MAX_MS for _, wait_ms in periods.values()), periods
    log = node.log.read_text(encoding="utf-8")
    assert "Fast DDS profile" not in log  # the shipped one: nothing to say


def test_a_profile_of_the_users_is_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    """FASTRTPS_DEFAULT_PROFILES_FILE set by the user wins; unset, the shipped file is used."""
    monkeypatch.setenv(PROFILE_ENV, "/etc/my_fastdds.xml")
    assert use_shipped_profile() == "/etc/my_fastdds.xml"
    assert os.environ[PROFILE_ENV] == "/etc/my_fastdds.xml"
    monkeypatch.delenv(PROFILE_ENV)
    assert use_shipped_profile() is None
    assert os.environ[PROFILE_ENV] == str(shipped_profile())
    assert shipped_profile().is_file()
    assert use_shipped_profile() is None  # chosen by a parent process: still the shipped one
