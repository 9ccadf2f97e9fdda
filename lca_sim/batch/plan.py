"""A sweep read from its files: the spec, the documents it names, every point's task.

The spec is checked by `lca_sim.batch.spec`, the files its base names are read by
`lca_sim.config.sweep_base` (as `lca-hil run` reads them), and a closed-loop point is built
by `lca_sim.batch.closed_loop_config`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from lca_sim.batch.closed_loop_config import closed_loop_builder
from lca_sim.batch.point import Documents
from lca_sim.batch.runner import SweepPlan, run_plan
from lca_sim.batch.spec import SweepSpec, parse_spec
from lca_sim.batch.tasks import build_tasks
from lca_sim.batch.version import package_version
from lca_sim.config.sweep_base import (
    base_fault_schedule,
    base_node_files,
    base_robot,
    base_scenario,
)
from lca_sim.config.yaml_files import read_yaml


def load_spec(spec_path: Path) -> tuple[SweepSpec, Documents]:
    """The validated spec and the base documents it names.

    Raises:
        ConfigError: the spec (or a file it names), the key, what was expected.
    """
    spec = parse_spec(read_yaml(spec_path), str(spec_path))
    base = spec.base
    controller: dict[str, Any] = {}
    simulator: dict[str, Any] = {}
    scenario: Any = {}
    faults: tuple[Any, ...] = ()
    faults_source = ""
    if spec.kind == "closed_loop":
        controller, simulator, simulator_path = base_node_files(base, spec_path)
        faults, faults_source = base_fault_schedule(base, simulator, spec_path, simulator_path)
    if spec.kind == "open_loop":
        scenario = base_scenario(base, spec_path)
    urdf_xml, robot_doc = base_robot(base, simulator, spec_path)
    documents = Documents(
        base=dict(base),
        robot=dict(robot_doc),
        urdf_xml=urdf_xml,
        controller=controller,
        simulator=simulator,
        scenario=dict(scenario),
        faults=faults,
        faults_source=faults_source,
    )
    return spec, documents


def plan_sweep(spec_path: Path) -> SweepPlan:
    """The sweep of a spec file, validated whole: every point's task built before any runs.

    Raises:
        ConfigError: a bad spec, a file it names, or a bad point (its key and values).
    """
    start = time.perf_counter()
    version = package_version()
    spec, documents = load_spec(spec_path)
    tasks = build_tasks(spec, documents, version, closed_loop_builder)
    return SweepPlan(spec_path, spec, tuple(tasks), version, time.perf_counter() - start)


def run_sweep(spec_path: Path, out: Path, **options: Any) -> dict[str, Any]:
    """Run the sweep of a spec file into `out`; returns the run log.

    `options` are `lca_sim.batch.runner.run_plan`'s (scheduler, workers, stream, function,
    client).

    Raises:
        ConfigError: a bad spec, before anything runs.
    """
    return run_plan(plan_sweep(spec_path), out, **options)
