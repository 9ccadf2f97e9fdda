"""The simulator's state as the plant contract's snapshot, and as the faulty sensors deliver it.

`SimSnapshots` takes the simulator's rows once (the model updates its arrays in place, so the
views stay current) and fills a `PlantSnapshot` from them with no per-axis objects. With
faults injected (docs/faults.md), `delivered` passes the snapshot through the faulty sensors
and the faulty state link: none, one or several snapshots go out for it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from lca_control.contract import PlantSnapshot
from lca_sim.model.faults import FaultInjector, StateLink
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator


class SimSnapshots:
    """Snapshots of one simulator, and their faulty delivery.

    Args:
        sim: the simulator.
        faults: its fault injector (sensor and link faults).
    """

    def __init__(self, sim: Simulator, faults: FaultInjector) -> None:
        self._sim = sim
        self._faults = faults
        self.link = StateLink(faults)
        self._gear_ratio = np.array([a.gear_ratio for a in sim.robot.axes])
        state = sim.state_array
        modes = sim.mode_array
        self._q = state[0]
        self._qdot = state[1]
        self._current = state[2]
        self._motion = modes[0]
        self._drive = modes[1]
        self._rows = {name: sim.signal_array[row] for row, name in enumerate(SIGNAL_NAMES)}
        n_axes = len(sim.axis_names)
        self._effort = np.zeros(n_axes)  # N * tau_m, joint side
        self._motor_position = np.zeros(n_axes)  # N * q
        self._measured = tuple(np.zeros(sim.n_axes) for _ in range(3))

    def snapshot(self, stamp_s: float) -> PlantSnapshot:
        """The plant now, as the contract's snapshot (views of the live state)."""
        rows = self._rows
        np.multiply(rows["motor_torque_nm"], self._gear_ratio, out=self._effort)
        np.multiply(self._q, self._gear_ratio, out=self._motor_position)
        return PlantSnapshot(
            stamp_s=stamp_s,
            joints=self._sim.axis_names,
            position=self._q,
            velocity=self._qdot,
            effort=self._effort,
            motor_position_rad=self._motor_position,
            motor_velocity_rad_s=rows["motor_velocity_rad_s"],
            current_a=self._current,
            motion_state=self._motion,
            drive_state=self._drive,
            state_names=self._sim.state_names,
            eta_m=rows["eta_m"],
            eta_l=rows["eta_l"],
            motor_torque_nm=rows["motor_torque_nm"],
            load_torque_nm=rows["load_torque_nm"],
            friction_torque_nm=rows["friction_torque_nm"],
            voltage_v=rows["voltage_v"],
        )

    def delivered(self, snap: PlantSnapshot) -> list[PlantSnapshot]:
        """The snapshot as the faulty sensors report it, routed through the faulty link."""
        faults = self._faults
        q, v, i = self._measured
        faults.measure(snap.position, snap.velocity, snap.current_a, (q, v, i))
        measured = dataclasses.replace(
            snap,
            position=q.copy(),
            velocity=v.copy(),
            current_a=i.copy(),
            motor_position_rad=q * self._gear_ratio,
            faults=tuple(faults.describe(j) for j in snap.joints),
            motor_velocity_rad_s=snap.motor_velocity_rad_s.copy(),
            effort=snap.effort.copy(),
            motion_state=snap.motion_state.copy(),
            drive_state=snap.drive_state.copy(),
            eta_m=snap.eta_m.copy(),
            eta_l=snap.eta_l.copy(),
            motor_torque_nm=snap.motor_torque_nm.copy(),
            load_torque_nm=snap.load_torque_nm.copy(),
            friction_torque_nm=snap.friction_torque_nm.copy(),
            voltage_v=snap.voltage_v.copy(),
        )
        return self.link.route(snap.stamp_s, measured)
