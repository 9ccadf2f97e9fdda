"""CiA 402 drive logic: the power state machine, statusword, torque demand (pure core).

What a CiA 402 servo drive decides, with no bus and no clock: how a controlword moves the power
state machine (CiA 402-2 transitions 0-16), what the statusword reports, the modes 0x6060 may
select (0, 9 = CSV, 10 = CST) and the torque the drive may apply; also the CiA 301 PDO mapping
and heartbeat-consumer entries. States are frozen values; every function returns a new one.
The rack (`lca_sim.canbus.virtual_rack`) is the shell around it (docs/can.md, "The virtual
drive rack").

    state = settle(Cia402AxisState(), standstill=True, quick_stop_option=2)  # SWITCH_ON_DISABLED
    state = apply_controlword(state, 0x06, quick_stop_option=2)          # -> READY_TO_SWITCH_ON
    statusword(state, target_reached=False, internal_limit=False)        # -> 0x0231
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, replace

# --- modes of operation (CiA 402-2 0x6060) ---

MODE_NONE = 0
MODE_PP = 1  # profile position (`mode_pp`)
MODE_PV = 3  # profile velocity (`mode_pv`)
MODE_HM = 6  # homing (`homing`)
MODE_CSP = 8  # cyclic synchronous position (`mode_csp`)
MODE_CSV = 9  # cyclic synchronous velocity: the drive closes the velocity loop (0x60FF)
MODE_CST = 10  # cyclic synchronous torque
# The profile modes and CSP: their logic is in mode_pp, mode_pv, homing and mode_csp, and a
# halt there is the mode's own ramp (the loops keep the demand), not zero torque.
PROFILE_MODES: frozenset[int] = frozenset({MODE_PP, MODE_PV, MODE_HM, MODE_CSP})
# Modes a write of 0x6060 may select; the others (reserved, manufacturer-specific) are refused
# with SDO abort 0x06090030 (value range exceeded).
SUPPORTED_MODES: frozenset[int] = frozenset({MODE_NONE, MODE_CSV, MODE_CST}) | PROFILE_MODES
# The modes in which the drive follows a cyclic target (the torque, or its velocity loop's).
CYCLIC_MODES: frozenset[int] = frozenset({MODE_CSV, MODE_CST})


def supported_drive_modes_bits(modes: frozenset[int]) -> int:
    """0x6502 (CiA 402-2) for a set of modes: bit n - 1 for mode n > 0."""
    return sum(1 << (mode - 1) for mode in modes if mode > 0)


# 0x6502 of the drive: bits 0 PP, 2 PV, 5 HM, 7 CSP, 8 CSV, 9 CST (0x03A5).
SUPPORTED_DRIVE_MODES_BITS = supported_drive_modes_bits(SUPPORTED_MODES)

# --- controlword bits (CiA 402-2 0x6040) ---

CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low: 0 commands a quick stop
CW_ENABLE_OPERATION = 1 << 3
CW_FAULT_RESET = 1 << 7  # acts on its rising edge only
CW_HALT = 1 << 8

# --- statusword bits (CiA 402-2 0x6041) ---

SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low: 0 while a quick stop is active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_REMOTE = 1 << 9  # the drive follows the controlword it receives over the bus
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11  # the torque demand is being clamped to 0x6072
SW_FOLLOWS_COMMAND = 1 << 12  # cyclic synchronous modes: the drive follows the target

# Masks a master uses to read the state out of a statusword (the standard's table).
SW_MASK_WITH_QUICK_STOP = 0x6F  # ready to switch on, switched on, operation enabled, quick stop
SW_MASK = 0x4F  # the others

# |torque actual - torque demand| within which statusword bit 10 says "target reached".
TARGET_TORQUE_WINDOW_PERMILLE = 10

# --- abort connection option codes (CiA 402-2 0x6007) ---

ABORT_NONE = 0
ABORT_FAULT = 1
ABORT_DISABLE_VOLTAGE = 2
ABORT_QUICK_STOP = 3
ABORT_OPTIONS: frozenset[int] = frozenset(
    {ABORT_NONE, ABORT_FAULT, ABORT_DISABLE_VOLTAGE, ABORT_QUICK_STOP}
)

# 0x605A quick stop option codes: 0 disable drive function; 1-4 stop, then switch on disabled;
# 5-8 stop and stay in quick stop active. In CST, "stop" is torque 0: the gear brakes.
QUICK_STOP_OPTIONS: frozenset[int] = frozenset(range(9))
_LAST_QUICK_STOP_TO_DISABLED = 4

# --- EMCY error codes (CiA 301 / 402) and the error register (0x1001) ---

EMCY_ERROR_RESET = 0x0000
EMCY_HEARTBEAT = 0x8130  # life guard or heartbeat error
EMCY_RPDO_TIMEOUT = 0x8250
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error (shorter than its mapping)
EMCY_PDO_LENGTH_EXCEEDED = 0x8220  # PDO length exceeded (longer than its mapping)
EMCY_SYNC_LENGTH = 0x8240  # unexpected SYNC data length
# Communication, generic: SYNCs come faster than the communication cycle period 0x1006 (a
# second SYNC producer on the bus); the excess ones do not advance the plant (`sync_rate`).
EMCY_SYNC_TOO_FAST = 0x8100
# Device specific (CiA 301: 0xFF00-0xFFFF), documented in docs/can.md: the node left NMT
# OPERATIONAL (NMT stop, enter pre-operational, reset communication) while its drive could
# produce torque, and the 0x6007 reaction acted. CiA 301 / 402 define no code for it.
EMCY_LEFT_OPERATIONAL = 0xFF01
# Device specific: the drive's process stood still longer than the watchdogs may discount
# (the virtual rack's `max_stall_discount_s`); bytes 3-4 of the EMCY: the stall in ms.
EMCY_PROCESS_STALL = 0xFF02
EMCY_SYNC_LOSS = 0x8700  # sync controller error (no SYNC within the watch time)
ERROR_REGISTER_GENERIC = 1 << 0
ERROR_REGISTER_COMMUNICATION = 1 << 4


class PowerState(enum.Enum):
    """The power states of the CiA 402 state machine; values are the names masters use."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


