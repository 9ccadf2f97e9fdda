"""The rack's NMT side: boot, NMT commands, resets, and 0x1029's reaction to a communication error.

A part of the virtual drive rack that keeps each drive's NMT state beside canopen's NMT slave
(which answers the frames and runs the heartbeat); docs/can.md, "The virtual drive rack".
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from lca_sim.canbus.rack_cia402 import DriveControl
from lca_sim.canbus.rack_state import (
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_STOPPED,
    Drive,
    RackCounters,
)
from lca_sim.cia402 import cia301
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import Cia402AxisState

_NMT_STATES = {
    cia301.NMT_START: NMT_OPERATIONAL,
    cia301.NMT_STOP: NMT_STOPPED,
    cia301.NMT_ENTER_PRE_OPERATIONAL: NMT_PRE_OPERATIONAL,
}


class RackNmt:
    """The NMT states of every drive of a rack.

    Args:
        axes: the rack's drives (each holds its `nmt`).
        counters: the rack's counters.
        control: the drives' CiA 402 part (the 0x6007 reactions).
        load_pdos: loads a drive's PDOs from its objects (after a reset).
        reassert: re-applies a drive's injected faults after a reset: (drive, now).
    """

    def __init__(
        self,
        axes: Sequence[Drive],
        counters: RackCounters,
        control: DriveControl,
        load_pdos: Callable[[Drive], None],
        reassert: Callable[[Drive, float], None],
    ) -> None:
        self._axes = axes
        self._counters = counters
        self._control = control
        self._load_pdos = load_pdos
        self._reassert = reassert

    def power_on(self, axis: Drive, now: float) -> None:
        """Reset every object, boot, and re-apply the drive's injected faults."""
        self._reset(axis, communication_only=False, now=now)
        self._boot(axis)
        self._reassert(axis, now)

    def _reset(self, axis: Drive, communication_only: bool, now: float) -> None:
        """Objects back to their defaults (0x1000-0x1FFF only for reset communication).

        Reset communication keeps 0x1001: the error register reports the drive's errors (0x603F
        and the FAULT it is in survive the reset), it is not a communication parameter.
        """
        for key, default in axis.defaults.items():
            if communication_only and key == (od.ERROR_REGISTER, 0):
                continue
            if not communication_only or key[0] < 0x2000:
                axis.values[key] = default
        for index in list(axis.node.data_store):
            if not communication_only or index < 0x2000:
                del axis.node.data_store[index]
        self._load_pdos(axis)
        if not communication_only:
            # Reset node: the drive forgets its home too (0x607C is back at its default, and
            # 0x6064 reads the encoder again), as a drive without a battery-backed home does.
            axis.modes.stop()
            axis.modes.offset_inc = 0.0
            axis.drive = Cia402AxisState(mode=axis.value(od.MODES_OF_OPERATION))
            self._control.set_drive(axis, axis.drive, now)
        axis.heartbeat_last_rx_s = None
        axis.sync_armed_s = now
        axis.sync_loss_reported = False

    def _boot(self, axis: Drive) -> None:
        """Boot-up message, then PRE-OPERATIONAL with the heartbeat of 0x1017 running."""
        axis.node.nmt.send_command(cia301.NMT_RESET_NODE)  # from INITIALISING: sends the boot-up
        axis.node.nmt.send_command(cia301.NMT_ENTER_PRE_OPERATIONAL)  # starts the heartbeat
        axis.nmt = NMT_PRE_OPERATIONAL

    def on_nmt(self, data: bytes, now: float) -> None:
        """Post-process an NMT command (canopen's NmtSlave has already set its state)."""
        if len(data) != 2:
            self._counters.bad_frames += 1
            return
        command, node_id = data[0], data[1]
        for axis in self._axes:
            if node_id not in (0, axis.config.node_id) or axis.faults.bus_off:
                continue
            if command in _NMT_STATES:
                self._enter(axis, _NMT_STATES[command], now)
            elif command in (cia301.NMT_RESET_NODE, cia301.NMT_RESET_COMMUNICATION):
                communication_only = command == cia301.NMT_RESET_COMMUNICATION
                if communication_only:
                    self._control.nmt_reaction(axis, now)
                self._reset(axis, communication_only, now)
                self._boot(axis)
                self._reassert(axis, now)

    def _enter(self, axis: Drive, state: str, now: float) -> None:
        """Move a node to an NMT state (its canopen NmtSlave is set by the caller).

        Leaving OPERATIONAL (no more PDOs: the last target must not stay applied) and entering
        STOPPED (no more SDO either) apply the 0x6007 reaction (`DriveControl.nmt_reaction`).
        """
        previous = axis.nmt
        if state == previous:
            return
        axis.nmt = state
        if state == NMT_OPERATIONAL:
            axis.sync_armed_s = now
            axis.sync_loss_reported = False
            for pdo in axis.tpdos:
                pdo.last_data, pdo.sync_count = None, 0
            return
        for pdo in axis.rpdos:
            pdo.latched, pdo.last_rx_s = None, None
        if previous == NMT_OPERATIONAL or state == NMT_STOPPED:
            self._control.nmt_reaction(axis, now)

    def communication_error(self, axis: Drive, code: int, now: float) -> None:
        """A watchdog fired: 0x603F, 0x1001, EMCY, the 0x6007 reaction, then 0x1029's NMT change.

        CiA 301 7.5.2.32 (0x1029 error behaviour, sub 1 communication error): 0 to
        PRE-OPERATIONAL if the node is OPERATIONAL, 1 no change, 2 to STOPPED.
        """
        self._control.connection_lost(axis, code, now)
        behaviour = axis.value(od.ERROR_BEHAVIOUR, 1)
        if behaviour == od.ERROR_BEHAVIOUR_PRE_OPERATIONAL and axis.nmt == NMT_OPERATIONAL:
            # the heartbeat says so too
            axis.node.nmt.send_command(cia301.NMT_ENTER_PRE_OPERATIONAL)
            self._enter(axis, NMT_PRE_OPERATIONAL, now)
        elif behaviour == od.ERROR_BEHAVIOUR_STOPPED and axis.nmt != NMT_STOPPED:
            axis.node.nmt.send_command(cia301.NMT_STOP)
            self._enter(axis, NMT_STOPPED, now)
