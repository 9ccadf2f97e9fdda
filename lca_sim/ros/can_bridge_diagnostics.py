"""The CAN bridge's /diagnostics: one `lca_hil/can_bridge` status and one per drive.

`BridgeDiagnostics` builds them each diagnostics period from the master's counters and state
and a `BridgeView` of the node (lifecycle, its own counters), and keeps what is measured over
a period: frame and bit rates (the bus load), the share of late commands, the controller's
command losses. The texts and keys are documented in docs/can.md and docs/contract.md.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node

from lca_sim.canbus import emcy
from lca_sim.canbus.lockstep import LockstepLoop
from lca_sim.canbus.master import Cia402Master
from lca_sim.cia402.bus_load import bus_load_pct
from lca_sim.config.can_bridge_params import CanBridgeNodeParams
from lca_sim.ros.node_util import status
from lca_sim.ros.plant_contract import PlantPublisher, worst_first

BRIDGE_STATUS = "lca_hil/can_bridge"
# More than this share of the cycles sending the previous command again is a WARN ...
LATE_COMMAND_SHARE = 0.05
# ... judged over this many diagnostics periods, all of them with commands flowing: the WARN says
# the loop runs with two periods of delay, a state of the loop, not a moment. A one-off stall of
# the host (70 ms are 35 late cycles at 500 Hz, 7 % of one second) does not raise it, nor does
# the controller's start (its first commands come late while DDS and both processes warm up:
# 5-10 % of the first second on the 2-core host); lateness that lasts does, within this many
# periods of the first command.
LATE_COMMAND_PERIODS = 3


class LateShare:
    """The share of late commands over the last `LATE_COMMAND_PERIODS` diagnostics periods."""

    def __init__(self) -> None:
        self._marks: deque[tuple[int, int]] = deque([(0, 0)], maxlen=LATE_COMMAND_PERIODS + 1)

    def update(self, in_time: int, late: int) -> tuple[float, int] | None:
        """Take the counters at a diagnostics period; (share, cycles) of the window, or None.

        None until the window lies wholly after the first command (it starts at a period whose
        counters had already counted commands).
        """
        self._marks.append((in_time, late))
        first_in_time, first_late = self._marks[0]
        if first_in_time + first_late == 0:
            return None
        window_late = late - first_late
        window_all = in_time - first_in_time + window_late
        return (window_late / window_all, window_all) if window_all else None


Finding = tuple[bytes, str]


@dataclass(frozen=True, slots=True)
class BridgeView:
    """What the node adds to its status, as it stands at one diagnostics period.

    Attributes:
        lifecycle_state: the lifecycle state's label.
        active: lifecycle ACTIVE (states published, commands passed on).
        params: the parameters in force.
        failures: a failed transition or init, each an ERROR text.
        counts: the node's own counters, in the order of the status's values.
        refused: the node refused a command (wrong interface, a refused JointState).
        warnings: WARN texts of the node's own (axes no command topic serves).
    """

    lifecycle_state: str
    active: bool
    params: CanBridgeNodeParams
    failures: tuple[str, ...]
    counts: dict[str, int]
    refused: bool
    warnings: tuple[str, ...] = ()


class BridgeDiagnostics:
    """The bridge's /diagnostics statuses, with what they measure from one period to the next.

    Args:
        node: the bridge node (its logger: a command loss is logged when it begins and ends).
        plant: the node's plant publisher (the ROS graph's health, joint_states' subscribers).
    """

    def __init__(self, node: Node, plant: PlantPublisher) -> None:
        self._plant = plant
        self._log = node.get_logger()  # type: ignore[no-untyped-call]  # rclpy is untyped here
        self._last_t = time.monotonic()
        self._last_frames_bits = (0, 0)  # frames and bits at the previous diagnostics
        self._late_share = LateShare()
        self._commands_lost = False  # the controller peer, as the status reports it
        self.command_losses = 0

    def statuses(
        self, view: BridgeView, master: Cia402Master | None, loop: LockstepLoop | None
    ) -> list[DiagnosticStatus]:
        """The bridge's status, then one per drive (none while no bus is open)."""
        if master is None:
            return [self._unconfigured_status(view)]
        codes = master.emcy_codes()
        advisory = master.advisory_emcy()
        return [
            self._bridge_status(view, master, loop),
            *(_axis_status(master, j, codes[j], advisory[j]) for j in view.params.joints),
        ]

    def _unconfigured_status(self, view: BridgeView) -> DiagnosticStatus:
        """The bridge's status with no bus open: the lifecycle state, or the failure."""
        state = view.lifecycle_state
        found = [(DiagnosticStatus.OK, f"{state}: no bus open; configure (lifecycle) to start")]
        level, message = worst_first([*found, *_failures(view)])
        values: dict[str, object] = {
            "lifecycle_state": state,
            "interface": view.params.interface,
            "channel": view.params.channel,
            "cycle_hz": view.params.cycle_hz,
        }
        return status(BRIDGE_STATUS, level, message, values)

    def _bridge_status(
        self, view: BridgeView, master: Cia402Master, loop: LockstepLoop | None
    ) -> DiagnosticStatus:
        p = view.params
        c = master.counters
        now = time.monotonic()
        span = max(now - self._last_t, 1e-6)
        frames = c.frames_sent + c.frames_received
        bits = c.bits_sent + c.bits_received
        last_frames, last_bits = self._last_frames_bits
        frames_per_s = (frames - last_frames) / span
        bits_per_s = (bits - last_bits) / span
        self._last_t, self._last_frames_bits = now, (frames, bits)
        latched = master.latched_reason()
        if latched:
            first = (DiagnosticStatus.ERROR, latched)
        elif not view.active:
            first = (
                DiagnosticStatus.OK,
                f"{view.lifecycle_state}: drives out of operation, commands ignored; activate "
                "(lifecycle) to run",
            )
        else:
            first = (DiagnosticStatus.OK, "commands again" if self.command_losses else "running")
        found: list[Finding] = [first, *_failures(view)]
        found += [(DiagnosticStatus.WARN, text) for text in view.warnings]
        if c.commands_rejected or c.send_failures or view.refused:
            found.append((DiagnosticStatus.WARN, "rejected commands or failed sends"))
        peer = self._command_health(master, master.now())
        _merge_findings(found, [] if peer is None else [peer])
        _merge_findings(found, self._lockstep_findings(view, loop, now))
        stall = master.cycle_stall()  # no complete cycle: a TPDO lost (latched while enabled)
        if stall and not latched:
            found.append((DiagnosticStatus.WARN, stall))
        late = self._late_commands(c.commands_in_time, c.commands_late)
        if late is not None:
            found.append(late)
        values: dict[str, object] = {
            "lifecycle_state": view.lifecycle_state,
            "interface": p.interface,
            "channel": p.channel,
            "cycle_hz": p.cycle_hz,
            "frames_per_s": frames_per_s,
            "bus_load_pct": bus_load_pct(bits_per_s, float(p.bitrate)),
            "command_age_s": master.command_age_s(master.now()),
            **_latency_values(master.take_command_latencies()),
            **_lockstep_values(loop),
            **view.counts,
            "command_losses": self.command_losses,
            **{k: getattr(c, k) for k in c.__slots__},
        }
        graph = self._plant.graph_health(values)
        if graph is not None:
            found.append(graph)
        level, message = worst_first(found)
        return status(BRIDGE_STATUS, level, message, values)

    def _command_health(self, master: Cia402Master, now: float) -> Finding | None:
        """The controller peer: WARN while the drives are halted for want of commands.

        ERROR once the silence has lasted into the quick stop, which holds until ~/enable.
        Nothing while the drives are not enabled. Before the first command ever the bridge
        waits for its controller, which is no fault: OK with the master's text. The loss is
        logged once when it begins (by the master, with its reaction) and once here when
        commands return.
        """
        silence = master.command_silence(now)
        if silence is None:
            if self._commands_lost:
                self._commands_lost = False
                self._log.info("commands again")
            return None
        latched, why = silence
        if not latched and not master.counters.commands_accepted:
            return DiagnosticStatus.OK, why  # waiting for the controller's first command
        if not self._commands_lost and master.counters.commands_accepted:
            self._commands_lost = True
            self.command_losses += 1
            self._log.warning(f"{why}; is the controller running?")
        return (DiagnosticStatus.ERROR if latched else DiagnosticStatus.WARN), why

    def _late_commands(self, in_time: int, late: int) -> Finding | None:
        """WARN while too many cycles of the last few diagnostics periods sent an old command.

        More than LATE_COMMAND_SHARE of the cycles of the last LATE_COMMAND_PERIODS periods
        sent the previous command again (the controller's answer came after the SYNC it was
        for): the loop then runs with two periods of delay instead of one, and a loop tuned for
        one (the paper's gains) rings. The host is too slow for `cycle_hz`.
        """
        window = self._late_share.update(in_time, late)
        if window is None or window[0] <= LATE_COMMAND_SHARE:
            return None
        share, cycles = window
        return (
            DiagnosticStatus.WARN,
            f"{100.0 * share:.0f} % of the last {cycles} cycles sent the previous command "
            "(the controller answered after the next SYNC): the loop has two periods of delay; "
            "lower cycle_hz or unload the host",
        )

    def _lockstep_findings(
        self, view: BridgeView, loop: LockstepLoop | None, wall_s: float
    ) -> list[Finding]:
        """Lockstep: OK while its start waits for subscribers, WARN while time stands.

        As the simulator's lockstep: a start waiting for its subscribers is no fault; simulated
        time standing for want of the controller's answer is.
        """
        if loop is None or not view.active:
            return []
        if not loop.started:
            matched = self._plant.joint_pub.get_subscription_count()
            return [
                (
                    DiagnosticStatus.OK,
                    f"lockstep: waiting for {view.params.lockstep_subscribers} joint_states "
                    f"subscribers ({matched} so far): simulated time has not started",
                )
            ]
        waited_s = loop.waiting_for_command_s(wall_s)
        if waited_s > view.params.lockstep_resend_s:
            return [
                (
                    DiagnosticStatus.WARN,
                    f"lockstep: no command for {waited_s:.1f} s; simulated time stands at "
                    f"{loop.clock.now():.3f} s (is the controller running?)",
                )
            ]
        return []