class Command(enum.Enum):
    """A device control command decoded from the controlword (bits 0-3 and 7)."""

    NONE = "none"  # fault-reset bit held high: the other bits are ignored
    DISABLE_VOLTAGE = "disable voltage"  # xxxx xx0x
    QUICK_STOP = "quick stop"  # xxxx x01x
    SHUTDOWN = "shutdown"  # xxxx x110
    SWITCH_ON = "switch on"  # xxxx 0111; from OPERATION ENABLED this is "disable operation"
    ENABLE_OPERATION = "enable operation"  # xxxx 1111; from READY TO SWITCH ON: switch on too
    FAULT_RESET = "fault reset"  # rising edge of bit 7


_S = PowerState
_C = Command

# (state, command) -> next state, numbered as the transitions of the CiA 402 state diagram.
# A pair missing here is not a legal transition: the state stays as it is.
TRANSITIONS: Mapping[tuple[PowerState, Command], PowerState] = {
    (_S.SWITCH_ON_DISABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 2
    (_S.READY_TO_SWITCH_ON, _C.SWITCH_ON): _S.SWITCHED_ON,  # 3
    (_S.READY_TO_SWITCH_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 3 + 4
    (_S.SWITCHED_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 4
    (_S.OPERATION_ENABLED, _C.SWITCH_ON): _S.SWITCHED_ON,  # 5 (disable operation)
    (_S.SWITCHED_ON, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 6
    (_S.READY_TO_SWITCH_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 7
    (_S.READY_TO_SWITCH_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,  # 7
    (_S.OPERATION_ENABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 8
    (_S.OPERATION_ENABLED, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 9
    (_S.SWITCHED_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 10
    (_S.SWITCHED_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,  # 10
    (_S.OPERATION_ENABLED, _C.QUICK_STOP): _S.QUICK_STOP_ACTIVE,  # 11
    (_S.QUICK_STOP_ACTIVE, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 12
    (_S.FAULT, _C.FAULT_RESET): _S.SWITCH_ON_DISABLED,  # 15
    (_S.QUICK_STOP_ACTIVE, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 16 (options 5-8)
}

# Statusword bits 0-6 per state (with bit 4 "voltage enabled" where the power stage is live).
_STATE_BITS: Mapping[PowerState, int] = {
    _S.NOT_READY_TO_SWITCH_ON: 0x0000,
    _S.SWITCH_ON_DISABLED: 0x0040,
    _S.READY_TO_SWITCH_ON: 0x0031,
    _S.SWITCHED_ON: 0x0033,
    _S.OPERATION_ENABLED: 0x0037,
    _S.QUICK_STOP_ACTIVE: 0x0017,
    _S.FAULT_REACTION_ACTIVE: 0x001F,
    _S.FAULT: 0x0008,
}


@dataclass(frozen=True, slots=True)
class Cia402AxisState:
    """The CiA 402 logic state of one drive axis.

    Attributes:
        power: the power state.
        controlword: the last controlword applied (its bit 7 is the reference for the next
            fault-reset edge, its bit 8 is halt).
        mode: modes of operation (0x6060), one of `SUPPORTED_MODES`.
    """

    power: PowerState = PowerState.NOT_READY_TO_SWITCH_ON
    controlword: int = 0
    mode: int = MODE_CST

    @property
    def halted(self) -> bool:
        """Controlword bit 8: hold the axis (in CST: torque 0) while operation stays enabled."""
        return bool(self.controlword & CW_HALT)


@dataclass(frozen=True, slots=True)
class TorqueDemand:
    """What the drive applies for a target torque.

    Attributes:
        permille: torque demand, per mille of the motor rated torque (0x6076).
        limited: True when the target was clamped to the max torque 0x6072 (statusword bit 11).
    """

    permille: int
    limited: bool


def decode_command(controlword: int, previous_controlword: int) -> Command:
    """The device control command of a controlword, given the one applied before it.

    Fault reset acts on the rising edge of bit 7 only; while bit 7 stays high the other bits are
    ignored (the standard's command table defines them with bit 7 = 0).
    """
    if controlword & CW_FAULT_RESET:
        return Command.NONE if previous_controlword & CW_FAULT_RESET else Command.FAULT_RESET
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not controlword & CW_SWITCH_ON:
        return Command.SHUTDOWN
    if not controlword & CW_ENABLE_OPERATION:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


def next_power_state(power: PowerState, command: Command, quick_stop_option: int) -> PowerState:
    """The state a command leads to from `power`; an illegal command leaves it unchanged.

    Transition 16 (quick stop active -> operation enabled) exists only for quick stop option
    codes 5-8; with 0-4 the drive goes on to switch on disabled instead.
    """
    if (
        power is PowerState.QUICK_STOP_ACTIVE
        and command is Command.ENABLE_OPERATION
        and quick_stop_option <= _LAST_QUICK_STOP_TO_DISABLED
    ):
        return power
    return TRANSITIONS.get((power, command), power)


def apply_controlword(
    state: Cia402AxisState, controlword: int, quick_stop_option: int
) -> Cia402AxisState:
    """Apply a controlword (by SDO, or by RPDO at a SYNC): the state it leads to."""
    command = decode_command(controlword, state.controlword)
    power = next_power_state(state.power, command, quick_stop_option)
    return replace(state, power=power, controlword=controlword & 0xFFFF)


def is_fault_reset_edge(controlword: int, previous_controlword: int) -> bool:
    """True when `controlword` raises bit 7 (the drive then clears its error register)."""
    return decode_command(controlword, previous_controlword) is Command.FAULT_RESET


def fault(state: Cia402AxisState) -> Cia402AxisState:
    """A fault occurred (transition 13): fault reaction active, unless already faulted."""
    if state.power in (PowerState.FAULT_REACTION_ACTIVE, PowerState.FAULT):
        return state
    return replace(state, power=PowerState.FAULT_REACTION_ACTIVE)


def abort_connection(
    state: Cia402AxisState, option: int, quick_stop_option: int
) -> Cia402AxisState:
    """The 0x6007 reaction to a lost connection (heartbeat, RPDO deadline, SYNC, NMT stop).

    The reaction acts on a drive that can produce torque (operation enabled, quick stop
    active); a drive whose power stage is off has nothing to stop, so it stays as it is (the
    shell still reports the error by EMCY and 0x603F).

    Args:
        state: the drive state before the reaction.
        option: 0 none, 1 fault, 2 disable voltage command, 3 quick stop command.
        quick_stop_option: 0x605A, for the quick stop command.

    Returns:
        The state after the reaction.
    """
    if state.power not in (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE):
        return state
    if option == ABORT_FAULT:
        return fault(state)
    if option == ABORT_DISABLE_VOLTAGE:
        command = Command.DISABLE_VOLTAGE
    elif option == ABORT_QUICK_STOP:
        command = Command.QUICK_STOP
    else:
        return state
    return replace(state, power=next_power_state(state.power, command, quick_stop_option))


# The states `settle` may leave: in any other it returns the state as it is. A tuple: its
# `in` compares by identity in C, where a set would hash the enum in Python (at every SYNC).
SETTLING_STATES: tuple[PowerState, ...] = (
    PowerState.NOT_READY_TO_SWITCH_ON,
    PowerState.FAULT_REACTION_ACTIVE,
    PowerState.QUICK_STOP_ACTIVE,
)


def settle(state: Cia402AxisState, *, standstill: bool, quick_stop_option: int) -> Cia402AxisState:
    """Take the automatic transitions that are due.

    0/1: not ready to switch on -> switch on disabled (the self-test of a simulated drive
    passes at once); 14: fault reaction active -> fault (the reaction, torque off, is immediate);
    quick stop active -> switch on disabled (transition 12) once the axis stands still, for
    quick stop options 1-4, and at once for option 0.

    Args:
        state: the drive state.
        standstill: the axis is not moving (the plant's motion state is stopped).
        quick_stop_option: 0x605A.
    """
    power = state.power
    if power is PowerState.NOT_READY_TO_SWITCH_ON:
        power = PowerState.SWITCH_ON_DISABLED
    elif power is PowerState.FAULT_REACTION_ACTIVE:
        power = PowerState.FAULT
    elif power is PowerState.QUICK_STOP_ACTIVE and (
        quick_stop_option == 0 or (standstill and quick_stop_option <= _LAST_QUICK_STOP_TO_DISABLED)
    ):
        power = PowerState.SWITCH_ON_DISABLED
    return state if power is state.power else replace(state, power=power)


def torque_demand(state: Cia402AxisState, target_permille: int, max_permille: int) -> TorqueDemand:
    """The torque the drive applies, per mille of rated torque (CST, and CSV).

    Zero unless operation is enabled in a cyclic mode without halt; otherwise the target (in
    CSV: the velocity loop's output) clamped to +-`max_permille` (0x6072).
    """
    if state.power is not PowerState.OPERATION_ENABLED or state.mode not in CYCLIC_MODES:
        return TorqueDemand(0, False)
    if state.halted:
        return TorqueDemand(0, False)
    if abs(target_permille) > max_permille:
        return TorqueDemand(max_permille if target_permille > 0 else -max_permille, True)
    return TorqueDemand(target_permille, False)


def statusword(state: Cia402AxisState, *, target_reached: bool, internal_limit: bool) -> int:
    """The statusword (0x6041) of a drive in `state`.

    Bits 0-6 encode the power state (read them with `SW_MASK_WITH_QUICK_STOP` or `SW_MASK`),
    bit 9 (remote) is always set, bit 10 and 11 come from the caller, bit 12 says the drive
    follows the target torque (operation enabled in CST, no halt).
    """
    word = _STATE_BITS[state.power] | SW_REMOTE
    if target_reached:
        word |= SW_TARGET_REACHED
    if internal_limit:
        word |= SW_INTERNAL_LIMIT
    enabled = state.power is PowerState.OPERATION_ENABLED
    if enabled and state.mode in CYCLIC_MODES and not state.halted:
        word |= SW_FOLLOWS_COMMAND
    return word


def _decode_power_state(word: int) -> PowerState | None:
    """CiA 402 Table 30 read literally: the first state whose masked bits match, or None."""
    for power, bits in _STATE_BITS.items():
        mask = SW_MASK_WITH_QUICK_STOP if power in _QUICK_STOP_BIT_STATES else SW_MASK
        if word & mask == bits & mask:
            return power
    return None


# The power state depends on bits 0-6 only: decoded once per pattern, looked up per statusword
# (the master reads four per cycle; the loop above was a tenth of its cycle).
_QUICK_STOP_BIT_STATES = frozenset(
    (
        PowerState.READY_TO_SWITCH_ON,
        PowerState.SWITCHED_ON,
        PowerState.OPERATION_ENABLED,
        PowerState.QUICK_STOP_ACTIVE,
    )
)
_POWER_BY_LOW_BITS: tuple[PowerState | None, ...] = tuple(
    _decode_power_state(bits) for bits in range(0x80)
)


def power_state_of(word: int) -> PowerState | None:
    """The power state a statusword reports (the master's view), or None if it is malformed."""
    return _POWER_BY_LOW_BITS[word & 0x7F]


def is_supported_mode(mode: int) -> bool:
    """True for the modes of operation a write of 0x6060 may select (`SUPPORTED_MODES`).

    0 no mode, 1 PP, 3 PV, 6 HM, 8 CSP, 9 CSV, 10 CST.
    """
    return mode in SUPPORTED_MODES


# --- CiA 301 codecs ------------------------------------------------------------------------

PDO_COB_ID_INVALID = 1 << 31  # sub 1 of a PDO communication object: the PDO does not exist
PDO_COB_ID_NO_RTR = 1 << 30
PDO_COB_ID_EXTENDED = 1 << 29
PDO_MAX_ENTRIES = 8
PDO_MAX_BITS = 64
SYNC_TRANSMISSION_MAX = 240  # 0-240: synchronous; 254/255: event driven
TRANSMISSION_EVENT_TYPES = frozenset({254, 255})


@dataclass(frozen=True, slots=True)
class MappingEntry:
    """One entry of a PDO mapping object: which object, and its length in bits."""

    index: int
    subindex: int
    bits: int

    @classmethod
    def decode(cls, value: int) -> MappingEntry:
        """From the u32 written to a mapping object (index << 16 | sub-index << 8 | bits)."""
        return cls((value >> 16) & 0xFFFF, (value >> 8) & 0xFF, value & 0xFF)

    def encode(self) -> int:
        """The u32 of the mapping object."""
        return (self.index << 16) | (self.subindex << 8) | self.bits


def heartbeat_consumer_entry(value: int) -> tuple[int, int]:
    """A 0x1016 entry -> (producer node id, consumer time ms); either 0 means unused."""
    return (value >> 16) & 0x7F, value & 0xFFFF


def is_valid_transmission_type(transmission_type: int) -> bool:
    """0-240 synchronous, 254/255 event driven; the RTR-only types 252/253 are not supported."""
    return (
        0 <= transmission_type <= SYNC_TRANSMISSION_MAX
        or transmission_type in TRANSMISSION_EVENT_TYPES
    )
