"""A closed-loop scenario file (config/runs/): what an `lca-hil run` is made of.

`controller` and `simulator` (the nodes' params files), `robot`, `faults` (a fault schedule)
and `duration_s`, each optional (the keys of a closed-loop sweep's base, docs/sweeps.md); a
file it names is a shipped name or a path from the scenario's folder.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

from lca_sim.config.loader import file_ref, resolve
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import ConfigError, unknown_key

SCENARIO_KEYS = ("description", "controller", "simulator", "robot", "faults", "duration_s")
# The shipped folder (config/KIND/) of the files a scenario names.
_FILE_KINDS = {"controller": "ros", "simulator": "ros", "robot": "robots", "faults": "faults"}


@dataclasses.dataclass(frozen=True, slots=True)
class RunScenario:
    """A closed-loop scenario file: what a run is made of (None: not given)."""

    controller: Path | None = None
    simulator: Path | None = None
    robot: Path | None = None
    faults: Path | None = None
    duration_s: float | None = None


def load_run_scenario(name_or_path: str) -> RunScenario:
    """A closed-loop scenario: a shipped name (config/runs/) or a path.

    Raises:
        ConfigError: the file, the bad key and what was expected.
    """
    path = resolve(name_or_path, "runs")
    document = read_yaml(path)
    if not isinstance(document, Mapping):
        raise ConfigError(str(path), "", "expected a closed-loop scenario (a mapping)")
    for key in document:
        if key not in SCENARIO_KEYS:
            raise ConfigError(str(path), str(key), unknown_key(str(key), SCENARIO_KEYS))
    duration = document.get("duration_s")
    if duration is not None and (
        isinstance(duration, bool) or not isinstance(duration, int | float) or not duration > 0
    ):
        raise ConfigError(str(path), "duration_s", f"expected a time > 0 s, got {duration!r}")
    files = {
        key: file_ref(document[key], path, kind, key)
        for key, kind in _FILE_KINDS.items()
        if document.get(key) is not None
    }
    return RunScenario(**files, duration_s=None if duration is None else float(duration))
