"""The version a sweep's results are keyed by: lca_hil's release and a hash of its code."""

from __future__ import annotations

import hashlib
import importlib.metadata
from pathlib import Path

import lca_control
import lca_sim


def _code_hash() -> str:
    """SHA-256 (12 hex) of every module of lca_sim and lca_control as this process loaded them.

    Taken when this module is imported, so a long-lived worker reports the code it runs, not
    what a later upgrade put on its disk.
    """
    digest = hashlib.sha256()
    for package in (lca_control, lca_sim):
        root = Path(str(package.__file__)).resolve().parent
        for module in sorted(root.rglob("*.py")):
            digest.update(module.relative_to(root.parent).as_posix().encode())
            digest.update(module.read_bytes())
    return digest.hexdigest()[:12]


_CODE_HASH = _code_hash()


def package_version() -> str:
    """lca_hil's version and a hash of its code (part of every point's key).

    `<release>+code.<12 hex>`: the installed release, and the SHA-256 of every module of
    lca_sim and lca_control when this process loaded them (`_code_hash`). The release alone is
    not bumped by every change of the model, and a result of older code must not be taken for a
    result of this one; nor may a worker with other code compute a point (`timed_point`
    refuses it).
    """
    try:
        release = importlib.metadata.version("lca_hil")
    except importlib.metadata.PackageNotFoundError:
        release = "0+unknown"
    return f"{release}+code.{_CODE_HASH}"