def _failures(view: BridgeView) -> list[Finding]:
    return [(DiagnosticStatus.ERROR, text) for text in view.failures]


def _axis_status(
    master: Cia402Master, joint: str, latched: int, advisory: tuple[int, int]
) -> DiagnosticStatus:
    """One drive: ERROR with the latched EMCY's text, WARN for an advisory EMCY, else OK.

    The message is the power state, then the EMCY decoded to text (`emcy.describe`).
    """
    s = master.axis_state(joint)
    power = s.power_state
    message = power.name.lower() if power else f"statusword 0x{s.statusword:04X}"
    level = DiagnosticStatus.OK
    code, count = advisory
    ours = master.has_drive_state()  # lca_hil's drive: its own codes have text
    if code:
        level = DiagnosticStatus.WARN
        message += f"; EMCY {emcy.describe(code, ours)} ({count} received)"
    if latched:
        level = DiagnosticStatus.ERROR
        message += f"; EMCY {emcy.describe(latched, ours)}: stopped until ~/recover"
    return status(
        f"{BRIDGE_STATUS}/{joint}",
        level,
        message,
        {
            "statusword": f"0x{s.statusword:04X}",
            "emcy_code": f"0x{latched:04X}",
            "emcy_text": emcy.describe(latched, ours) if latched else "none",
            "advisory_emcy": emcy.describe(code, ours) if code else "none",
            "advisory_emcy_count": count,
            "position": s.position,
            "current_a": s.current_a,
        },
    )


