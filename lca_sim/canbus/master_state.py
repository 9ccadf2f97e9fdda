"""What the CAN bridge master reports: each drive's last state in SI units, snapshots, counters."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields
from itertools import starmap
from operator import attrgetter

from lca_sim.cia402 import controlword as ctl
from lca_sim.cia402.device import PowerState


@dataclass(slots=True)
class AxisState:
    """What one drive last reported, in SI units (joint side unless named motor)."""

    statusword: int = 0
    position: float = 0.0
    velocity: float = 0.0
    motor_position_rad: float = 0.0
    motor_velocity_rad_s: float = 0.0
    current_a: float = 0.0
    drive_state: int = -1
    motion_state: int = 0
    eta_m: float = math.nan
    eta_l: float = math.nan
    # Drive-chain extras a real CiA 402 drive does not report: NaN means "this backend cannot
    # know" (only the virtual rack maps them, on manufacturer-specific objects).
    load_torque_nm: float = math.nan
    friction_torque_nm: float = math.nan
    voltage_v: float = math.nan

    @property
    def power_state(self) -> PowerState | None:
        """The CiA 402 state of the statusword."""
        return ctl.power_state(self.statusword)


@dataclass(frozen=True, slots=True)
class Snapshot:
    """Every axis at one SYNC: states in joint order, the SYNC's wall time (time.time)."""

    sync_wall_s: float
    cycle: int
    axes: tuple[AxisState, ...]


@dataclass(slots=True)
class Counters:
    """Events counted for diagnostics."""

    cycles: int = 0
    complete_cycles: int = 0
    late_cycles: int = 0
    commands_accepted: int = 0
    commands_rejected: int = 0
    commands_clamped: int = 0
    send_failures: int = 0
    receive_errors: int = 0  # exceptions of the bus's receive (python-can's notifier thread)
    error_frames: int = 0
    emcy_received: int = 0
    bad_pdos: int = 0
    silence_halts: int = 0
    drive_restarts: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    bits_sent: int = 0  # worst-case stuffing (`frame_bits`)
    bits_received: int = 0
    nominal_bits: int = 0  # both directions, without stuffing (`frame_bits_nominal`)
    process_freezes: int = 0
    heartbeats_lost: int = 0  # a drive's heartbeat silent beyond its consumer time, per loss
    cycle_stalls: int = 0  # runs of `BridgeParams.stall_cycles` SYNCs without a complete cycle
    # Cycles (once commands flow) that sent a command newer than the previous cycle, and those
    # that had to send the previous one again: the controller's answer to the last states came
    # after this SYNC, so it acts a cycle later (a loop delay of two periods instead of one).
    commands_in_time: int = 0
    commands_late: int = 0
    # Complete sets of TPDOs after a SYNC whose state had gone out already (late TPDOs of the
    # SYNC before): not handed on.
    extra_complete_sets: int = 0


AXIS_FIELDS = frozenset(AxisState.__slots__)
# Every field of an AxisState in its constructor's order, read in one C call: `copied` runs
# per drive per SYNC on the notifier thread (`copied_all`).
_ALL_FIELDS = attrgetter(*(f.name for f in fields(AxisState)))


def copied(state: AxisState) -> AxisState:
    """A copy of `state` that the master's later TPDOs do not change."""
    return AxisState(*_ALL_FIELDS(state))


def copied_all(states: Iterable[AxisState]) -> tuple[AxisState, ...]:
    """`copied` of each state, in one call (the snapshot of every drive at a complete cycle)."""
    return tuple(starmap(AxisState, map(_ALL_FIELDS, states)))
