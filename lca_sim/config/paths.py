"""Where the shipped configs are: one light module (no model, no Pinocchio), for the node shells."""

from __future__ import annotations

import importlib
from pathlib import Path

_CONFIG_PACKAGE = "lca_sim.data"


def config_dir() -> Path:
    """The folder holding the shipped configs (robots/, scenarios/, urdf/, ...).

    An installed package has them as the data package `lca_sim.data` (a namespace package, so
    its `__path__` is searched); a source checkout reads the top-level config/ folder directly.
    """
    try:
        package = importlib.import_module(_CONFIG_PACKAGE)
    except ModuleNotFoundError:
        package = None
    for entry in getattr(package, "__path__", []):
        if (Path(entry) / "robots").is_dir():
            return Path(entry)
    return Path(__file__).resolve().parents[2] / "config"
