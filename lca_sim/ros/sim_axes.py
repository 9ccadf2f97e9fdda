"""The simulator's per-axis watch: end stops hit or pushed into, back-driving, injected faults.

`AxisWatch` follows each axis from one published state to the next (the speed it last moved
at, the speed it reached an end stop with) and builds its `lca_hil/simulator/<joint>`
/diagnostics status: WARN "end stop hit at X", "<joint> pushing into its lower (upper) end
stop", "back-driving: <joint> moving at X with no command", WARN or ERROR for an injected
fault; OK "resting on its lower end stop" for a pose it never moved into. docs/faults.md and
docs/reliability.md have the whole story.
"""

from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus

from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.faults import FaultInjector
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator
from lca_sim.ros.node_util import status

_ROW = {name: row for row, name in enumerate(SIGNAL_NAMES)}
_END_STOP = "stop_end_stop"


class AxisWatch:
    """End-stop and back-drive detection per axis, and the axes' /diagnostics statuses.

    Args:
        sim: the simulator (its arrays are read in place).
        plant: the commanded plant (enabled, the command in force).
        faults: the fault injector (the faults active per axis).
    """

    def __init__(self, sim: Simulator, plant: CommandedPlant, faults: FaultInjector) -> None:
        self._sim = sim
        self._plant = plant
        self._faults = faults
        # V_eps of the state machine, motor side: faster is moving.
        self._velocity_eps_rad_s = sim.robot.state_machine.velocity_eps_rad_s
        self._end_stop_code = sim.state_names.index(_END_STOP)
        self._position_min = np.array([low for low, _ in sim.position_limits])
        self._position_max = np.array([high for _, high in sim.position_limits])
        # `Simulator` updates its arrays in place: these views stay current.
        self._q = sim.state_array[0]
        self._qdot = sim.state_array[1]
        self._drive = sim.mode_array[1]
        self._motor_velocity = sim.signal_array[_ROW["motor_velocity_rad_s"]]
        n_axes = len(sim.axis_names)
        self._moving_speed = np.zeros(n_axes)  # |joint velocity| when last published moving
        self._contact_speed = np.zeros(n_axes)  # that speed when the end stop was reached
        self._at_end_stop = np.zeros(n_axes, dtype=bool)

    def forget(self) -> None:
        """After a reset: a pose at a stop is parked there, not a hit."""
        self._moving_speed[:] = 0.0
        self._contact_speed[:] = 0.0
        self._at_end_stop[:] = False

    def track(self) -> None:
        """Keep each axis's last moving speed, and take it as the contact speed at an end stop.

        Called with each published state. An axis is at its end stop when the model clamped
        it there: a load that drove it in leaves the drive state at `stop_hold`
        (`stop_end_stop` only while the motor pushes).
        """
        at_stop = self._at_limit()
        contact = at_stop & ~self._at_end_stop
        self._contact_speed[contact] = self._moving_speed[contact]
        self._at_end_stop[:] = at_stop
        moving = ~at_stop & (np.abs(self._motor_velocity) > self._velocity_eps_rad_s)
        self._moving_speed[moving] = np.abs(self._qdot[moving])

    def _at_limit(self) -> np.ndarray:
        """Per axis: at an end stop (clamped to a position limit, or the motor pushing into it)."""
        at_limit: np.ndarray = (
            (self._drive == self._end_stop_code)
            | (self._q <= self._position_min)
            | (self._q >= self._position_max)
        )
        return at_limit

    def statuses(self) -> list[DiagnosticStatus]:
        """One status per axis, in the simulator's axis order."""
        return [self._axis_status(a, name) for a, name in enumerate(self._sim.axis_names)]

    def _axis_status(self, a: int, name: str) -> DiagnosticStatus:
        """One axis: its drive state, or WARN at an end stop or back-driven without command.

        At an end stop: WARN while the motor pushes into it or after an arrival with speed (a
        hit); OK while it rests there having never moved into it (a pose at start or reset).
        """
        sim, plant, faults = self._sim, self._plant, self._faults
        signals = sim.signal_array
        drive_state = sim.state_names[int(sim.mode_array[1, a])]
        velocity = float(sim.state_array[1, a])
        unit = "m/s" if sim.prismatic[a] else "rad/s"
        uncommanded = not plant.enabled or plant.target[a] == 0.0
        moving = abs(float(signals[_ROW["motor_velocity_rad_s"], a])) > self._velocity_eps_rad_s
        level, message, fault = DiagnosticStatus.OK, drive_state, "none"
        injected = faults.active(name) if faults.any_active else []
        contact_speed = self._contact_speed[a]
        if injected:
            tripped = "i2t_trip" in injected
            level = DiagnosticStatus.ERROR if tripped else DiagnosticStatus.WARN
            fault = f"injected: {faults.describe(name)}"
            message = fault + (" (I2t trip: torque off, latched)" if tripped else "")
        elif self._at_limit()[a]:
            side = "upper" if self._q[a] >= self._position_max[a] else "lower"
            hit = f"end stop hit at {contact_speed:.3g} {unit}"
            if self._drive[a] == self._end_stop_code:
                level, fault = DiagnosticStatus.WARN, "pushing into end stop"
                message = f"{name} pushing into its {side} end stop"
                if contact_speed > 0.0:
                    message += f" ({hit})"
            elif contact_speed > 0.0:
                level, fault = DiagnosticStatus.WARN, "at end stop"
                message = hit
            else:  # parked there, never driven into it: no fault
                message = f"{drive_state}: resting on its {side} end stop"
        elif moving and uncommanded:
            level, fault = DiagnosticStatus.WARN, "back-driving"
            message = f"back-driving: {name} moving at {abs(velocity):.3g} {unit} with no command"
        return status(
            f"lca_hil/simulator/{name}",
            level,
            message,
            {
                "drive_state": drive_state,
                "position": float(sim.state_array[0, a]),
                "velocity": velocity,
                "command": float(plant.target[a]),
                "voltage_v": float(signals[_ROW["voltage_v"], a]),
                "current_a": float(sim.state_array[2, a]),
                "end_stop_contact_speed": float(contact_speed),
                "fault": fault,
                "faults": self._faults.describe(name),
            },
        )
