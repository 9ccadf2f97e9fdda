"""The pure CiA 402 core: state machine table, statusword, torque demand, CiA 301 codecs.

The units (per mille, increments, efficiency) are tested with the object table in
test_objects_codec.py.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim.cia402 import device as cia402
from lca_sim.cia402.device import Cia402AxisState, Command, MappingEntry, PowerState

S = PowerState
QUICK_STOP_TO_DISABLED = 2  # 0x605A default: stop, then switch on disabled
QUICK_STOP_STAY = 6  # 0x605A 5-8: stop, stay in quick stop active


def _in(power: PowerState, controlword: int = 0, mode: int = cia402.MODE_CST) -> Cia402AxisState:
    return Cia402AxisState(power=power, controlword=controlword, mode=mode)


@pytest.mark.parametrize(
    ("controlword", "previous", "command"),
    [
        (0x0006, 0x0000, Command.SHUTDOWN),
        (0x0007, 0x0006, Command.SWITCH_ON),
        (0x000F, 0x0007, Command.ENABLE_OPERATION),
        (0x0000, 0x000F, Command.DISABLE_VOLTAGE),
        (0x0004, 0x000F, Command.DISABLE_VOLTAGE),  # bit 1 low wins over the rest
        (0x0002, 0x000F, Command.QUICK_STOP),
        (0x000B, 0x000F, Command.QUICK_STOP),  # bit 2 is active low
        (0x010F, 0x000F, Command.ENABLE_OPERATION),  # halt does not change the command
        (0x0080, 0x0000, Command.FAULT_RESET),  # rising edge of bit 7
        (0x0080, 0x0080, Command.NONE),  # held high: no second reset, other bits ignored
        (0x008F, 0x0080, Command.NONE),
        (0x0086, 0x000F, Command.FAULT_RESET),
    ],
)
def test_decode_command(controlword: int, previous: int, command: Command) -> None:
    """Controlword bits 0-3 and the edge of bit 7 give the standard's device control commands."""
    assert cia402.decode_command(controlword, previous) is command


# (from, controlword, to): every numbered transition, and illegal jumps that change nothing.
TRANSITION_CASES = [
    (S.SWITCH_ON_DISABLED, 0x06, S.READY_TO_SWITCH_ON),  # 2
    (S.READY_TO_SWITCH_ON, 0x07, S.SWITCHED_ON),  # 3
    (S.READY_TO_SWITCH_ON, 0x0F, S.OPERATION_ENABLED),  # 3 + 4
    (S.SWITCHED_ON, 0x0F, S.OPERATION_ENABLED),  # 4
    (S.OPERATION_ENABLED, 0x07, S.SWITCHED_ON),  # 5
    (S.SWITCHED_ON, 0x06, S.READY_TO_SWITCH_ON),  # 6
    (S.READY_TO_SWITCH_ON, 0x00, S.SWITCH_ON_DISABLED),  # 7
    (S.READY_TO_SWITCH_ON, 0x02, S.SWITCH_ON_DISABLED),  # 7 (quick stop)
    (S.OPERATION_ENABLED, 0x06, S.READY_TO_SWITCH_ON),  # 8
    (S.OPERATION_ENABLED, 0x00, S.SWITCH_ON_DISABLED),  # 9
    (S.SWITCHED_ON, 0x00, S.SWITCH_ON_DISABLED),  # 10
    (S.SWITCHED_ON, 0x02, S.SWITCH_ON_DISABLED),  # 10 (quick stop)
    (S.OPERATION_ENABLED, 0x02, S.QUICK_STOP_ACTIVE),  # 11
    (S.QUICK_STOP_ACTIVE, 0x00, S.SWITCH_ON_DISABLED),  # 12
    (S.FAULT, 0x80, S.SWITCH_ON_DISABLED),  # 15
    # illegal: the state stays
    (S.SWITCH_ON_DISABLED, 0x0F, S.SWITCH_ON_DISABLED),
    (S.SWITCH_ON_DISABLED, 0x07, S.SWITCH_ON_DISABLED),
    (S.READY_TO_SWITCH_ON, 0x06, S.READY_TO_SWITCH_ON),
    (S.FAULT, 0x0F, S.FAULT),
    (S.FAULT, 0x06, S.FAULT),
    (S.FAULT_REACTION_ACTIVE, 0x80, S.FAULT_REACTION_ACTIVE),
    (S.QUICK_STOP_ACTIVE, 0x0F, S.QUICK_STOP_ACTIVE),  # 16 needs option 5-8
    (S.OPERATION_ENABLED, 0x80, S.OPERATION_ENABLED),  # a reset edge outside FAULT
    (S.NOT_READY_TO_SWITCH_ON, 0x06, S.NOT_READY_TO_SWITCH_ON),
]


