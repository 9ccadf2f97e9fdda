"""The typed parameter tables: one check per spec, one message format, --help from the table."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_control.controller import CONTROLLER_PARAMETERS, validate_controller_params
from lca_control.parameters import (
    ParameterError,
    ParameterTable,
    ParamKind,
    ParamSpec,
    non_negative,
    positive,
)

PERIOD = positive("period_s", 0.5, "a period, s", high=60.0)


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_a_positive_double_takes_exactly_its_documented_range(value: float) -> None:
    """(0, 60]: inside it the value comes back as a float, outside it the error names it."""
    inside = math.isfinite(value) and 0.0 < value <= 60.0
    if inside:
        assert PERIOD.check(value) == value
    else:
        with pytest.raises(ParameterError, match=r"^period_s: expected a number in \(0, 60\]"):
            PERIOD.check(value)


def test_an_integer_is_a_double_but_a_bool_is_not_a_number() -> None:
    """500 is a valid double (the YAML and `-p x:=500` spelling); True is refused."""
    assert PERIOD.check(5) == 5.0 and isinstance(PERIOD.check(5), float)
    with pytest.raises(ParameterError, match="got True"):
        PERIOD.check(True)


@pytest.mark.parametrize(
    ("spec", "bad", "expected"),
    [
        (ParamSpec("mode", ParamKind.STRING, "a", "m", choices=("a", "b")), "c", "one of a, b"),
        (ParamSpec("n", ParamKind.INTEGER, 1, "n", 1, 127), 128, r"an integer in \[1, 127\]"),
        (ParamSpec("n", ParamKind.INTEGER, 1, "n", 1, 127), 1.0, "an integer"),
        (ParamSpec("on", ParamKind.BOOL, True, "b"), "yes", "true or false"),
        (
            ParamSpec("ids", ParamKind.INTEGER_ARRAY, [1], "i", 1, 127),
            [1, 0],
            r"an integer in \[1, 127\]",
        ),
        (ParamSpec("names", ParamKind.STRING_ARRAY, ["a"], "s"), "a", "an array"),
        (non_negative("t_s", 0.0, "t"), -1e-9, r"a number in \[0, inf\)"),
    ],
)
def test_every_refusal_names_the_parameter_and_what_was_expected(
    spec: ParamSpec, bad: object, expected: str
) -> None:
    """One format: `<name>: expected <what>, got <value>`."""
    with pytest.raises(ParameterError, match=f"^{spec.name}: expected {expected}"):
        spec.check(bad)


def test_a_default_outside_its_own_range_is_refused_when_the_table_is_built() -> None:
    """A table cannot ship a default its own rules reject."""
    with pytest.raises(ParameterError, match="period_s"):
        positive("period_s", 0.0, "a period, s")
    with pytest.raises(ValueError, match="twice"):
        ParameterTable((PERIOD, PERIOD))


def test_check_all_fills_defaults_and_refuses_unknown_names() -> None:
    """Missing names take their default; a misspelt one is an error naming it."""
    table = ParameterTable((PERIOD, ParamSpec("on", ParamKind.BOOL, True, "b", live=False)))
    assert table.check_all({}) == {"period_s": 0.5, "on": True}
    assert table.read_only == frozenset({"on"})
    with pytest.raises(ParameterError, match=r"^perod_s: expected one of period_s, on"):
        table.check_all({"perod_s": 1.0})


def test_help_lists_every_controller_parameter_with_type_default_range_and_liveness() -> None:
    """The --help text comes from the table: one line per parameter, nothing left out."""
    lines = CONTROLLER_PARAMETERS.describe().splitlines()
    assert len(lines) == len(CONTROLLER_PARAMETERS.names)
    for line, spec in zip(lines, CONTROLLER_PARAMETERS, strict=True):
        assert line.strip().startswith(f"{spec.name} ({spec.kind.value}; default ")
        assert ("read-only" if not spec.live else "live") in line
    assert (
        "velocity_ti_s (double; default 0.01; (0, inf); live)" in CONTROLLER_PARAMETERS.describe()
    )


@pytest.mark.parametrize("name", ["trapezoid_accel_s", "ramp_duration_s"])
def test_profile_parameters_are_checked_when_their_profile_is_not_running(name: str) -> None:
    """A bad value of an idle profile fails now, not later when the profile is switched on."""
    values = {**CONTROLLER_PARAMETERS.defaults(), "reference_source": "hold", name: 0.0}
    with pytest.raises(ParameterError, match=f"^{name}: expected a number in"):
        validate_controller_params(values)
