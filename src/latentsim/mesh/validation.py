"""MeshError and the checks of the arrays and numbers every mesh function takes.

All mesh functions validate their arguments through these few functions, so a bad
argument always raises :class:`MeshError` with a message that names the
argument (or file, or mesh) and the offending value or index.  The ``what``
argument of each of them is that name, e.g. ``"armadillo.vtu: tet"``.
"""

from __future__ import annotations

import math

import numpy as np

_AXES = {"x": 0, "y": 1, "z": 2}


class MeshError(ValueError):
    """Any problem with a mesh: missing or corrupt file, bad hash, bad topology or quality."""


def positive_int(value, what: str, minimum: int = 1) -> int:
    """``value`` as an int, which must be an integer (not a bool) ``>= minimum``."""
    if isinstance(value, bool) or int(value) != value or int(value) < minimum:
        raise MeshError(f"{what} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def finite_float(value, what: str, *, positive: bool = False) -> float:
    """``value`` as a finite float (``positive``: also ``> 0``)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{what} must be a number, got {value!r}") from exc
    if not math.isfinite(v) or (positive and not v > 0):
        kind = "a positive finite" if positive else "a finite"
        raise MeshError(f"{what} must be {kind} number, got {value!r}")
    return v


def vector3(value, what: str) -> np.ndarray:
    """``value`` as a (3,) float64 array of finite numbers."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{what} must be 3 numbers, got {value!r}") from exc
    if arr.size != 3 or not np.isfinite(arr).all():
        raise MeshError(f"{what} must be 3 finite numbers, got {value!r}")
    return arr.reshape(3)


def unit_vector(value, what: str) -> np.ndarray:
    """``value / |value|`` as a (3,) float64 array; ``value`` must be a non-zero 3-vector."""
    v = vector3(value, what)
    norm = np.linalg.norm(v)
    if not norm > 0:
        raise MeshError(f"{what} must be a non-zero vector, got {value!r}")
    return v / norm


def axis_index(axis, what: str = "axis") -> int:
    """0, 1, 2 for ``"x"``, ``"y"``, ``"z"`` (a leading ``+`` allowed) or for the ints 0..2."""
    if isinstance(axis, str) and axis.lower().lstrip("+") in _AXES:
        return _AXES[axis.lower().lstrip("+")]
    if not isinstance(axis, bool) and isinstance(axis, (int, np.integer)) and 0 <= axis < 3:
        return int(axis)
    raise MeshError(f"{what} must be 'x', 'y', 'z' or 0..2, got {axis!r}")


def as_vertices(vertices, what: str = "vertices") -> np.ndarray:
    """``vertices`` as an (n, 3) float64 array (no copy when it already is one)."""
    arr = np.asarray(vertices, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MeshError(f"{what} must have shape (n, 3), got {arr.shape}")
    return arr


def nonfinite_problem(vertices: np.ndarray, what: str) -> str | None:
    """The message naming the first vertex with a NaN/inf coordinate, or None if there is none."""
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if not bad.size:
        return None
    i = int(bad[0])
    return (f"{what}: {bad.size} vertices with NaN/inf coordinates, first is vertex {i} "
            f"{vertices[i].tolist()}")


def require_finite(vertices: np.ndarray, what: str) -> None:
    """Raise :class:`MeshError` (see :func:`nonfinite_problem`) if a coordinate is NaN/inf."""
    problem = nonfinite_problem(vertices, what)
    if problem:
        raise MeshError(problem)


def out_of_range(cells: np.ndarray, n_vertices: int, what: str) -> tuple[np.ndarray, str | None]:
    """Rows of ``cells`` (e, k) with an index outside ``0 .. n_vertices - 1``.

    Returns
    -------
    bad : (b,) int64, the offending rows.
    problem : str or None, the message naming the first of them.
    """
    bad = np.flatnonzero(((cells < 0) | (cells >= n_vertices)).any(axis=1))
    if not bad.size:
        return bad, None
    i = int(bad[0])
    return bad, (f"{what} {i} has vertex index out of range {cells[i].tolist()} "
                 f"({n_vertices} vertices)")


def as_cells(cells, k: int, what: str, n_vertices: int | None = None) -> np.ndarray:
    """``cells`` as an (e, k) int64 array, its indices checked against ``n_vertices`` if given."""
    arr = np.asarray(cells)
    if arr.ndim != 2 or arr.shape[1] != k:
        raise MeshError(f"{what} must have shape (n, {k}), got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise MeshError(f"{what} must be an integer array, got dtype {arr.dtype}")
    arr = arr.astype(np.int64, copy=False)
    if n_vertices is not None and arr.size:
        _, problem = out_of_range(arr, n_vertices, what)
        if problem:
            raise MeshError(problem)
    return arr
