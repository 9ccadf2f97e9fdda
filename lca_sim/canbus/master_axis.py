"""What the CANopen master keeps per drive: node, PDO binding, state and watch stamps.

docs/can.md, "The PDO layout the bridge maps (compact)" and "Watchdogs and safety".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import canopen

from lca_sim.canbus.master_pdo import CONTROLWORD_REFRESH_CYCLES, RpdoPacker
from lca_sim.canbus.master_state import AxisState
from lca_sim.cia402 import controlword as ctl
from lca_sim.cia402.codec import Codec, DriveUnits
from lca_sim.cia402.controlword import TorqueScale, Want
from lca_sim.cia402.device import (
    CW_HALT,
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    PowerState,
    power_state_of,
)


@dataclass(slots=True)
class MasterAxis:
    """The master's bookkeeping for one drive."""

    joint: str
    node: canopen.RemoteNode
    k_t: float
    gear: float
    scale: TorqueScale | None = None
    units: DriveUnits | None = None  # 0x6075, 0x6076, 0x608F as read by init()
    velocity: Codec | None = None  # motor rad/s <-> increments/s, from `units` (0x60FF)
    position: Codec | None = None  # motor rad <-> increments, from `units` (0x607A, 0x6064)
    state: AxisState = field(default_factory=AxisState)
    controlword: int = 0
    command_a: float = 0.0
    command_rad_s: float = 0.0  # CSV: the joint velocity command
    # CSP: the joint position command (rad, m); NaN: none since the drive was enabled, so the
    # target is the drive's own position (a CSP target never jumps at enabling).
    command_rad: float = math.nan
    mode: int = MODE_CST  # 0x6060 as init() wrote it
    last_tpdo_t: float = 0.0
    fresh: int = 0  # a bit per every-SYNC TPDO that arrived this cycle
    sync_mask: int = 0  # the bits of all its every-SYNC TPDOs: the cycle's complete at this
    seen: int = 0  # the every-SYNC TPDO bits that came since the last complete cycle
    last_heartbeat_t: float = 0.0  # monotonic reception of its last heartbeat (or the arming)
    heartbeat_lost: bool = False  # silent beyond the consumer time, until its next heartbeat
    emcy_code: int = 0  # the latched one (a fault reaction), 0: none
    advisory_code: int = 0  # the last advisory one (`emcy.ADVISORY`), 0: none
    advisory_count: int = 0
    has_drive_state: bool = False
    decoded: frozenset[str] = frozenset()  # the AxisState fields its TPDOs fill
    rpdo: Any = None  # canopen PdoMap of the RPDO with the target torque, sent each cycle
    cw_rpdo: Any = None  # the one with the controlword when it is another RPDO, else None
    cw_sent: int = -1  # the controlword last sent in `cw_rpdo`
    cw_age: int = 0  # cycles since `cw_rpdo` was last sent
    cw_var: Any = None
    target_var: Any = None  # the mode's target in `rpdo`: 0x6071 (CST) or 0x60FF (CSV)
    packer: RpdoPacker | None = None  # packs both RPDOs per cycle (None: canopen does)
    rpdo_cob_id: int = 0
    cw_cob_id: int = 0
    tpdo_cob_ids: tuple[int, ...] = ()  # the COB-IDs of its TPDOs the master decodes
    # (COB-ID, decoder) the last init() subscribed, unsubscribed by the next one
    tpdo_decoders: tuple[tuple[int, Any], ...] = ()
    boot_watch: Any = None  # its boot-up callback on the network, once subscribed
    emcy_watch: Any = None  # its EMCY consumer, once added
    statuswords_received: int = 0
    statuswords_at_reset: int = 0  # `statuswords_received` when recover() asked for a reset

    def add_rpdo_frames(self, frames: list[tuple[int, bytes]], want: Want, halted: bool) -> bool:
        """Append the drive's RPDO frame(s) this cycle: the controlword's if due, the target's.

        Returns:
            Whether the current command was clamped to 0x6072.
        """
        axis = self
        clamped = False
        state = power_state_of(axis.state.statusword)  # `AxisState.power_state`, one call
        controlword = ctl.next_controlword(state, want, axis.controlword)
        target = 0
        running = want is Want.ENABLED and state is PowerState.OPERATION_ENABLED
        if axis.mode == MODE_CSP and axis.position is not None:
            target = axis.csp_target(running and not halted)
        if running and halted:
            controlword |= CW_HALT
        elif axis.mode == MODE_CSP:
            pass  # the position target above, in every state
        elif running and axis.mode == MODE_CSV and axis.velocity is not None:
            target = axis.velocity.encode(axis.command_rad_s * axis.gear)
        elif running and axis.scale is not None:
            target, clamped = axis.scale.target_permille(axis.command_a)
        axis.controlword = controlword
        packer = axis.packer
        if packer is None:  # an object at a bit offset: canopen packs the mapping
            axis.cw_var.raw = controlword
            axis.target_var.raw = target
            cw_data, target_data = bytes(axis.cw_var.pdo_parent.data), bytes(axis.rpdo.data)
        else:
            cw_data, target_data = packer.pack(controlword, target)
        cw_rpdo = axis.cw_rpdo
        if cw_rpdo is not None:
            axis.cw_age += 1
            if controlword != axis.cw_sent or axis.cw_age >= CONTROLWORD_REFRESH_CYCLES:
                axis.cw_sent, axis.cw_age = controlword, 0
                frames.append((axis.cw_cob_id, cw_data))
        frames.append((axis.rpdo_cob_id, target_data))
        return clamped

    def csp_target(self, commanded: bool) -> int:
        """0x607A of a CSP drive, increments: the command, or where the drive is.

        Sent in every state, not only while enabled: the drive latches it at the SYNC, and the
        cycle in which it becomes enabled must not find a stale or zero target (CiA 402-2: in
        CSP the drive follows 0x607A from the moment it is enabled). Not commanded (halted,
        not enabled): its own position, and the command is forgotten, so a drive enabled
        again holds until the next position command.
        """
        assert self.position is not None
        if not commanded:
            self.command_rad = math.nan
        joint_rad = self.command_rad if math.isfinite(self.command_rad) else self.state.position
        return self.position.encode(joint_rad * self.gear)
