"""A payload on a link of the URDF: a point mass added to the link's inertial (a sweep's base)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from typing import Any

import numpy as np

from lca_sim.batch.checks import finite_number, mapping_of
from lca_sim.errors import ConfigError, InvalidValueError


def _floats(text: str | None, n: int, what: str) -> list[float]:
    values = [float(x) for x in (text or " ".join(["0"] * n)).split()]
    if len(values) != n:
        raise InvalidValueError(f"expected {n} numbers in {what}")
    return values


def add_payload(
    urdf_xml: str, link: str, mass_kg: float, xyz_m: tuple[float, float, float], source: str
) -> str:
    """The URDF with a point mass added to one link's inertial (mass, CoG, parallel axes).

    The combined body keeps the link's inertia about its own centre of mass, moved to the new
    centre of mass by the parallel-axis theorem, plus the point mass's m (|d|^2 E - d d^T).
    A zero mass returns the URDF unchanged.

    Raises:
        ConfigError: `base.payload.*`: an unknown link, a negative mass, a rotated inertial.
    """
    if mass_kg == 0.0:
        return urdf_xml
    if not (math.isfinite(mass_kg) and mass_kg > 0.0):
        raise ConfigError(source, "base.payload.mass_kg", f"expected a mass >= 0, got {mass_kg!r}")
    root = ET.fromstring(urdf_xml)
    links = {el.get("name"): el for el in root.iter("link")}
    if link not in links:
        names = ", ".join(str(n) for n in links)
        raise ConfigError(source, "base.payload.link", f"expected one of {names}, got {link!r}")
    inertial = links[link].find("inertial")
    if inertial is None:
        raise ConfigError(source, "base.payload.link", f"{link} has no inertial to add to")
    origin = inertial.find("origin")
    if origin is None:
        origin = ET.SubElement(inertial, "origin")
    if any(_floats(origin.get("rpy"), 3, "rpy")):
        raise ConfigError(source, "base.payload.link", f"{link}'s inertial is rotated (rpy != 0)")
    mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
    if mass_el is None or inertia_el is None:
        raise ConfigError(source, "base.payload.link", f"{link}'s inertial lacks mass or inertia")
    m1 = float(mass_el.get("value", "0"))
    c1 = np.array(_floats(origin.get("xyz"), 3, "xyz"))
    ixx, ixy, ixz, iyy, iyz, izz = (
        float(inertia_el.get(k, "0")) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    )
    i1 = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    p = np.array(xyz_m, dtype=float)
    total = m1 + mass_kg
    c = (m1 * c1 + mass_kg * p) / total

    def shift(mass: float, d: np.ndarray) -> np.ndarray:
        return mass * (float(d @ d) * np.eye(3) - np.outer(d, d))

    inertia = i1 + shift(m1, c1 - c) + shift(mass_kg, p - c)
    mass_el.set("value", repr(total))
    origin.set("xyz", " ".join(repr(float(x)) for x in c))
    for (r, col), name in zip(
        ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
        ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"),
        strict=True,
    ):
        inertia_el.set(name, repr(float(inertia[r, col])))
    return ET.tostring(root, encoding="unicode")


def payload_of(base: Mapping[str, Any], source: str) -> tuple[str, float, tuple[float, ...]] | None:
    """The base block's payload as (link, mass_kg, xyz_m), or None.

    Raises:
        ConfigError: `base.payload.*`: a missing or wrong value.
    """
    raw = base.get("payload")
    if raw is None:
        return None
    payload = mapping_of(raw, source, "base.payload", "{link, mass_kg, xyz_m}")
    link = payload.get("link")
    if not isinstance(link, str):
        raise ConfigError(source, "base.payload.link", "expected a link name of the URDF")
    mass = finite_number(payload.get("mass_kg"), source, "base.payload.mass_kg")
    xyz = payload.get("xyz_m", [0.0, 0.0, 0.0])
    if not isinstance(xyz, list) or len(xyz) != 3:
        raise ConfigError(
            source, "base.payload.xyz_m", "expected 3 numbers (m, in the link's frame)"
        )
    return (
        link,
        mass,
        tuple(finite_number(x, source, f"base.payload.xyz_m[{i}]") for i, x in enumerate(xyz)),
    )
