"""Vertex selection rules given as config data: the Dirichlet (prescribed) set of a scene.

A rule is a mapping with a ``type`` and that type's keys (all required, no
others, so config typos fail): ``extreme`` (a fraction of the extent along an
axis), ``sphere``, ``box``, ``indices``; and, for rod scenes, ``roots`` (each
rod's root, clamped: also its second vertex).  Every error quotes the rule.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from latentsim.mesh.validation import (
    MeshError,
    as_vertices,
    axis_index,
    finite_float,
    vector3,
)

#: The keys each rule type reads, besides ``type``.
RULE_KEYS: dict[str, tuple[str, ...]] = {
    "extreme": ("axis", "side", "fraction"),
    "sphere": ("center", "radius"),
    "box": ("min", "max"),
    "indices": ("indices",),
}


def _extreme(v: np.ndarray, rule: dict, what: str) -> np.ndarray:
    """Within ``fraction * extent`` of the max (``side: max``) or min along ``axis``, boundary included."""
    ax = axis_index(rule["axis"], f"{what}: axis")
    side = rule["side"]
    if side not in ("max", "min"):
        raise MeshError(f"{what}: side must be 'max' or 'min'")
    frac = finite_float(rule["fraction"], f"{what}: 'fraction'")
    if not (0.0 <= frac <= 1.0):
        raise MeshError(f"{what}: fraction must be in [0, 1]")
    coord = v[:, ax]
    lo, hi = coord.min(), coord.max()
    if side == "max":
        return coord >= hi - frac * (hi - lo)
    return coord <= lo + frac * (hi - lo)


def _sphere(v: np.ndarray, rule: dict, what: str) -> np.ndarray:
    """``|x - center| <= radius``."""
    c = vector3(rule["center"], f"{what}: 'center'")
    r = finite_float(rule["radius"], f"{what}: 'radius'")
    if r < 0:
        raise MeshError(f"{what}: radius must be >= 0")
    return np.einsum("ij,ij->i", v - c, v - c) <= r * r


def _box(v: np.ndarray, rule: dict, what: str) -> np.ndarray:
    """Inside the closed box ``min <= x <= max``."""
    lo, hi = vector3(rule["min"], f"{what}: 'min'"), vector3(rule["max"], f"{what}: 'max'")
    if (lo > hi).any():
        raise MeshError(f"{what}: min > max")
    return ((v >= lo) & (v <= hi)).all(axis=1)


def _indices(v: np.ndarray, rule: dict, what: str) -> np.ndarray:
    """The listed vertex indices."""
    raw = np.asarray(rule["indices"])
    if raw.ndim != 1 or (raw.size and not np.issubdtype(raw.dtype, np.integer)):
        raise MeshError(f"{what}: indices must be a list of integers")
    idx = raw.astype(np.int64)
    bad = idx[(idx < 0) | (idx >= len(v))]
    if bad.size:
        raise MeshError(f"{what}: index {int(bad[0])} out of range ({len(v)} vertices)")
    mask = np.zeros(len(v), dtype=bool)
    mask[idx] = True
    return mask


_MASKS: dict[str, Callable[[np.ndarray, dict, str], np.ndarray]] = {
    "extreme": _extreme, "sphere": _sphere, "box": _box, "indices": _indices,
}


def _checked_rule(rule: Any) -> tuple[str, dict]:
    """The rule's type and the rule as a dict, its keys checked against :data:`RULE_KEYS`."""
    if not isinstance(rule, Mapping) or "type" not in rule:
        raise MeshError(f"selection rule must be a mapping with a 'type', got {rule!r}")
    rule_d = dict(rule)
    kind = rule_d["type"]
    if kind == "roots":
        raise MeshError(
            f"selection rule {rule_d!r}: 'roots' is resolved by the rod scene from "
            "rod_bundle's roots, not by select_vertices")
    if kind not in RULE_KEYS:
        raise MeshError(f"selection rule {rule_d!r}: unknown type {kind!r} "
                        f"(known: {', '.join(sorted(RULE_KEYS))})")
    required = {"type", *RULE_KEYS[kind]}
    missing = required - set(rule_d)
    extra = set(rule_d) - required
    if missing or extra:
        raise MeshError(f"selection rule {rule_d!r}: "
                        + (f"missing keys {sorted(missing)} " if missing else "")
                        + (f"unknown keys {sorted(extra)}" if extra else ""))
    return kind, rule_d


def select_vertices(vertices: np.ndarray, rule: Mapping[str, Any]) -> np.ndarray:
    """Indices of the vertices matched by a selection rule given as config data.

    Rules (all keys required, no others allowed, so config typos fail):

    * ``{"type": "extreme", "axis": "y", "side": "max", "fraction": 0.05}``:
      vertices whose coordinate along ``axis`` is within ``fraction * extent``
      of the maximum (``side: "min"``: of the minimum), boundary included,
      with ``0 <= fraction <= 1`` (0 picks the extreme vertices only).
    * ``{"type": "sphere", "center": [x, y, z], "radius": r}``: ``|x - c| <= r``.
    * ``{"type": "box", "min": [..], "max": [..]}``: inside the closed box.
    * ``{"type": "indices", "indices": [...]}``: explicit indices.

    (``{"type": "roots"}`` belongs to rod scenes, see :func:`select_dirichlet`,
    and is rejected here.)

    Parameters
    ----------
    vertices : (n, 3)
    rule : mapping

    Returns
    -------
    indices : (k,) int64, sorted, unique, k >= 1.

    Raises
    ------
    MeshError
        Unknown type, missing/unknown keys, bad values, or an empty selection;
        the message quotes the rule.
    """
    v = as_vertices(vertices)
    kind, rule_d = _checked_rule(rule)
    mask = _MASKS[kind](v, rule_d, f"selection rule {rule_d!r}")
    out = np.flatnonzero(mask).astype(np.int64)
    if out.size == 0:
        lo_b, hi_b = (v.min(axis=0).round(6).tolist(), v.max(axis=0).round(6).tolist()) \
            if len(v) else (None, None)
        raise MeshError(f"selection rule {rule_d!r} selects no vertex "
                        f"(mesh bounding box {lo_b} .. {hi_b})")
    return out


def select_dirichlet(rest_positions: np.ndarray, rule: Mapping[str, Any],
                     root_of: np.ndarray | None = None) -> np.ndarray:
    """Indices (k,) int64 of a scene's Dirichlet vertices.

    Rule ``{"type": "free"}`` selects none (a free body).  Rule ``{"type": "roots"}`` selects each rod's root and, with ``clamp``
    (the default), also the next vertex, so the root edge's direction is held:
    a clamped rod (hair in its follicle) rather than a pinned pendulum.  Other
    rules go to :func:`select_vertices` with only their own keys (the config
    schema fills every rule key with a default).

    Parameters
    ----------
    rest_positions : (n, 3)
    rule : mapping, a scene's ``dirichlet`` config.
    root_of : (n,) int, the root vertex of each vertex (rod scenes only).
    """
    if rule["type"] == "free":
        return np.zeros(0, dtype=np.int64)
    if rule["type"] == "roots":
        if root_of is None:
            raise MeshError("dirichlet rule 'roots' needs a rod scene")
        roots = np.unique(root_of).astype(np.int64)
        if rule.get("clamp", True):
            roots = np.union1d(roots, roots + 1)
        return roots
    keys = ("type",) + RULE_KEYS.get(rule["type"], ())
    return select_vertices(rest_positions, {k: rule[k] for k in keys if k in rule})
