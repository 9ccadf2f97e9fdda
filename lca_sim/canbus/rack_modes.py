"""The rack's loop modes: CSV, PP, PV, HM and CSP through the drive's own loops (CiA 402-2).

A part of each virtual drive. Once per SYNC that advances the plant, for a drive enabled in
one of these modes, the mode's logic (`lca_sim.cia402.mode_pp`, `mode_pv`, `homing`,
`mode_csp`) turns its objects and the controlword into a demand (0x6062 and a velocity) and
the statusword bits 10, 12 and 13; lca_control's `DriveLoops`, the same loops the simulator
node runs for its position and velocity joints, closes the position and velocity loops on the
plant's joint state; their output, a current setpoint, becomes the drive's demand in per mille
of 0x6075. CST does not come here. Positions are motor increments (0x608F) on the bus and
joint rad (m) in the loops: increments = joint x gear ratio x 0x608F / 2 pi, plus the home
offset homing set. docs/can-modes.md.
"""

from __future__ import annotations

from lca_control.drive_loops import DriveLoopParams, DriveLoops, DriveMode
from lca_sim.canbus.rack_state import Drive
from lca_sim.cia402 import mode_params
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import CW_HALT, MODE_CSP, MODE_CSV, MODE_HM, MODE_PP, MODE_PV
from lca_sim.cia402.homing import HomingInputs, HomingMode, HomingParams
from lca_sim.cia402.mode_common import Loop, ModeOutput
from lca_sim.cia402.mode_csp import CspParams, CyclicPositionMode
from lca_sim.cia402.mode_pp import PpParams, ProfilePositionMode
from lca_sim.cia402.mode_pv import ProfileVelocityMode, PvParams
from lca_sim.cia402.profile import ProfileGenerator

# The modes whose demand comes from the drive's loops (CST's is the target torque itself).
LOOP_MODES = frozenset({MODE_CSV, MODE_PP, MODE_PV, MODE_HM, MODE_CSP})
# The gantry's joint limits act as limit switches (homing methods 17 / 18) this share of the
# joint's range before its mechanical stop.
LIMIT_SWITCH_SHARE = 0.005
_LOOPS = {Loop.POSITION: DriveMode.POSITION, Loop.VELOCITY: DriveMode.VELOCITY}
# 0x605A options that ramp down in quick stop: on 0x6084 (1, 5) or on 0x6085 (2, 6).
QUICK_STOP_SLOW_DOWN = frozenset({1, 5})
QUICK_STOP_RAMPS = QUICK_STOP_SLOW_DOWN | frozenset({2, 6})


