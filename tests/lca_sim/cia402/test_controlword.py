"""What a CiA 402 master commands (`lca_sim.cia402.controlword`): statusword, walk, torque."""

from __future__ import annotations

import pytest

from lca_sim.cia402 import controlword as ctl
from lca_sim.cia402.controlword import TorqueScale, Want
from lca_sim.cia402.device import PowerState


@pytest.mark.parametrize(
    ("statusword", "state"),
    [
        (0x0000, PowerState.NOT_READY_TO_SWITCH_ON),
        (0x0250, PowerState.SWITCH_ON_DISABLED),  # remote + quick stop bits set, as drives send
        (0x0231, PowerState.READY_TO_SWITCH_ON),
        (0x0233, PowerState.SWITCHED_ON),
        (0x0237, PowerState.OPERATION_ENABLED),
        (0x0637, PowerState.OPERATION_ENABLED),  # with target reached
        (0x0217, PowerState.QUICK_STOP_ACTIVE),
        (0x021F, PowerState.FAULT_REACTION_ACTIVE),
        (0x0218, PowerState.FAULT),
        (0x0208, PowerState.FAULT),
    ],
)
def test_statusword_patterns_of_cia402(statusword: int, state: PowerState) -> None:
    assert ctl.power_state(statusword) is state


def _drive(state: PowerState, controlword: int) -> PowerState:
    """The transitions of CiA 402 a conforming drive makes (the ones the walk needs)."""
    command = controlword & 0x8F
    table = {
        (PowerState.SWITCH_ON_DISABLED, 0x06): PowerState.READY_TO_SWITCH_ON,
        (PowerState.READY_TO_SWITCH_ON, 0x07): PowerState.SWITCHED_ON,
        (PowerState.SWITCHED_ON, 0x0F): PowerState.OPERATION_ENABLED,
        (PowerState.OPERATION_ENABLED, 0x07): PowerState.SWITCHED_ON,
        (PowerState.SWITCHED_ON, 0x06): PowerState.READY_TO_SWITCH_ON,
        (PowerState.OPERATION_ENABLED, 0x02): PowerState.QUICK_STOP_ACTIVE,
        (PowerState.QUICK_STOP_ACTIVE, 0x02): PowerState.SWITCH_ON_DISABLED,
        (PowerState.FAULT, 0x80): PowerState.SWITCH_ON_DISABLED,
    }
    return table.get((state, command), state)


def test_enable_walk_is_06_07_0f_and_back() -> None:
    state, controlword, sent = PowerState.SWITCH_ON_DISABLED, 0, []
    for _ in range(5):
        controlword = ctl.next_controlword(state, Want.ENABLED, controlword)
        sent.append(controlword)
        state = _drive(state, controlword)
    assert sent == [0x06, 0x07, 0x0F, 0x0F, 0x0F]
    assert state is PowerState.OPERATION_ENABLED
    controlword = ctl.next_controlword(state, Want.DISABLED, controlword)
    assert controlword == 0x07
    state = _drive(state, controlword)
    assert ctl.next_controlword(state, Want.DISABLED, controlword) == 0x06


def test_fault_reset_is_a_rising_edge_then_the_walk() -> None:
    state, controlword, sent = PowerState.FAULT, 0x0F, []
    for _ in range(3):
        controlword = ctl.next_controlword(state, Want.FAULT_RESET, controlword)
        sent.append(controlword)
        state = _drive(state, controlword)
    # bit 7 was high before (0x0F has it low): edge at once; then no second edge is needed
    assert sent[0] == 0x80
    assert state is PowerState.READY_TO_SWITCH_ON
    # starting from a controlword that already had bit 7 high, it first drops the bit
    assert ctl.next_controlword(PowerState.FAULT, Want.FAULT_RESET, 0x80) == 0x00


def test_quick_stop_from_enabled_ends_switch_on_disabled() -> None:
    state, controlword = PowerState.OPERATION_ENABLED, 0x0F
    for _ in range(3):
        controlword = ctl.next_controlword(state, Want.QUICK_STOP, controlword)
        state = _drive(state, controlword)
    assert controlword == ctl.CMD_QUICK_STOP
    assert state is PowerState.SWITCH_ON_DISABLED
    # and a fault is never "quick stopped" out of (only a reset leaves it)
    assert ctl.next_controlword(PowerState.FAULT, Want.QUICK_STOP, 0) == ctl.CMD_DISABLE_VOLTAGE


def test_torque_scale_per_mille_and_clamp() -> None:
    scale = TorqueScale(
        torque_constant_nm_per_a=0.12, rated_torque_nm=1.2, max_torque_permille=2000
    )
    assert scale.target_permille(5.0) == (500, False)  # 0.6 N m of 1.2 N m rated
    assert scale.target_permille(-2.5) == (-250, False)
    assert scale.target_permille(0.104) == (10, False)  # rounds to the nearest per mille
    assert scale.target_permille(30.0) == (2000, True)  # 3.6 N m > 2 x rated
    assert scale.target_permille(-30.0) == (-2000, True)
    with pytest.raises(ValueError, match="rated torque"):
        TorqueScale(0.12, 0.0, 1000)
