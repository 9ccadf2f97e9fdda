"""Fault schedules: which fault acts when, as a user writes it (pure core; docs/faults.md).

A schedule file is a `faults:` list of entries (kind, value, start_s, optional end_s, and the
joint for a joint's fault); a params file's `faults.<owner>.<kind>` values are standing entries
on from t = 0. `FaultInjector.set_schedule` takes either.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from lca_control.parameters import ParameterError, ParamSpec
from lca_sim.errors import ConfigError
from lca_sim.model.faults import JOINT_KIND, LINK, LINK_KIND, SCHEDULABLE, fault_table, split_name


@dataclass(frozen=True, slots=True)
class ScheduledFault:
    """One entry of a fault schedule: `kind` of `owner` is `value` from start_s until end_s."""

    owner: str  # a joint, or LINK
    kind: str
    value: Any
    start_s: float
    end_s: float  # inf: to the end of the run

    def active(self, t_s: float) -> bool:
        """True at simulated time t_s (start inclusive, end exclusive)."""
        return self.start_s <= t_s < self.end_s


def standing_faults(values: Mapping[str, Any], joints: Sequence[str]) -> tuple[ScheduledFault, ...]:
    """The `faults.<owner>.<kind>` values of a params file as entries on from t = 0 for good.

    Raises:
        ParameterError: an unknown name or a value outside its range.
    """
    table = fault_table(joints)
    entries = []
    for name, value in values.items():
        if not name.startswith("faults."):
            continue
        if name not in table:
            raise ParameterError(name, "faults.<joint>.<kind> of a known joint and kind", value)
        checked = table[name].check(value)
        owner, kind = split_name(name)
        if checked != table[name].default:
            entries.append(ScheduledFault(owner, kind, checked, 0.0, math.inf))
    return tuple(entries)


def parse_fault_schedule(
    data: object, source: str, joints: Sequence[str]
) -> tuple[ScheduledFault, ...]:
    """A schedule from YAML data: a mapping with `faults:`, a list of entries.

    Each entry: `kind`, `value`, `start_s`, optional `end_s` (default: never ends) and `joint`
    (required for a joint's fault, absent for a link fault). Entries of one kind and owner may
    not overlap in time.

    Raises:
        ConfigError: the first bad key, named by its path.
    """
    raw = schedule_entries(data, source)
    entries = [_parse_entry(item, source, f"faults[{i}]", joints) for i, item in enumerate(raw)]
    _check_overlaps(entries, source)
    return tuple(sorted(entries, key=lambda e: (e.start_s, e.owner, e.kind)))


def schedule_entries(data: object, source: str) -> list[Any]:
    """The unparsed entries of a schedule document: a mapping with only a `faults` list.

    Raises:
        ConfigError: not such a mapping, or another key.
    """
    if not isinstance(data, Mapping) or "faults" not in data:
        raise ConfigError(source, "faults", "expected a mapping with a 'faults' list")
    extra = sorted(str(k) for k in data if k != "faults")
    if extra:
        raise ConfigError(source, extra[0], "unknown key; a fault schedule has only 'faults'")
    raw = data["faults"]
    if not isinstance(raw, list):
        raise ConfigError(source, "faults", "expected a list of fault entries")
    return raw


def _parse_entry(item: object, source: str, path: str, joints: Sequence[str]) -> ScheduledFault:
    if not isinstance(item, Mapping):
        raise ConfigError(source, path, "expected a mapping with kind, value, start_s")
    allowed = {"joint", "kind", "value", "start_s", "end_s"}
    for key in item:
        if key not in allowed:
            raise ConfigError(source, f"{path}.{key}", f"unknown key; expected {sorted(allowed)}")
    owner, spec = _entry_target(item, source, path, joints)
    if "value" not in item:
        raise ConfigError(source, f"{path}.value", "missing")
    try:
        value = spec.check(item["value"])
    except ParameterError as exc:
        raise ConfigError(source, f"{path}.value", str(exc)) from exc
    start_s = _time(item.get("start_s"), source, f"{path}.start_s")
    end_s = math.inf if item.get("end_s") is None else _time(item["end_s"], source, f"{path}.end_s")
    if not end_s > start_s:
        raise ConfigError(source, f"{path}.end_s", f"expected a time after start_s {start_s:g}")
    return ScheduledFault(owner, spec.name, value, start_s, end_s)


def _entry_target(
    item: Mapping[Any, Any], source: str, path: str, joints: Sequence[str]
) -> tuple[str, ParamSpec]:
    """The owner (a joint, or LINK) and the kind's spec of a schedule entry."""
    kind = item.get("kind")
    if kind not in SCHEDULABLE:
        raise ConfigError(source, f"{path}.kind", f"expected one of {sorted(SCHEDULABLE)}")
    if kind in JOINT_KIND:
        owner = item.get("joint")
        if owner not in joints:
            raise ConfigError(source, f"{path}.joint", f"expected one of {list(joints)}")
        return str(owner), JOINT_KIND[str(kind)].spec
    if "joint" in item:
        raise ConfigError(source, f"{path}.joint", f"{kind} is a link fault: no joint")
    return LINK, LINK_KIND[str(kind)].spec


def _time(value: object, source: str, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0.0:
        raise ConfigError(source, path, f"expected a time >= 0 s, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(source, path, f"expected a finite time, got {value!r}")
    return float(value)


def _check_overlaps(entries: Sequence[ScheduledFault], source: str) -> None:
    by_target: dict[tuple[str, str], list[ScheduledFault]] = {}
    for entry in entries:
        by_target.setdefault((entry.owner, entry.kind), []).append(entry)
    for (owner, kind), group in by_target.items():
        group.sort(key=lambda e: e.start_s)
        for before, after in itertools.pairwise(group):
            if after.start_s < before.end_s:
                raise ConfigError(
                    source,
                    "faults",
                    f"two entries of {kind} on {owner} overlap at {after.start_s:g} s",
                )