class AxisModes:
    """One drive's loops and the logic of the loop mode in force.

    Args:
        loop_params: the drive loops' gains and limits (rack.yaml's velocity PI, the position
            gain, the current limit of 0x6072).
        increments_per_joint: encoder increments per joint rad (m): gear x 0x608F / 2 pi.
        joint_limits: the joint's (min, max), rad or m: the limit switches of homing.
    """

    def __init__(
        self,
        loop_params: DriveLoopParams,
        increments_per_joint: float,
        joint_limits: tuple[float, float],
    ) -> None:
        self.loops = DriveLoops(loop_params, DriveMode.VELOCITY)
        self._k = increments_per_joint
        low, high = joint_limits
        margin = LIMIT_SWITCH_SHARE * (high - low)
        self._switches = (low + margin, high - margin)
        self._pp = ProfilePositionMode()
        self._pv = ProfileVelocityMode()
        self._hm = HomingMode()
        self._csp = CyclicPositionMode()
        self._quick = ProfileGenerator()  # the quick stop's ramp
        self.quick_stopping = False  # QUICK STOP ACTIVE on a ramp: the loops run
        self._entered: int | None = None  # the mode whose logic runs (None: not enabled)
        self.permille = 0  # the loops' current setpoint, per mille of 0x6075
        self.status_bits = 0  # bits 10, 12, 13 of the profile mode in force
        self.demand_inc = 0.0  # 0x6062
        self.following_error_inc = 0.0  # 0x60F4
        self.offset_inc = 0.0  # homing's shift: 0x6064 = joint x k + this

    def position_inc(self, joint_position: float) -> float:
        """0x6064 of a joint position, increments (before the INTEGER32 wrap)."""
        return joint_position * self._k + self.offset_inc

    def stop(self) -> None:
        """Not enabled (or halted in CSV): loops at rest, each mode starts afresh when enabled."""
        self.loops.reset()
        self._entered = None
        self.quick_stopping = False
        self.permille = 0
        self.status_bits = 0

    def run(
        self,
        axis: Drive,
        dt_s: float,
        joint: tuple[float, float, float],
    ) -> int | None:
        """One SYNC's span of the mode in force; an EMCY code for the caller to act on, or None.

        Args:
            axis: the drive (its objects, controlword, mode and current codec).
            dt_s: the span the plant advances, s (> 0).
            joint: the plant's joint position (rad, m), velocity (rad/s, m/s) and current (A).
        """
        mode, controlword = axis.drive.mode, axis.drive.controlword
        position, velocity, current_a = joint
        k = self._k
        self.quick_stopping = False
        position_inc, velocity_inc_s = self.position_inc(position), velocity * k
        if mode != self._entered:
            self._enter(axis, mode, position_inc, velocity_inc_s, position, velocity)
        if mode == MODE_CSV:
            target = axis.velocity.decode(axis.value(od.TARGET_VELOCITY)) / axis.gear_ratio
            current = self.loops.update(
                dt_s, position=position, velocity=velocity, velocity_target=target
            )
            self.permille = axis.current.encode(current)
            return None
        out = self._step(axis, mode, dt_s, controlword, position_inc, velocity_inc_s, current_a)
        self.offset_inc += out.position_shift_inc  # homing: the frame moves, the axis does not
        wanted = _LOOPS.get(out.loop, DriveMode.POSITION)
        if wanted is not self.loops.mode:
            self.loops.set_mode(wanted, position=position, velocity=velocity)
        offset_a = axis.current.decode(out.torque_offset_permille)
        current = self.loops.update(
            dt_s,
            position=position,
            velocity=velocity,
            position_target=(out.position_inc - self.offset_inc) / k,
            velocity_target=_velocity_target(wanted, mode, controlword, out) / k,
            current_target_a=offset_a,
        )
        self.permille = axis.current.encode(current)
        self.status_bits = out.status_bits
        self.demand_inc = out.position_inc
        self.following_error_inc = out.following_error_inc
        return out.emcy_code

    def _enter(
        self,
        axis: Drive,
        mode: int,
        position_inc: float,
        velocity_inc_s: float,
        position: float,
        velocity: float,
    ) -> None:
        """The mode starts from the present state (CiA 402-2 0x6060 while enabled: bumpless)."""
        controlword = axis.drive.controlword
        if mode == MODE_PP:
            self._pp.enter(position_inc, velocity_inc_s, controlword, _pp_params(axis))
        elif mode == MODE_PV:
            self._pv.enter(position_inc, velocity_inc_s, controlword)
        elif mode == MODE_HM:
            self._hm.enter(position_inc, velocity_inc_s, controlword, _homing_params(axis))
        elif mode == MODE_CSP:
            self._csp.enter(position_inc, velocity_inc_s, controlword)
        loop = DriveMode.VELOCITY if mode in (MODE_CSV, MODE_PV) else DriveMode.POSITION
        # PP and HM ramp down from the actual velocity: their demand starts moving with it.
        moving = mode in (MODE_PP, MODE_HM)
        self._restart_loops(loop, position, velocity, velocity if moving else 0.0)
        self._entered = mode
        self.demand_inc = position_inc
        self.following_error_inc = 0.0
        self.status_bits = 0

    def quick_stop(self, axis: Drive, dt_s: float, joint: tuple[float, float, float]) -> None:
        """One SYNC's span of QUICK STOP ACTIVE on a ramp (0x605A in `QUICK_STOP_RAMPS`).

        CiA 402-2 quick stop function: from the actual position and velocity the demand ramps
        to rest on 0x6084 (options 1, 5) or 0x6085 (2, 6), the position loop following it,
        then holds. Back in OPERATION ENABLED (options 5, 6) the mode starts afresh.
        """
        position, velocity, _ = joint
        k = self._k
        if not self.quick_stopping:
            self._quick.reset(self.position_inc(position), velocity * k)
            profile = mode_params.profile_params(axis.value)
            slow = axis.value(od.QUICK_STOP_OPTION) in QUICK_STOP_SLOW_DOWN
            self._quick.stop(
                profile.deceleration_inc_s2 if slow else profile.quick_stop_deceleration_inc_s2
            )
            self._restart_loops(DriveMode.POSITION, position, velocity, velocity)
            self.quick_stopping = True
            self._entered = None
        point = self._quick.step(dt_s)
        current = self.loops.update(
            dt_s,
            position=position,
            velocity=velocity,
            position_target=(point.position_inc - self.offset_inc) / k,
        )
        self.permille = axis.current.encode(current)
        self.status_bits = 0
        self.demand_inc = point.position_inc
        self.following_error_inc = point.position_inc - self.position_inc(position)

    def _restart_loops(
        self, loop: DriveMode, position: float, velocity: float, demand_velocity: float
    ) -> None:
        """The loops in `loop`, started from the present state (bumpless).

        A new mode on the same loop (PP -> CSP, HM -> PP) restarts it as a change of loop
        does; else the position loop kept the old mode's target as its feed-forward's last
        sample and the PI its old error, and the current jumped by kp x velocity a cycle
        after the switch. `demand_velocity` (rad/s, m/s) is the velocity the new position
        demand starts with (PP, HM and quick stop ramp down from the actual velocity): the
        PI is re-based on the error the first update sees, else the current stepped by kp x v.
        """
        self.loops.set_mode(
            loop,
            position=position,
            velocity=velocity,
            velocity_setpoint=demand_velocity,
            restart=True,
        )

    def _step(
        self,
        axis: Drive,
        mode: int,
        dt_s: float,
        controlword: int,
        position_inc: float,
        velocity_inc_s: float,
        current_a: float,
    ) -> ModeOutput:
        if mode == MODE_PP:
            target = axis.value(od.TARGET_POSITION)
            return self._pp.update(dt_s, controlword, target, position_inc, _pp_params(axis))
        if mode == MODE_PV:
            target = axis.value(od.TARGET_VELOCITY)
            return self._pv.update(dt_s, controlword, target, velocity_inc_s, _pv_params(axis))
        if mode == MODE_HM:
            low, high = self._switches
            joint = (position_inc - self.offset_inc) / self._k
            inputs = HomingInputs(
                position_inc, velocity_inc_s, current_a, joint <= low, joint >= high
            )
            return self._hm.update(dt_s, controlword, inputs, _homing_params(axis))
        return self._csp.update(
            dt_s,
            controlword,
            axis.value(od.TARGET_POSITION),
            position_inc,
            _csp_params(axis),
            velocity_offset_inc_s=axis.value(od.VELOCITY_OFFSET),
            torque_offset_permille=axis.value(od.TORQUE_OFFSET),
        )


def _pp_params(axis: Drive) -> PpParams:
    return mode_params.pp_params(axis.value)


def _pv_params(axis: Drive) -> PvParams:
    return mode_params.pv_params(axis.value)


def _csp_params(axis: Drive) -> CspParams:
    return mode_params.csp_params(axis.value)


def _homing_params(axis: Drive) -> HomingParams:
    return mode_params.homing_params(axis.value, axis.units)


def _velocity_target(loop: DriveMode, mode: int, controlword: int, out: ModeOutput) -> float:
    """The loops' velocity target, increments/s: the set-point, or CSP's 0x60B1 offset.

    In the velocity loop the mode's velocity is the set-point; in the position loop only CSP's
    0x60B1 velocity offset is passed.

    The position loop feeds the rate of its position demand forward itself (`DriveLoops`); the
    profile generator's velocity is that same rate, so passing it too would feed it forward
    twice (the axis then ran ahead of 0x6062 by v / kp).
    """
    if loop is DriveMode.VELOCITY:
        return out.velocity_inc_s
    if mode == MODE_CSP and not controlword & CW_HALT:
        return out.velocity_inc_s  # 0x60B1 (a halt's ramp is in the demand's rate)
    return 0.0
