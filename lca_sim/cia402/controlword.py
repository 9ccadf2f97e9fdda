"""What a CiA 402 master commands each cycle, as pure functions (no bus, no clock, no ROS).

From the last statusword of each drive and the master's own latches: the controlword that walks
the drive towards the wanted power state, and the target torque (per mille of the rated torque)
for a current command. The bus I/O around it is `lca_sim.canbus.master`.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, field

from lca_sim.cia402 import codec
from lca_sim.cia402.device import CW_FAULT_RESET, PowerState, power_state_of
from lca_sim.errors import InvalidValueError

# Whole controlwords a master sends (CiA 402, "device control commands"); the single bits
# (CW_FAULT_RESET, CW_HALT, ...) are lca_sim.cia402.device's.
CMD_DISABLE_VOLTAGE = 0x0000
CMD_QUICK_STOP = 0x0002
CMD_SHUTDOWN = 0x0006
CMD_SWITCH_ON = 0x0007
CMD_ENABLE_OPERATION = 0x000F


def power_state(statusword: int) -> PowerState | None:
    """The power state a statusword reports, or None for a pattern CiA 402 does not define.

    The drive side's decoding (`lca_sim.cia402.device.power_state_of`): one table for both ends.
    """
    return power_state_of(statusword)


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
            return CMD_DISABLE_VOLTAGE if previous_controlword & CW_FAULT_RESET else CW_FAULT_RESET
        want = Want.DISABLED
    if want is Want.QUICK_STOP:
        # Quick stop from operation enabled; from any other state it leads to (or keeps)
        # switch on disabled, the state no single controlword leaves for motion.
        return CMD_DISABLE_VOLTAGE if state is PowerState.FAULT else CMD_QUICK_STOP
    if state in (None, PowerState.NOT_READY_TO_SWITCH_ON, PowerState.FAULT_REACTION_ACTIVE):
        return CMD_SHUTDOWN
    if state is PowerState.FAULT:
        return CMD_DISABLE_VOLTAGE  # stays in fault until a reset is wanted
    if state is PowerState.QUICK_STOP_ACTIVE:
        return CMD_QUICK_STOP  # let the quick stop finish (-> switch on disabled)
    if want is Want.DISABLED:
        return CMD_SWITCH_ON if state is PowerState.OPERATION_ENABLED else CMD_SHUTDOWN
    # want ENABLED
    if state is PowerState.SWITCH_ON_DISABLED:
        return CMD_SHUTDOWN
    if state is PowerState.READY_TO_SWITCH_ON:
        return CMD_SWITCH_ON
    return CMD_ENABLE_OPERATION  # switched on -> enable; enabled -> stay


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
    _encode_torque: Callable[[float], int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (self.torque_constant_nm_per_a > 0.0 and math.isfinite(self.rated_torque_nm)):
            raise InvalidValueError("k_t must be > 0 and the rated torque finite")
        if not self.rated_torque_nm > 0.0:
            raise InvalidValueError(f"rated torque must be > 0 N m, got {self.rated_torque_nm!r}")
        if not 0 < self.max_torque_permille <= 32767:
            raise InvalidValueError(
                f"max torque must be 1..32767 per mille: {self.max_torque_permille}"
            )
        # 0x6071's codec: per mille of 0x6076 (the other two references do not enter it).
        units = codec.DriveUnits(self.rated_torque_nm, rated_current_a=1.0, increments_per_rev=1.0)
        object.__setattr__(self, "_encode_torque", codec.torque(units).encoder())

    def target_permille(self, current_a: float) -> tuple[int, bool]:
        """The target torque (0x6071) for a finite current command, and whether it was clamped."""
        permille = self._encode_torque(self.torque_constant_nm_per_a * current_a)
        limit = self.max_torque_permille
        if permille > limit:
            return limit, True
        if permille < -limit:
            return -limit, True
        return permille, False
