"""Fingerprints of compiled code, against numba's cache of code compiled from other files.

numba keys the on-disk cache of a function on its own source file only. A cached function
that calls a compiled function of another file carries that callee's code of the day it was
compiled: after an edit of the callee's file, it keeps running the old callee, silently. So a
module whose cached functions call into other files takes a fingerprint of those files'
compiled functions and layout constants when it is imported, and its compiled functions compare
it with the value they were compiled with (a global, frozen into the compiled code): on a
mismatch they refuse to run and the module recompiles them (`rigid_body.CODE_VERSION` for
`kernel.step_in_frame`, `commanded_plant.CODE_VERSION` for the current loops).

From the bytecode, not the files: no I/O, and an edit of a comment changes nothing.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from types import CodeType, FunctionType
from typing import Any

import numpy as np


def fingerprint(namespace: Mapping[str, Any], module: str) -> int:
    """A module's compiled functions and the values they may freeze, as one 63-bit number.

    Every function defined in `module` (numba's dispatchers by their Python function, with
    their compile options and defaults) and every number, string, tuple or array of
    `namespace` (a module's `vars`; dunder names aside), in name order: numba freezes the
    globals a compiled function reads into its code.
    """
    digest = hashlib.sha256()
    for name, value in sorted(namespace.items()):
        if name.startswith("__"):
            continue
        if isinstance(value, (int, float, complex, str, tuple, np.generic)):
            digest.update(f"{name}={value!r};".encode())
        elif isinstance(value, np.ndarray):
            digest.update(f"{name}={value.dtype.str}{value.shape};".encode())
            digest.update(np.ascontiguousarray(value).tobytes())
        function = getattr(value, "py_func", value)
        if isinstance(function, FunctionType) and function.__module__ == module:
            options = getattr(value, "targetoptions", None)
            digest.update(f"{name}{options!r}{function.__defaults__!r}".encode())
            _hash_code(digest, function.__code__)
    return _fold(digest)


def combined(*versions: int) -> int:
    """One 63-bit number for several fingerprints, different when any of them differs."""
    digest = hashlib.sha256()
    for version in versions:
        digest.update(version.to_bytes(8, "little"))
    return _fold(digest)


def _fold(digest: Any) -> int:
    return int.from_bytes(digest.digest()[:8], "little") >> 1  # an int64 in compiled code


def _hash_code(digest: Any, code: CodeType) -> None:
    """Feed a code object's bytecode, names and constants (nested code too) into `digest`."""
    digest.update(code.co_code)
    digest.update(repr(code.co_names).encode())
    for const in code.co_consts:
        if isinstance(const, CodeType):
            _hash_code(digest, const)
        else:
            digest.update(repr(const).encode())