@pytest.mark.parametrize(("start", "controlword", "end"), TRANSITION_CASES)
def test_controlword_transitions(start: PowerState, controlword: int, end: PowerState) -> None:
    """Each controlword moves the state as the CiA 402 diagram says, or not at all."""
    state = cia402.apply_controlword(_in(start), controlword, QUICK_STOP_TO_DISABLED)
    assert state.power is end
    assert state.controlword == controlword


def test_transition_16_needs_a_quick_stop_option_that_stays() -> None:
    """Quick stop active -> operation enabled only with 0x605A in 5-8."""
    state = cia402.apply_controlword(_in(S.QUICK_STOP_ACTIVE, 0x02), 0x0F, QUICK_STOP_STAY)
    assert state.power is S.OPERATION_ENABLED


def test_enable_walk_and_statuswords() -> None:
    """Boot, 0x06, 0x07, 0x0F: statusword masked with 0x6F reads 0x21, 0x23, 0x27."""
    state = cia402.settle(Cia402AxisState(), standstill=True, quick_stop_option=2)
    assert state.power is S.SWITCH_ON_DISABLED
    words = [cia402.statusword(state, target_reached=False, internal_limit=False)]
    for controlword in (0x06, 0x07, 0x0F):
        state = cia402.apply_controlword(state, controlword, QUICK_STOP_TO_DISABLED)
        words.append(cia402.statusword(state, target_reached=False, internal_limit=False))
    assert words == [0x0240, 0x0231, 0x0233, 0x1237]
    assert [w & 0x4F for w in words[:1]] == [0x40]
    assert [w & 0x6F for w in words[1:]] == [0x21, 0x23, 0x27]


@pytest.mark.parametrize(
    ("power", "word"),
    [
        (S.NOT_READY_TO_SWITCH_ON, 0x0200),
        (S.SWITCH_ON_DISABLED, 0x0240),
        (S.READY_TO_SWITCH_ON, 0x0231),
        (S.SWITCHED_ON, 0x0233),
        (S.OPERATION_ENABLED, 0x1237),
        (S.QUICK_STOP_ACTIVE, 0x0217),
        (S.FAULT_REACTION_ACTIVE, 0x021F),
        (S.FAULT, 0x0208),
    ],
)
def test_statusword_per_state_and_back(power: PowerState, word: int) -> None:
    """Each state's statusword, and a master's mask reading gives the state back."""
    assert cia402.statusword(_in(power), target_reached=False, internal_limit=False) == word
    assert cia402.power_state_of(word) is power


# CiA 402 (IEC 61800-7-201) Table 30, statusword bits 6..0 as (mask, value): written out here
# independently of the drive's table.
_TABLE_30 = (
    (0b1001111, 0b0000000, S.NOT_READY_TO_SWITCH_ON),
    (0b1001111, 0b1000000, S.SWITCH_ON_DISABLED),
    (0b1101111, 0b0100001, S.READY_TO_SWITCH_ON),
    (0b1101111, 0b0100011, S.SWITCHED_ON),
    (0b1101111, 0b0100111, S.OPERATION_ENABLED),
    (0b1101111, 0b0000111, S.QUICK_STOP_ACTIVE),
    (0b1001111, 0b0001111, S.FAULT_REACTION_ACTIVE),
    (0b1001111, 0b0001000, S.FAULT),
)


