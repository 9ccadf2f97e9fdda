"""The CAN bridge master's parameters (`BridgeParams`) and its error (`BridgeError`).

Validated once, where they are built; docs/can.md, "The bridge's parameters", lists them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lca_sim.cia402 import device
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import MODE_CSP, MODE_CST, MODE_CSV
from lca_sim.errors import InvalidValueError, LcaHilError

PDO_LAYOUTS = ("compact", "drive")
# CiA 402-2 cyclic synchronous modes the bridge runs an axis in: 0x6060 value, target object.
MODES = {"cst": MODE_CST, "csv": MODE_CSV, "csp": MODE_CSP}
MODE_TARGETS = {
    MODE_CST: od.TARGET_TORQUE,
    MODE_CSV: od.TARGET_VELOCITY,
    MODE_CSP: od.TARGET_POSITION,
}


class BridgeError(LcaHilError, RuntimeError):
    """A drive could not be configured or started (one line, with the drive and the object).

    Also a RuntimeError: bench/can_cycle.py catches it as one around its rig.
    """


@dataclass(frozen=True, slots=True)
class BridgeParams:
    """What the bridge needs to know of the robot and the bus.

    Attributes:
        joints: joint names, in the order of command arrays and published states.
        node_ids: the CANopen node id of each joint's drive.
        torque_constants_nm_per_a, gear_ratios: per joint, from the robot config.
        drive_state_names: names of the drive-chain state codes (0x2010), if known.
        master_node_id: the bridge's heartbeat id.
        cycle_hz: SYNC rate.
        bitrate_bit_s: for the bus-load figure.
        command_timeout_s: controller silence beyond this: zero torque with halt.
        quick_stop_after_s: silence beyond command_timeout_s + this: quick stop.
        stale_timeout_s: a drive without TPDO for this long while running is stale.
        heartbeat_producer_ms: written to each drive's 0x1017.
        heartbeat_consumer_ms: written to each drive's 0x1016 (watching the master).
        heartbeat_loss_periods: the master's own consumer time of each drive's heartbeat
            (CiA 301 7.2.8.3.2.2; 0x1016 on a consumer), in the drives' producer periods
            (`heartbeat_producer_ms`): a drive silent that long has lost its heartbeat.
        rpdo_deadline_ms: written to each drive's 0x1400 sub 5.
        max_send_failures: consecutive failed sends after which the axes halt.
        pdo_layout: "compact": `init()` maps every drive's PDOs for this cycle
            (`configure_compact_pdos`: a 4-axis 1 kHz cycle fits 1 Mbit/s); "drive": use the
            mapping the drive has (it must map what `DriveSetup` binds).
        modes: per joint, "cst" (cyclic synchronous torque: the current command becomes the
            target torque), "csv" (cyclic synchronous velocity: the velocity command becomes
            the target velocity 0x60FF and the drive closes the velocity loop) or "csp"
            (cyclic synchronous position: the position command becomes the target position
            0x607A and the drive closes the position and velocity loops); empty: all CST.
        slow_tpdo_rate_hz: compact layout: the rate of the TPDOs that are not needed every
            cycle (statusword and current, the drive-chain extras): every n-th SYNC with
            n = round(cycle_hz / this), at least 1.
    """

    joints: tuple[str, ...]
    node_ids: tuple[int, ...]
    torque_constants_nm_per_a: tuple[float, ...]
    gear_ratios: tuple[float, ...]
    drive_state_names: tuple[str, ...] = ()
    master_node_id: int = 127
    cycle_hz: float = 500.0
    bitrate_bit_s: float = 1_000_000.0
    command_timeout_s: float = 0.1
    quick_stop_after_s: float = 0.5
    stale_timeout_s: float = 0.1
    heartbeat_producer_ms: int = 100
    heartbeat_consumer_ms: int = 300
    heartbeat_loss_periods: float = 3.0
    rpdo_deadline_ms: int = 100
    max_send_failures: int = 10
    pdo_layout: str = "compact"
    slow_tpdo_rate_hz: float = 50.0
    modes: tuple[str, ...] = ()

    def mode_of(self, k: int) -> int:
        """The 0x6060 value of joint k."""
        return MODES[self.modes[k]] if self.modes else MODE_CST

    @property
    def drive_heartbeat_timeout_s(self) -> float:
        """The master's heartbeat consumer time of every drive, s (0: 0x1017 = 0, not watched)."""
        return self.heartbeat_loss_periods * self.heartbeat_producer_ms * 1e-3

    @property
    def stall_cycles(self) -> int:
        """SYNCs without a complete cycle that make a stall: `stale_timeout_s` in SYNCs, >= 3."""
        return max(3, math.ceil(self.stale_timeout_s * self.cycle_hz))

    @property
    def slow_tpdo_every(self) -> int:
        """The transmission type (every n-th SYNC) of the compact layout's slow TPDOs."""
        return max(
            1, min(device.SYNC_TRANSMISSION_MAX, round(self.cycle_hz / self.slow_tpdo_rate_hz))
        )

    def __post_init__(self) -> None:
        n = len(self.joints)
        if n == 0 or len(set(self.joints)) != n:
            raise InvalidValueError(
                f"joints must be distinct and not empty, got {list(self.joints)}"
            )
        for name, values in (
            ("node_ids", self.node_ids),
            ("torque_constants_nm_per_a", self.torque_constants_nm_per_a),
            ("gear_ratios", self.gear_ratios),
        ):
            if len(values) != n:
                raise InvalidValueError(
                    f"{name} needs {n} values (one per joint), got {len(values)}"
                )
        ids = [*self.node_ids, self.master_node_id]
        if any(not 1 <= i <= 127 for i in ids) or len(set(ids)) != len(ids):
            raise InvalidValueError(f"node ids must be distinct, in 1..127, got {ids}")
        if not 1.0 <= self.cycle_hz <= 2000.0:
            raise InvalidValueError(f"cycle_hz must be in 1..2000, got {self.cycle_hz!r}")
        for name in ("command_timeout_s", "quick_stop_after_s", "stale_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InvalidValueError(f"{name} must be > 0, got {value!r}")
        if self.max_send_failures < 1:
            raise InvalidValueError("max_send_failures must be >= 1")
        if not (math.isfinite(self.heartbeat_loss_periods) and self.heartbeat_loss_periods > 1.0):
            # CiA 301 7.2.8.3.2.2: the consumer time must exceed the producer time
            raise InvalidValueError(
                f"heartbeat_loss_periods must be > 1, got {self.heartbeat_loss_periods!r}"
            )
        self._check_pdo_layout()

    def _check_pdo_layout(self) -> None:
        if self.modes and (
            len(self.modes) != len(self.joints) or not set(self.modes) <= set(MODES)
        ):
            raise InvalidValueError(
                f"modes must give one of {sorted(MODES)} per joint, got {list(self.modes)}"
            )
        if self.pdo_layout not in PDO_LAYOUTS:
            raise InvalidValueError(
                f"pdo_layout must be one of {PDO_LAYOUTS}, got {self.pdo_layout!r}"
            )
        if not (math.isfinite(self.slow_tpdo_rate_hz) and self.slow_tpdo_rate_hz > 0.0):
            raise InvalidValueError(
                f"slow_tpdo_rate_hz must be > 0, got {self.slow_tpdo_rate_hz!r}"
            )
