"""Fault schedules as a user writes them (`lca_sim.model.fault_schedule`)."""

from __future__ import annotations

import math

import pytest
import yaml

from lca_sim.config.paths import config_dir
from lca_sim.errors import ConfigError
from lca_sim.model.fault_schedule import parse_fault_schedule, standing_faults

CONFIG = config_dir()


def test_schedule_errors_name_the_bad_key() -> None:
    """One clear error per bad schedule, naming its key; overlaps refused; shipped ones parse."""
    joints = ("l_arm", "pivot", "c_arc", "lift")
    good = {"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 1.0}]}
    assert parse_fault_schedule(good, "f", joints)[0].end_s == math.inf
    cases = [
        ({"faults": [{"joint": "wrist", "kind": "jam", "value": True, "start_s": 0}]}, "joint"),
        ({"faults": [{"joint": "pivot", "kind": "melt", "value": 1, "start_s": 0}]}, "kind"),
        ({"faults": [{"joint": "pivot", "kind": "supply_sag", "value": 2, "start_s": 0}]}, "value"),
        ({"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": -1}]}, "start_s"),
        ({"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 2, "end_s": 1}]},
         "end_s"),
        ({"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 0, "x": 1}]},
         "faults[0].x"),
        ({"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 0, "end_s": 2},
                     {"joint": "pivot", "kind": "jam", "value": True, "start_s": 1}]}, "overlap"),
        ({"faults": [{"joint": "pivot", "kind": "state_drop", "value": 0.5, "start_s": 0}]},
         "link fault"),
    ]  # fmt: skip
    for data, word in cases:
        with pytest.raises(ConfigError, match=word.replace("[", r"\[").replace("]", r"\]")):
            parse_fault_schedule(data, "f", joints)
    shipped = CONFIG / "faults"
    for path in shipped.glob("*.yaml"):
        assert parse_fault_schedule(yaml.safe_load(path.read_text()), str(path), joints)


def test_standing_faults_are_the_params_files_values_on_for_good() -> None:
    """`faults.<owner>.<kind>` values off their default become entries from 0 to the end."""
    joints = ("l_arm", "pivot", "c_arc", "lift")
    values = {"faults.pivot.jam": True, "faults.lift.encoder_bias": 0.0, "enabled": True}
    (entry,) = standing_faults(values, joints)
    assert (entry.owner, entry.kind, entry.value) == ("pivot", "jam", True)
    assert (entry.start_s, entry.end_s) == (0.0, math.inf)
    with pytest.raises(ValueError, match=r"faults\.wrist\.jam"):
        standing_faults({"faults.wrist.jam": True}, joints)
