"""The rack's CiA 402 side: each drive's power state, errors, torque demand and loop modes.

A part of the virtual drive rack over the pure logic of `lca_sim.cia402.device`: it applies a
controlword, a lost connection's 0x6007 reaction and the error objects (0x603F, 0x1001), and
turns the targets into the current the plant follows. docs/can.md, "The virtual drive rack".
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from lca_sim.canbus.rack_modes import LOOP_MODES, QUICK_STOP_RAMPS
from lca_sim.canbus.rack_state import Drive
from lca_sim.cia402 import device as cia402
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import Cia402AxisState, PowerState
from lca_sim.cia402.mode_common import EMCY_FOLLOWING_ERROR, SW_BIT13

_FAULT_STATES = frozenset({PowerState.FAULT_REACTION_ACTIVE, PowerState.FAULT})
# `Drive.values` keys read at every SYNC, looked up directly (no `Drive.value` call).
_MAX_TORQUE = (od.MAX_TORQUE, 0)
_TARGET_TORQUE = (od.TARGET_TORQUE, 0)


class DriveControl:
    """The CiA 402 state of every drive of a rack, over the plant's read-only arrays.

    Args:
        state, modes: the simulator's state and mode arrays (views it updates in place).
        emcy: sends an EMCY from a drive: (drive, code).
        reset_raised_emcy: switches off an injected EMCY at a fault reset: (drive, now).
    """

    def __init__(
        self,
        state: Any,
        modes: Any,
        emcy: Callable[[Drive, int], None],
        reset_raised_emcy: Callable[[Drive, float], None],
    ) -> None:
        self._state = state
        self._modes = modes
        self._emcy = emcy
        self._reset_raised_emcy = reset_raised_emcy

    # --- what the drive makes of its targets ---------------------------------------------

    def torque_actual_permille(self, axis: Drive) -> int:
        """0x6077: k_t x the plant's current, per mille of 0x6076."""
        current_a = float(self._state[2, axis.plant_index])
        return axis.torque.encode(axis.torque_constant_nm_per_a * current_a)

    def demand(self, axis: Drive) -> cia402.TorqueDemand:
        """The torque demand of the drive's mode (CST: 0x6071; the loop modes: their loops').

        In the profile modes and CSP a halt is the mode's own ramp and hold, so their loops
        keep the demand; CSV and CST give zero torque while halted (`cia402.torque_demand`).
        """
        drive = axis.drive
        max_permille = axis.values[_MAX_TORQUE]
        if drive.mode in cia402.PROFILE_MODES:
            running = drive.power is PowerState.OPERATION_ENABLED or axis.modes.quick_stopping
            if not running:
                return cia402.TorqueDemand(0, False)
            permille = axis.modes.permille
            if abs(permille) > max_permille:
                return cia402.TorqueDemand(max_permille if permille > 0 else -max_permille, True)
            return cia402.TorqueDemand(permille, False)
        target = axis.modes.permille if drive.mode == cia402.MODE_CSV else None
        return cia402.torque_demand(
            drive, axis.values[_TARGET_TORQUE] if target is None else target, max_permille
        )

    def run_loops(self, axis: Drive, dt_s: float, now: float) -> None:
        """The loop modes (CSV, PP, PV, HM, CSP): the drive's loops over one SYNC's span.

        Run once per SYNC that advances the plant, on the plant's joint state (`rack_modes`).
        Outside operation enabled, or halted in CSV, the loops rest and each mode starts again
        from the present state when enabled. A following error the mode reports (EMCY 0x8611)
        is the drive's fault reaction: error code, EMCY, FAULT. QUICK STOP ACTIVE in the
        profile modes and CSP ramps down (0x605A 1, 2, 5, 6: `AxisModes.quick_stop`).
        """
        drive = axis.drive
        a, state = axis.plant_index, self._state
        if (
            drive.power is PowerState.QUICK_STOP_ACTIVE
            and drive.mode in cia402.PROFILE_MODES
            and axis.value(od.QUICK_STOP_OPTION) in QUICK_STOP_RAMPS
        ):
            if dt_s > 0.0:
                joint = (float(state[0, a]), float(state[1, a]), float(state[2, a]))
                axis.modes.quick_stop(axis, dt_s, joint)
            return
        if drive.power is not PowerState.OPERATION_ENABLED or (
            drive.mode == cia402.MODE_CSV and drive.halted
        ):
            axis.modes.stop()
            return
        if dt_s <= 0.0:
            return
        code = axis.modes.run(
            axis, dt_s, (float(state[0, a]), float(state[1, a]), float(state[2, a]))
        )
        if code is not None:
            axis.values[(od.ERROR_CODE, 0)] = code
            axis.values[(od.ERROR_REGISTER, 0)] = axis.value(od.ERROR_REGISTER) | (
                od.error_register_for(code)
            )
            self._emcy(axis, code)
            self.set_drive(axis, cia402.fault(axis.drive), now)
            axis.modes.stop()

    def currents_a(self, axes: Sequence[Drive], span_s: float, now: float) -> list[float] | None:
        """Every drive's current setpoint, A, in plant order, after `span_s` of the loop modes.

        None when every power stage is off (the plant then holds zero current).
        """
        currents_a = [0.0] * len(axes)
        any_enabled = False
        for axis in axes:
            if axis.drive.mode in LOOP_MODES:
                self.run_loops(axis, span_s, now)
            # Rated torque is k_t x rated current: a torque in per mille of 0x6076 is the same
            # per mille of 0x6075 (CiA 402-2 0x6071 / 0x6075), the drive's current setpoint.
            currents_a[axis.joint_index] = axis.current.decode(self.demand(axis).permille)
            any_enabled = (
                any_enabled
                or axis.drive.power is PowerState.OPERATION_ENABLED
                or axis.modes.quick_stopping
            )
        return currents_a if any_enabled else None

    def statusword(self, axis: Drive) -> int:
        """0x6041: the power state, internal limit, and bits 10 / 12 / 13 of the mode.

        CST and CSV: target reached is 0x6077 within the window of the demand. The profile
        modes and CSP: bits 10, 12 and 13 are their logic's (`rack_modes`); in FAULT after a
        following error (0x603F = 0x8611) bit 13 stays set.
        """
        drive = axis.drive
        demand = self.demand(axis)
        if drive.mode in cia402.PROFILE_MODES:
            word = cia402.statusword(drive, target_reached=False, internal_limit=demand.limited)
            if drive.power is PowerState.OPERATION_ENABLED:
                word |= axis.modes.status_bits
            elif drive.power in _FAULT_STATES and axis.value(od.ERROR_CODE) == (
                EMCY_FOLLOWING_ERROR
            ):
                # The fault reaction follows bit 13 within the same SYNC, so without this a
                # master would never see it; it stays up until the fault reset clears 0x603F.
                word |= SW_BIT13
            return word
        reached = (
            drive.power is PowerState.OPERATION_ENABLED
            and abs(self.torque_actual_permille(axis) - demand.permille)
            <= cia402.TARGET_TORQUE_WINDOW_PERMILLE
        )
        return cia402.statusword(drive, target_reached=reached, internal_limit=demand.limited)

    # --- state changes -------------------------------------------------------------------

    def settle(self, axes: Sequence[Drive], now: float) -> None:
        """Take the automatic transitions that are due (`cia402.settle`), at each SYNC."""
        for axis in axes:
            if axis.drive.power in cia402.SETTLING_STATES:  # any other stays as it is
                self.set_drive(axis, axis.drive, now)

    def set_drive(self, axis: Drive, state: Cia402AxisState, now: float) -> None:
        """Settle and store a new CiA 402 state; entering operation enabled arms SYNC loss."""
        state = cia402.settle(
            state,
            standstill=bool(self._modes[0, axis.plant_index] == 0.0),
            quick_stop_option=axis.value(od.QUICK_STOP_OPTION),
        )
        enabled = PowerState.OPERATION_ENABLED
        if state.power is enabled and axis.drive.power is not enabled:
            axis.sync_armed_s = now  # SYNC loss is watched from here on
            axis.sync_loss_reported = False
        axis.drive = state

    def apply_controlword(self, axis: Drive, controlword: int, now: float) -> None:
        """A write of 0x6040: the state machine's transition, a fault reset's clearing."""
        persisting = axis.faults.drive_fault  # an injected drive fault whose cause lasts
        if cia402.is_fault_reset_edge(controlword, axis.drive.controlword) and not persisting:
            self._clear_errors(axis)
            if axis.faults.emcy_code:  # the raised EMCY is reset with the other errors
                self._reset_raised_emcy(axis, now)
        state = cia402.apply_controlword(axis.drive, controlword, axis.value(od.QUICK_STOP_OPTION))
        if persisting:
            # CiA 402-2: a fault reset leaves FAULT only once the fault's cause is gone.
            state = cia402.fault(state)
        self.set_drive(axis, state, now)

    def _clear_errors(self, axis: Drive) -> None:
        if axis.value(od.ERROR_REGISTER) or axis.value(od.ERROR_CODE):
            axis.values[(od.ERROR_REGISTER, 0)] = 0
            axis.values[(od.ERROR_CODE, 0)] = 0
            self._emcy(axis, cia402.EMCY_ERROR_RESET)

    def _set_error(self, axis: Drive, code: int) -> None:
        """A communication error: 0x603F, 0x1001 (generic + communication), then its EMCY."""
        axis.values[(od.ERROR_CODE, 0)] = code
        axis.values[(od.ERROR_REGISTER, 0)] = axis.value(od.ERROR_REGISTER) | (
            cia402.ERROR_REGISTER_GENERIC | cia402.ERROR_REGISTER_COMMUNICATION
        )
        self._emcy(axis, code)  # not in STOPPED

    def connection_lost(self, axis: Drive, code: int | None, now: float) -> None:
        """A watchdog fired (or NMT stop): error code, EMCY, then the 0x6007 reaction."""
        if code is not None:
            self._set_error(axis, code)
        state = cia402.abort_connection(
            axis.drive,
            axis.value(od.ABORT_CONNECTION_OPTION),
            axis.value(od.QUICK_STOP_OPTION),
        )
        self.set_drive(axis, state, now)

    def nmt_reaction(self, axis: Drive, now: float) -> None:
        """The master took the node out of OPERATIONAL, stopped or reset it: the 0x6007 reaction.

        CiA 402-2 0x6007 covers the NMT master stopping the node as well as a lost connection.
        Where the reaction acted (the drive could produce torque), 0x603F and 0x1001 say so
        with `EMCY_LEFT_OPERATIONAL`, and the EMCY goes out unless the node is now STOPPED
        (CiA 301: no EMCY there).
        """
        before = axis.drive.power
        self.connection_lost(axis, None, now)
        if axis.drive.power is not before:
            self._set_error(axis, cia402.EMCY_LEFT_OPERATIONAL)