def test_every_statusword_decodes_as_table_30_says() -> None:
    """All 65,536 words: the state of the one Table 30 pattern that matches, else None."""
    undefined = 0
    for word in range(0x10000):
        matches = [state for mask, value, state in _TABLE_30 if word & mask == value]
        assert len(matches) <= 1, f"0x{word:04X} matches {matches}"
        expected = matches[0] if matches else None
        undefined += expected is None
        assert cia402.power_state_of(word) is expected, f"0x{word:04X}"
    # Defined: 4 states x 4 (bits 4, 5 free) + 4 states x 2 (bit 4 free) = 24 of 128 patterns.
    assert undefined == 0x10000 * 104 // 128


def test_statusword_flags() -> None:
    """Bit 10 target reached, bit 11 internal limit, bit 12 only when following the target."""
    enabled = _in(S.OPERATION_ENABLED, 0x0F)
    assert cia402.statusword(enabled, target_reached=True, internal_limit=True) == 0x1E37
    halted = _in(S.OPERATION_ENABLED, 0x010F)
    assert cia402.statusword(halted, target_reached=False, internal_limit=False) == 0x0237
    no_mode = _in(S.OPERATION_ENABLED, 0x0F, mode=cia402.MODE_NONE)
    assert cia402.statusword(no_mode, target_reached=False, internal_limit=False) == 0x0237


@pytest.mark.parametrize(
    ("option", "start", "end"),
    [
        (cia402.ABORT_NONE, S.OPERATION_ENABLED, S.OPERATION_ENABLED),
        (cia402.ABORT_FAULT, S.OPERATION_ENABLED, S.FAULT_REACTION_ACTIVE),
        (cia402.ABORT_FAULT, S.QUICK_STOP_ACTIVE, S.FAULT_REACTION_ACTIVE),
        (cia402.ABORT_DISABLE_VOLTAGE, S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED),
        (cia402.ABORT_DISABLE_VOLTAGE, S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED),
        (cia402.ABORT_QUICK_STOP, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE),
        # power stage off: nothing to react on
        (cia402.ABORT_FAULT, S.SWITCH_ON_DISABLED, S.SWITCH_ON_DISABLED),
        (cia402.ABORT_FAULT, S.SWITCHED_ON, S.SWITCHED_ON),
        (cia402.ABORT_FAULT, S.FAULT, S.FAULT),
        (cia402.ABORT_DISABLE_VOLTAGE, S.READY_TO_SWITCH_ON, S.READY_TO_SWITCH_ON),
        (cia402.ABORT_QUICK_STOP, S.SWITCHED_ON, S.SWITCHED_ON),
    ],
)
def test_abort_connection_reactions(option: int, start: PowerState, end: PowerState) -> None:
    """0x6007 on a torque-producing drive: 0 nothing, 1 fault, 2 disable voltage, 3 quick stop."""
    state = cia402.abort_connection(_in(start, 0x0F), option, QUICK_STOP_TO_DISABLED)
    assert state.power is end


@pytest.mark.parametrize(
    ("start", "standstill", "option", "end"),
    [
        (S.NOT_READY_TO_SWITCH_ON, False, 2, S.SWITCH_ON_DISABLED),  # 0/1
        (S.FAULT_REACTION_ACTIVE, False, 2, S.FAULT),  # 14
        (S.QUICK_STOP_ACTIVE, False, 2, S.QUICK_STOP_ACTIVE),  # still moving
        (S.QUICK_STOP_ACTIVE, True, 2, S.SWITCH_ON_DISABLED),  # 12, once stopped
        (S.QUICK_STOP_ACTIVE, False, 0, S.SWITCH_ON_DISABLED),  # option 0: at once
        (S.QUICK_STOP_ACTIVE, True, 6, S.QUICK_STOP_ACTIVE),  # 5-8: stays
        (S.OPERATION_ENABLED, True, 2, S.OPERATION_ENABLED),
    ],
)
def test_automatic_transitions(
    start: PowerState, standstill: bool, option: int, end: PowerState
) -> None:
    """settle() takes the transitions no command triggers."""
    assert cia402.settle(_in(start), standstill=standstill, quick_stop_option=option).power is end


