"""What lca-plot marks on a bag's panels: drive-state changes, fault bands, the axes that moved."""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass, field

from lca_sim.model.state_machine import StopState
from lca_sim.ros.bag_read import LEVEL_NAMES, LEVEL_OK, BagData

# An axis whose joint_states position range is at most this (rad, or m for the lift) did not
# move: left out of the figures unless --all-axes. Well above the encoder noise of a held axis,
# far below any commanded motion.
MOVE_THRESHOLD = 1e-4


@dataclass(frozen=True, slots=True)
class StateChange:
    """A change of an axis's drive state.

    Attributes:
        joint: the axis.
        time_s: the first sample in the new state, on the plot's time axis.
        before, after: the drive-state names.
        position: the joint's position at (the joint_states sample nearest to) that time, rad
            (m for the lift); nan without joint_states.
    """

    joint: str
    time_s: float
    before: str
    after: str
    position: float


@dataclass(frozen=True, slots=True)
class FaultBand:
    """A time a status was above OK without a change of level or fault.

    Attributes:
        status: the DiagnosticStatus name (`lca_hil/simulator/pivot`, `drive_chain/pivot`).
        joint: the joint it belongs to, "" for a node's own status.
        level: 1 WARN, 2 ERROR, 3 STALE.
        message: the status message of its first sample.
        start_s, end_s: from its first sample to the next sample of another level or fault (or
            the status's last sample), on the plot's time axis.
    """

    status: str
    joint: str
    level: int
    message: str
    start_s: float
    end_s: float

    @property
    def level_name(self) -> str:
        """WARN, ERROR or STALE."""
        return LEVEL_NAMES.get(self.level, str(self.level))


def state_order(seen: Sequence[str]) -> list[str]:
    """The y-axis order of drive states: the stop states first, then the others as first seen."""
    order = [s.name.lower() for s in StopState]
    for name in seen:
        if name not in order:
            order.append(name)
    return order


def _nearest(times: list[float], t: float) -> int:
    """Index of the sample of `times` (ascending) nearest to `t`."""
    k = bisect_right(times, t)
    if k == 0:
        return 0
    if k == len(times) or t - times[k - 1] <= times[k] - t:
        return k - 1
    return k


def drive_state_changes(data: BagData) -> dict[str, list[StateChange]]:
    """Per axis of drive_chain_states, every change of its drive state, in time order."""
    changes: dict[str, list[StateChange]] = {}
    for joint, drive in data.drives.items():
        found: list[StateChange] = []
        series = data.joints.get(joint)
        for k in range(1, len(drive.state)):
            if drive.state[k] == drive.state[k - 1]:
                continue
            t = drive.time_s[k]
            position = math.nan
            if series is not None and series.time_s:
                position = series.values["position"][_nearest(series.time_s, t)]
            found.append(StateChange(joint, t, drive.state[k - 1], drive.state[k], position))
        changes[joint] = found
    return changes


def _status_joint(name: str, joints: Sequence[str]) -> str:
    """The joint a status belongs to: its name's last part (`.../pivot`), else ""."""
    last = name.rsplit("/", 1)[-1]
    return last if "/" in name and last in joints else ""


def fault_bands(data: BagData) -> list[FaultBand]:
    """Every time a status of /diagnostics (or drive_chain_states) was above OK, by start time.

    A band lasts while the level and the fault (the status's `fault` value, else its message)
    stay the same: a message whose numbers change (a speed) does not split it.
    """
    joints = data.joint_names()
    bands: list[FaultBand] = []
    for name, series in data.statuses.items():
        joint = _status_joint(name, joints)
        start: int | None = None
        for k in range(len(series.level) + 1):
            ended = k == len(series.level)
            same = (
                not ended
                and start is not None
                and (series.level[k], series.kind[k]) == (series.level[start], series.kind[start])
            )
            if start is not None and not same:
                end_s = series.time_s[k] if not ended else series.time_s[-1]
                bands.append(
                    FaultBand(
                        name,
                        joint,
                        series.level[start],
                        series.message[start],
                        series.time_s[start],
                        end_s,
                    )
                )
                start = None
            if not ended and start is None and series.level[k] != LEVEL_OK:
                start = k
    return sorted(bands, key=lambda b: (b.start_s, b.status))


def moved_joints(data: BagData, threshold: float = MOVE_THRESHOLD) -> list[str]:
    """The joints whose joint_states position range exceeds `threshold` (rad, or m).

    A joint without joint_states samples counts as moved (nothing says it did not).
    """
    moved = []
    for joint in data.joint_names():
        series = data.joints.get(joint)
        positions = [] if series is None else series.values["position"]
        finite = [x for x in positions if not math.isnan(x)]
        if series is None or (finite and max(finite) - min(finite) > threshold):
            moved.append(joint)
    return moved


@dataclass
class PlotSpec:
    """What the figures show: the joints with a panel, the ones left out, and notes."""

    joints: list[str]
    left_out: list[str]
    changes: dict[str, list[StateChange]]
    bands: list[FaultBand]
    notes: list[str] = field(default_factory=list)


def plot_spec(data: BagData, all_axes: bool = False) -> PlotSpec:
    """The panels of the figures of `data`: every joint if `all_axes`, else the moved ones."""
    names = data.joint_names()
    notes: list[str] = []
    joints = names
    if not all_axes:
        moved = moved_joints(data)
        if moved:
            joints = moved
            if len(moved) < len(names):
                still = [j for j in names if j not in moved]
                notes.append(
                    f"left out axes that did not move (position range <= {MOVE_THRESHOLD:g}): "
                    f"{', '.join(still)} (--all-axes plots them)"
                )
        elif names:
            notes.append(f"no axis moved more than {MOVE_THRESHOLD:g}: plotting all")
    bands = fault_bands(data)
    for band in bands:
        if not band.joint:
            notes.append(
                f"{band.level_name} {band.status}: {band.message} "
                f"({band.start_s:.3f} s to {band.end_s:.3f} s)"
            )
    return PlotSpec(
        joints=list(joints),
        left_out=[j for j in names if j not in joints],
        changes=drive_state_changes(data),
        bands=bands,
        notes=notes,
    )
