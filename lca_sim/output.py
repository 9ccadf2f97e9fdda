"""Writing the tools' files atomically: any file, CSV tables and strict JSON.

A file is written to a temporary name in the target folder and renamed into place, so an
interrupted tool never leaves a half-written file behind. JSON is strict (RFC 8259): a
non-finite float (NaN, +-Infinity, which Python's `json` would write as the invalid tokens
`NaN`/`Infinity`) becomes `null`, and the document's top-level `"reasons"` object says why,
keyed by the value's path (`"summary.transition_time_s"`, `"runs[2].rate"`). Nothing here
needs the model, so `lca-plot` (which only reads bags) does not load numba or Pinocchio
through it; the PNGs are written by `lca_sim.cli.plotting.save_png` (matplotlib stays in the
entry layer).
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from lca_sim.errors import OutputError

REASONS_KEY = "reasons"  # where a strict JSON document says why a value is null


def number_cell(x: float) -> str:
    """A float as a CSV cell: shortest round-trip form, `nan` as such."""
    return "nan" if math.isnan(x) else repr(float(x))


def cell(x: object) -> str:
    """A CSV cell: floats in shortest round-trip form (nan as such), the rest as text."""
    return number_cell(float(x)) if isinstance(x, float | np.floating) else str(x)


def output_folder(folder: Path) -> Path:
    """`folder`, made with its parents if missing.

    Raises:
        OutputError: it cannot be made (a file in the way, no permission, a read-only place).
    """
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {folder} ({exc.strerror or exc})") from None
    return folder


@contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """A temporary path next to `target`, renamed onto it only if the block succeeds.

    Raises:
        OutputError: the folder cannot be made or written to.
    """
    output_folder(target.parent)
    try:
        fd, tmp_name = tempfile.mkstemp(
            prefix=f".{target.name}.", suffix=".part", dir=target.parent
        )
    except OSError as exc:
        raise OutputError(f"cannot write {target} ({exc.strerror or exc})") from None
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


def _finite_only(value: Any, path: str, nulled: dict[str, str]) -> Any:
    """`value` with every non-finite float replaced by None; `nulled` gets path -> the value."""
    if isinstance(value, float | np.floating):
        if math.isfinite(value):
            return float(value)
        nulled[path] = repr(float(value))
        return None
    if isinstance(value, Mapping):
        prefix = f"{path}." if path else ""
        return {str(k): _finite_only(v, f"{prefix}{k}", nulled) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_only(v, f"{path}[{i}]", nulled) for i, v in enumerate(value)]
    return value


def strict_json(
    data: Any, reasons: Mapping[str, str] | None = None, *, indent: int | None = 2
) -> str:
    """`data` as strict JSON text: non-finite floats as null, with why under "reasons".

    Args:
        data: JSON-able values (dicts, lists, str, int, float, bool, None; numpy floats too).
        reasons: why a value may be missing, by its path (`"transition_time_s"`); a nulled
            value without one is explained as "not a finite number (nan)".
        indent: as for `json.dumps`; None gives one line (a benchmark's JSON line).

    Returns:
        The JSON text (no trailing newline). When a value was nulled and `data` is a dict,
        the document gains a top-level "reasons" object {path: why} (merged with one it has).

    Raises:
        ValueError: a value JSON cannot hold without NaN or Infinity (never for finite data).
    """
    nulled: dict[str, str] = {}
    clean = _finite_only(data, "", nulled)
    if nulled and isinstance(clean, dict):
        why = dict(clean.get(REASONS_KEY) or {})
        for path, value in nulled.items():
            why.setdefault(path, (reasons or {}).get(path, f"not a finite number ({value})"))
        clean[REASONS_KEY] = why
    return json.dumps(clean, indent=indent, allow_nan=False)


def write_json(path: Path, data: Any, reasons: Mapping[str, str] | None = None) -> None:
    """Write `data` as strict, indented JSON atomically (see `strict_json`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(strict_json(data, reasons) + "\n", encoding="utf-8")
