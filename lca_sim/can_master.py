"""The CANopen master's side of CiA 402, as pure functions (no bus, no clock, no ROS).

What the CAN bridge decides every cycle, from the last statusword of each drive and its own
latches: the controlword that walks the drive towards the wanted power state, the target torque
(per mille of the rated torque) for a current command, and the bus load a set of frames puts on
a classical CAN bus. The bus I/O around it is `lca_sim.can_bridge`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

# Controlword commands (CiA 402, table "device control commands"); bit 8 is halt.
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080
CW_HALT = 0x0100

MODE_CST = 10  # cyclic synchronous torque
MODE_CSV = 9  # cyclic synchronous velocity


class PowerState(enum.Enum):
    """The CiA 402 power states, as a master reads them from the statusword."""

    NOT_READY_TO_SWITCH_ON = "not_ready_to_switch_on"
    SWITCH_ON_DISABLED = "switch_on_disabled"
    READY_TO_SWITCH_ON = "ready_to_switch_on"
    SWITCHED_ON = "switched_on"
    OPERATION_ENABLED = "operation_enabled"
    QUICK_STOP_ACTIVE = "quick_stop_active"
    FAULT_REACTION_ACTIVE = "fault_reaction_active"
    FAULT = "fault"


# (mask, value, state): the statusword patterns of CiA 402, checked in this order.
_STATUS_PATTERNS = (
    (0x4F, 0x00, PowerState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, PowerState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, PowerState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, PowerState.SWITCHED_ON),
    (0x6F, 0x27, PowerState.OPERATION_ENABLED),
    (0x6F, 0x07, PowerState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, PowerState.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, PowerState.FAULT),
)


def power_state(statusword: int) -> PowerState | None:
    """The power state a statusword reports, or None for a pattern CiA 402 does not define."""
    for mask, value, state in _STATUS_PATTERNS:
        if statusword & mask == value:
            return state
    return None


class Want(enum.Enum):
    """What the master wants of a drive this cycle."""

    ENABLED = "enabled"  # operation enabled, torque follows the command
    DISABLED = "disabled"  # ready to switch on: power stage off, no torque
    QUICK_STOP = "quick_stop"  # quick stop, then switch on disabled
    FAULT_RESET = "fault_reset"  # a rising edge of bit 7, then DISABLED


def next_controlword(state: PowerState | None, want: Want, previous_controlword: int) -> int:
    """The controlword that moves a drive in `state` one legal step towards `want`.

    The enable walk is 0x06 -> 0x07 -> 0x0F (ready to switch on, switched on, operation
    enabled). A fault reset needs a rising edge on bit 7, so after a controlword with bit 7 set
    the next one clears it. Unknown states get a shutdown, which no state turns into motion.
    """
    if want is Want.FAULT_RESET:
        if state is PowerState.FAULT:
            return CW_DISABLE_VOLTAGE if previous_controlword & CW_FAULT_RESET else CW_FAULT_RESET
        want = Want.DISABLED
    if want is Want.QUICK_STOP:
        # Quick stop from operation enabled; from any other state it leads to (or keeps)
        # switch on disabled, the state no single controlword leaves for motion.
        return CW_DISABLE_VOLTAGE if state is PowerState.FAULT else CW_QUICK_STOP
    if state in (None, PowerState.NOT_READY_TO_SWITCH_ON, PowerState.FAULT_REACTION_ACTIVE):
        return CW_SHUTDOWN
    if state is PowerState.FAULT:
        return CW_DISABLE_VOLTAGE  # stays in fault until a reset is wanted
    if state is PowerState.QUICK_STOP_ACTIVE:
        return CW_QUICK_STOP  # let the quick stop finish (-> switch on disabled)
    if want is Want.DISABLED:
        return CW_SWITCH_ON if state is PowerState.OPERATION_ENABLED else CW_SHUTDOWN
    # want ENABLED
    if state is PowerState.SWITCH_ON_DISABLED:
        return CW_SHUTDOWN
    if state is PowerState.READY_TO_SWITCH_ON:
        return CW_SWITCH_ON
    return CW_ENABLE_OPERATION  # switched on -> enable; enabled -> stay


@dataclass(frozen=True, slots=True)
class TorqueScale:
    """Current (A) to CiA 402 torque (per mille of the rated torque 0x6076) for one axis.

    Attributes:
        torque_constant_nm_per_a: k_t of the motor (robot config).
        rated_torque_nm: 0x6076 of the drive (read in mN m).
        max_torque_permille: 0x6072 of the drive; larger targets are clamped.
    """

    torque_constant_nm_per_a: float
    rated_torque_nm: float
    max_torque_permille: int

    def __post_init__(self) -> None:
        if not (self.torque_constant_nm_per_a > 0.0 and math.isfinite(self.rated_torque_nm)):
            raise ValueError("k_t must be > 0 and the rated torque finite")
        if not self.rated_torque_nm > 0.0:
            raise ValueError(f"rated torque must be > 0 N m, got {self.rated_torque_nm!r}")
        if not 0 < self.max_torque_permille <= 32767:
            raise ValueError(f"max torque must be 1..32767 per mille: {self.max_torque_permille}")

    def target_permille(self, current_a: float) -> tuple[int, bool]:
        """The target torque for a current command, and whether it was clamped."""
        permille = round(self.torque_constant_nm_per_a * current_a / self.rated_torque_nm * 1000.0)
        limit = self.max_torque_permille
        if permille > limit:
            return limit, True
        if permille < -limit:
            return -limit, True
        return permille, False


def frame_bits(data_bytes: int) -> int:
    """Bits on the wire of a classical CAN frame with an 11-bit identifier, worst-case stuffing.

    44 + 8 n bits of frame, 3 of interframe space, and one stuff bit per 4 of the 34 + 8 n
    bits that are stuffed (CiA / Bosch worst case, as used for bus-load budgets).
    """
    return 47 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4


def bus_load_pct(bits_per_s: float, bitrate_bit_s: float) -> float:
    """Bus load in percent of the bit rate."""
    return 100.0 * bits_per_s / bitrate_bit_s
