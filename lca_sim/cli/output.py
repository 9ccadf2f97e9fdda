"""Writing the tools' files atomically: any file, CSV tables and matplotlib PNGs (the I/O edge).

A file is written to a temporary name in the target folder and renamed into place, so an
interrupted tool never leaves a half-written file behind. Nothing here needs the model, so
`lca-plot` (which only reads bags) does not load numba or Pinocchio through it.
"""

from __future__ import annotations

import csv
import math
import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

PNG_DPI = 110  # every PNG the tools write


def number_cell(x: float) -> str:
    """A float as a CSV cell: shortest round-trip form, `nan` as such."""
    return "nan" if math.isnan(x) else repr(float(x))


def cell(x: object) -> str:
    """A CSV cell: floats in shortest round-trip form (nan as such), the rest as text."""
    return number_cell(float(x)) if isinstance(x, float | np.floating) else str(x)


@contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """A temporary path next to `target`, renamed onto it only if the block succeeds."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o666 & ~umask)  # mkstemp makes 0600; the result is an ordinary file
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_table(path: Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Write a CSV table atomically, floats in shortest round-trip form."""
    with atomic_path(path) as tmp, tmp.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(header)
        writer.writerows([cell(x) for x in row] for row in rows)


def save_png(fig: Figure, path: Path) -> None:
    """Lay out and write a matplotlib figure as PNG, atomically."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=PNG_DPI)
