"""lca_sim.output: an --out that cannot be made is one error line, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from lca_sim.cli import hil, sim
from lca_sim.errors import EXIT_BAD_INPUT, OutputError
from lca_sim.output import atomic_path, output_folder


def _blocked(tmp_path: Path) -> Path:
    """A folder that cannot be made: a file stands where its parent should be."""
    (tmp_path / "file").write_text("in the way")
    return tmp_path / "file" / "out"


def test_output_folder_and_atomic_path_raise_output_errors(tmp_path: Path) -> None:
    blocked = _blocked(tmp_path)
    with pytest.raises(OutputError, match=f"cannot create {blocked}"):
        output_folder(blocked)
    with pytest.raises(OutputError, match=f"cannot create {blocked}"), atomic_path(blocked / "a"):
        pass
    made = output_folder(tmp_path / "new" / "deeper")
    assert made.is_dir()


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "--duration-s", "0.1", "--out"],
        ["paper", "--no-ros", "--out"],
    ],
)
def test_lca_hil_says_it_cannot_write_the_out_folder(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocked = _blocked(tmp_path)
    assert hil.main([*argv, str(blocked)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"lca-hil {argv[0]}: error: cannot create {blocked} (Not a directory)"


def test_lca_sim_says_it_cannot_write_the_out_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocked = _blocked(tmp_path)
    code = sim.main(["run", "--scenario", "hold_pivot", "--no-plot", "--out", str(blocked)])
    assert code == EXIT_BAD_INPUT
    assert f"cannot create {blocked}" in capsys.readouterr().err