def test_fault_from_fault_reaction_to_reset() -> None:
    """Fault, the automatic 14, then only a rising edge of bit 7 leaves FAULT."""
    state = cia402.fault(_in(S.OPERATION_ENABLED, 0x0F))
    assert state.power is S.FAULT_REACTION_ACTIVE
    state = cia402.settle(state, standstill=False, quick_stop_option=2)
    assert state.power is S.FAULT
    state = cia402.apply_controlword(replace(state, controlword=0x80), 0x80, 2)  # held high
    assert state.power is S.FAULT
    state = cia402.apply_controlword(state, 0x00, 2)
    state = cia402.apply_controlword(state, 0x80, 2)
    assert state.power is S.SWITCH_ON_DISABLED
    assert cia402.is_fault_reset_edge(0x80, 0x00)
    assert not cia402.is_fault_reset_edge(0x80, 0x80)


@pytest.mark.parametrize(
    ("state", "target", "maximum", "demand"),
    [
        (_in(S.OPERATION_ENABLED, 0x0F), 250, 2000, cia402.TorqueDemand(250, False)),
        (_in(S.OPERATION_ENABLED, 0x0F), -250, 2000, cia402.TorqueDemand(-250, False)),
        (_in(S.OPERATION_ENABLED, 0x0F), 2500, 2000, cia402.TorqueDemand(2000, True)),
        (_in(S.OPERATION_ENABLED, 0x0F), -700, 500, cia402.TorqueDemand(-500, True)),
        (_in(S.OPERATION_ENABLED, 0x010F), 250, 2000, cia402.TorqueDemand(0, False)),  # halt
        (_in(S.SWITCHED_ON, 0x07), 250, 2000, cia402.TorqueDemand(0, False)),
        (_in(S.QUICK_STOP_ACTIVE, 0x02), 250, 2000, cia402.TorqueDemand(0, False)),
        (_in(S.FAULT), 250, 2000, cia402.TorqueDemand(0, False)),
        (_in(S.OPERATION_ENABLED, 0x0F, mode=0), 250, 2000, cia402.TorqueDemand(0, False)),
    ],
)
def test_torque_demand(
    state: Cia402AxisState, target: int, maximum: int, demand: cia402.TorqueDemand
) -> None:
    """Torque only when enabled in CST without halt, clamped to 0x6072."""
    assert cia402.torque_demand(state, target, maximum) == demand


def test_supported_modes_are_the_profile_and_cyclic_modes() -> None:
    """0x6502 = bits 0, 2, 5, 7, 8, 9 (bit n - 1 for mode n): PP, PV, HM, CSP, CSV, CST."""
    assert sorted(cia402.PROFILE_MODES) == [1, 3, 6, 8]
    assert all(cia402.is_supported_mode(m) for m in (0, 1, 3, 6, 8, 9, 10))
    assert not any(cia402.is_supported_mode(m) for m in (-1, 2, 4, 5, 7, 11, 127))
    assert cia402.supported_drive_modes_bits(cia402.SUPPORTED_MODES) == 0x03A5


@given(
    st.integers(min_value=0, max_value=0xFFFF),
    st.integers(min_value=0, max_value=0xFF),
    st.integers(min_value=0, max_value=0xFF),
)
def test_mapping_entry_round_trip(index: int, subindex: int, bits: int) -> None:
    """A mapping entry survives encode then decode, for every u32 a mapping object holds."""
    entry = MappingEntry(index, subindex, bits)
    assert MappingEntry.decode(entry.encode()) == entry


def test_mapping_and_heartbeat_entries() -> None:
    """The default RPDO1 entries and the default heartbeat consumer, decoded."""
    assert MappingEntry.decode(0x60400010) == MappingEntry(0x6040, 0, 16)
    assert MappingEntry.decode(0x60640020) == MappingEntry(0x6064, 0, 32)
    assert cia402.heartbeat_consumer_entry(0x007F00FA) == (127, 250)
    assert [cia402.is_valid_transmission_type(t) for t in (0, 1, 240, 241, 253, 254, 255)] == [
        True,
        True,
        True,
        False,
        False,
        True,
        True,
    ]
