"""Packaging: a plain (non-editable) install carries the shipped configs and the console script."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from support import ROOT


def _tracked_files() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    return [name for name in listed if (ROOT / name).is_file()]


def test_non_editable_install_finds_shipped_configs(tmp_path: Path) -> None:
    """A pip install of a copy of the tree loads the shipped configs from the package."""
    source = tmp_path / "src"
    for name in _tracked_files():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
         "--target", str(target), str(source)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    assert (target / "lca_sim" / "data" / "robots" / "default.yaml").is_file()
    data = target / "lca_sim" / "data"
    for shipped in (
        "faults/pivot_encoder_freeze.yaml",
        "sweeps/gear_wear_pivot.yaml",
        "layouts/lca_hil.plotjuggler.xml",
        "layouts/lca_hil.foxglove.json",
        "ros2_control/controllers.yaml",
        "ros2_control/lca_hil.ros2_control.xacro",
        "dds/fastdds.xml",
    ):
        assert (data / shipped).is_file(), shipped
    assert (target / "bin" / "lca-sim").is_file()
    probe = (
        "import lca_sim, lca_sim.config.loader as c;"
        "r = lca_sim.load_robot('reversible');"
        "print(lca_sim.__file__); print(c.config_dir()); print(r.name, len(r.axes))"
    )
    shutil.rmtree(source)  # nothing may come from the source tree any more
    out = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=tmp_path,
        env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"},
        check=True,
        capture_output=True,
        text=True,
    ).stdout.splitlines()
    assert out[0].startswith(str(target))
    assert out[1] == str(target / "lca_sim" / "data")
    assert out[2] == "lca_reversible 4"
