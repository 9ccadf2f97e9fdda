"""The rack's fault injection: object 0x2030 and the rack.yaml `faults:` schedule.

A part of the virtual drive rack that owns the schedule, the fault log and each drive's
injected faults' effects on the bus (mute, heartbeat off, bus-off); what a fault does to the
drive (EMCY, 0x603F and FAULT, the communication error's reactions) is the rack's, handed in.
With none configured the rack's frames are what they were without it (docs/can.md, "Fault
injection").
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence

from canopen import SdoAbortedError

from lca_sim.canbus.rack_network import RackNetwork
from lca_sim.canbus.rack_state import Drive, FaultEvent, RackCounters
from lca_sim.cia402 import cia301
from lca_sim.cia402 import device as cia402
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import Cia402AxisState
from lca_sim.config.rack import FAULT_KINDS, FAULT_VALUE_RANGE, FaultEntry
from lca_sim.errors import InvalidValueError, UnknownNameError

# CiA 301 EMCY 0x8140 "recovered from bus off": sent when a node is back on the bus, and the
# 0x603F code of the bus-off while it lasts (as CANopenNode's CO_EM_CAN_TX_BUS_OFF reports it).
EMCY_BUS_OFF_RECOVERED = 0x8140


class RackFaults:
    """The faults injected into a rack's drives, by SDO, by the API or on schedule.

    Args:
        axes: the rack's drives (each holds its `faults`).
        network: the rack's network (its mute sets and after-send hooks).
        counters: the rack's counters.
        schedule: the `faults:` entries, timed by the rack's plant time.
        dt_s: the plant step, s (the rack's time is steps x dt_s).
        steps: the plant steps run since start.
        started: whether the rack has started (heartbeats run).
        lock, clock: the rack's lock and clock (for a bus-off that follows an SDO answer).
        emcy, communication_error, set_drive: what the rack does to a drive.
    """

    def __init__(
        self,
        axes: Sequence[Drive],
        network: RackNetwork,
        counters: RackCounters,
        schedule: Sequence[FaultEntry],
        dt_s: float,
        *,
        steps: Callable[[], int],
        started: Callable[[], bool],
        lock: threading.RLock,
        clock: Callable[[], float],
        emcy: Callable[[Drive, int], None],
        communication_error: Callable[[Drive, int, float], None],
        set_drive: Callable[[Drive, Cia402AxisState, float], None],
    ) -> None:
        self._axes = axes
        self._network = network
        self._counters = counters
        self._dt_s = dt_s
        self._steps = steps
        self._started = started
        self._lock = lock
        self._clock = clock
        self._emcy = emcy
        self._communication_error = communication_error
        self._set_drive = set_drive
        # The schedule as (entry, first step on, first step off), which entries are on, and
        # every fault going on or off.
        self._schedule = [
            (f, self._step_of(f.start_s), None if f.end_s is None else self._step_of(f.end_s))
            for f in schedule
        ]
        self._schedule_on = [False] * len(schedule)
        self.log: list[FaultEvent] = []
        network.on_dropped = self._dropped

    @property
    def idle(self) -> bool:
        """No schedule and no fault so far: nothing to run at a SYNC."""
        return not self._schedule and not self.log

    def _step_of(self, time_s: float) -> int:
        """The first plant step count at which the rack's time is >= `time_s`."""
        return math.ceil(time_s / self._dt_s - 1e-9)

    def write(self, axis: Drive, subindex: int, value: int, now: float) -> None:
        """An SDO write of 0x2030: switch the fault of that sub-index on or off."""
        kind = next((k for k, sub in FAULT_KINDS.items() if sub == subindex), None)
        if kind is None:
            raise SdoAbortedError(cia301.ABORT_NO_SUBINDEX)
        if kind == "heartbeat_off" and value not in (0, 1):
            raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
        if kind != "bus_off":
            self.set(axis, kind, value, "sdo", now)
        elif value and not axis.faults.bus_off:
            # Off the bus after this write's SDO answer, the node's last frame (the master
            # sees the write succeed), for `value` ms of the rack's time.
            def go_off() -> None:
                with self._lock:
                    self.set(axis, "bus_off", 1, "sdo", self._clock())
                    axis.faults.bus_off_ms = value
                    axis.faults.bus_off_until_step = self._steps() + self._step_of(value * 1e-3)

            self._network.after_send[cia301.SDO_RESPONSE_COB_BASE + axis.config.node_id] = go_off

    def set_checked(self, axis: Drive, kind: str, value: int) -> None:
        """`set` from the API, after checking the kind and its value's range (`FAULT_KINDS`).

        Raises:
            UnknownNameError: an unknown kind.
            ValueError: a value out of the kind's range.
        """
        if kind not in FAULT_KINDS:
            raise UnknownNameError("fault kind", kind, tuple(FAULT_KINDS))
        high = FAULT_VALUE_RANGE[kind][1]
        if isinstance(value, bool) or not 0 <= value <= high:
            raise InvalidValueError(f"{kind}: expected a value in [0, {high}], got {value!r}")
        with self._lock:
            self.set(axis, kind, value, "api", self._clock())

    def set(self, axis: Drive, kind: str, value: int, source: str, now: float) -> None:
        """Switch one fault of one drive on (value != 0) or off (0), and log it."""
        if kind == "lost_tpdo":
            axis.faults.lost_tpdos = value
        elif kind == "heartbeat_off":
            axis.faults.heartbeat_off = bool(value)
            self.update_silence(axis)
        elif kind == "emcy":
            self._raise_emcy(axis, value)
        elif kind == "drive_fault":
            self._drive_fault(axis, value, now)
        else:
            self._bus_off(axis, bool(value), now)
        self.log.append(
            FaultEvent(self._steps() * self._dt_s, axis.config.name, kind, value, source)
        )

    def _raise_emcy(self, axis: Drive, code: int) -> None:
        """Send EMCY `code` with its 0x1001 bits set (CiA 301 7.2.7, 7.5.2.2); 0 clears them.

        The drive's CiA 402 state and 0x603F do not change: an EMCY that is not a drive fault
        (`_drive_fault` is). Clearing leaves 0x1001 as a drive error (0x603F) needs it, and
        sends EMCY 0x0000 "error reset" when no error is left (CiA 301 7.2.7.1).
        """
        axis.faults.emcy_code = code
        register = axis.value(od.ERROR_REGISTER)
        if code:
            axis.values[(od.ERROR_REGISTER, 0)] = register | od.error_register_for(code)
            self._emcy(axis, code)
        elif register and not axis.value(od.ERROR_CODE):
            axis.values[(od.ERROR_REGISTER, 0)] = 0
            self._emcy(axis, cia402.EMCY_ERROR_RESET)

    def _drive_fault(self, axis: Drive, code: int, now: float) -> None:
        """A drive fault (CiA 402-2 transition 13): 0x603F = code, 0x1001, EMCY, FAULT.

        The power stage goes off (no torque: a self-locking axis holds, a reversible one
        moves under its load). 0 removes the fault's cause; the drive stays in FAULT until the
        master's fault reset (controlword bit 7), which is refused while the cause lasts.
        """
        axis.faults.drive_fault = code
        if not code:
            return
        axis.values[(od.ERROR_CODE, 0)] = code
        axis.values[(od.ERROR_REGISTER, 0)] = axis.value(od.ERROR_REGISTER) | od.error_register_for(
            code
        )
        self._emcy(axis, code)
        self._set_drive(axis, cia402.fault(axis.drive), now)

    def _bus_off(self, axis: Drive, on: bool, now: float) -> None:
        """A node's CAN controller goes bus-off (on) or recovers (off).

        In bus-off a node takes no part in the bus (ISO 11898-1): it sends nothing (TPDO,
        EMCY, SDO answer, heartbeat) and takes nothing (SDO, NMT, SYNC, RPDO, heartbeat).
        Bus-off is a communication error: 0x603F = 0x8140, 0x1001, the CiA 402-2 0x6007
        reaction and the CiA 301 0x1029 sub 1 NMT change (7.5.2.32 lists bus-off among the
        communication errors) apply at once. On recovery the node resumes in the NMT state
        that left it, with its configuration (no reset, no boot-up: CiA 301 asks none), and
        sends EMCY 0x8140 "recovered from bus off" with 0x1001.
        """
        faults = axis.faults
        if on == faults.bus_off:
            return
        faults.bus_off = on
        node, network = axis.node, self._network
        sdo_cob = cia301.SDO_REQUEST_COB_BASE + axis.config.node_id
        if on:
            network.unsubscribe(sdo_cob, node.sdo.on_request)
            network.unsubscribe(cia301.NMT_COB_ID, node.nmt.on_command)
            self.update_silence(axis)
            for pdo in axis.rpdos:
                pdo.latched = None
            self._communication_error(axis, EMCY_BUS_OFF_RECOVERED, now)
            return
        faults.bus_off_ms, faults.bus_off_until_step = 0, None
        network.subscribe(sdo_cob, node.sdo.on_request)
        network.subscribe(cia301.NMT_COB_ID, node.nmt.on_command)
        self.update_silence(axis, restart_heartbeat=False)
        self._emcy(axis, EMCY_BUS_OFF_RECOVERED)  # its first frame back, then the heartbeat
        if not faults.heartbeat_off and self._started():
            node.nmt.start_heartbeat(axis.value(od.HEARTBEAT_PRODUCER))

    def update_silence(self, axis: Drive, restart_heartbeat: bool = True) -> None:
        """Mute the frames of bus-off nodes, stop or restart `axis`'s heartbeat producer."""
        muted: set[int] = set()
        periodic: set[int] = set()
        for a in self._axes:
            node_id = a.config.node_id
            if a.faults.bus_off:
                muted |= {
                    cia301.EMCY_COB_BASE + node_id,
                    cia301.SDO_RESPONSE_COB_BASE + node_id,
                    cia301.HEARTBEAT_COB_BASE + node_id,
                }
            if a.faults.bus_off or a.faults.heartbeat_off:
                periodic.add(cia301.HEARTBEAT_COB_BASE + node_id)
        cob = cia301.HEARTBEAT_COB_BASE + axis.config.node_id
        was_silent = cob in self._network.muted_periodic
        self._network.muted = frozenset(muted)
        self._network.muted_periodic = frozenset(periodic)
        nmt = axis.node.nmt
        if cob in periodic and not was_silent:
            nmt.stop_heartbeat()  # type: ignore[no-untyped-call]
        elif was_silent and cob not in periodic and self._started() and restart_heartbeat:
            nmt.start_heartbeat(axis.value(od.HEARTBEAT_PRODUCER))

    def _dropped(self, cob_id: int) -> None:
        self._counters.frames_dropped_bus_off += 1

    def run_clock(self, now: float) -> None:
        """At a SYNC: the schedule's faults that start or end now, and timed bus-offs' ends."""
        step = self._steps()
        for k, (entry, start, end) in enumerate(self._schedule):
            on = step >= start and (end is None or step < end)
            if on != self._schedule_on[k]:
                self._schedule_on[k] = on
                axis = next(a for a in self._axes if a.config.name == entry.joint)
                self.set(axis, entry.kind, entry.value if on else 0, "schedule", now)
        for axis in self._axes:
            until = axis.faults.bus_off_until_step
            if until is not None and step >= until:
                self.set(axis, "bus_off", 0, "sdo", now)

    def reassert(self, axis: Drive, now: float) -> None:
        """After a reset node: a drive fault whose cause lasts faults the drive again."""
        if axis.faults.drive_fault:
            self._drive_fault(axis, axis.faults.drive_fault, now)