def _lockstep_values(loop: LockstepLoop | None) -> dict[str, object]:
    if loop is None:
        return {}
    c = loop.counters
    return {
        "timing_mode": "lockstep",
        "sim_time_s": loop.clock.now(),
        **{f"lockstep_{k}": getattr(c, k) for k in c.__slots__},
    }


def _merge_findings(found: list[Finding], more: list[Finding]) -> None:
    """Add findings to a status's list: WARN and above appended, OK ones as its text.

    An OK finding (a wait that is no fault: for the first command, for subscribers) becomes
    the status's text while nothing worse stands first.
    """
    for level, text in more:
        if level != DiagnosticStatus.OK:
            found.append((level, text))
        elif found[0][0] == DiagnosticStatus.OK:
            found[0] = (level, text)


def _latency_values(latencies_s: list[float]) -> dict[str, object]:
    """SYNC -> first command wall latency over a diagnostics period: p50, p99, max in ms.

    NaN when no command came (strict JSON tools read the level and message first).
    """
    if not latencies_s:
        return {f"command_latency_ms_{k}": math.nan for k in ("p50", "p99", "max")}
    ms = np.asarray(latencies_s) * 1e3
    return {
        "command_latency_ms_p50": float(np.percentile(ms, 50)),
        "command_latency_ms_p99": float(np.percentile(ms, 99)),
        "command_latency_ms_max": float(ms.max()),
    }
