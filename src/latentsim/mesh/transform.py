"""Rigid and scaling transforms of vertex arrays: rotations, normalisation, placement.

Rotations follow Rodrigues' formula ``R = cos t I + sin t [k]x + (1 - cos t) k k^T``
for a unit axis ``k`` and angle ``t`` (right-handed, rotating column vectors).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from latentsim.mesh.validation import (
    MeshError,
    as_vertices,
    axis_index,
    finite_float,
    require_finite,
    unit_vector,
)


def rotation_matrix(axis: str | Sequence[float], degrees: float) -> np.ndarray:
    """Right-handed rotation by ``degrees`` about ``axis`` (Rodrigues).

    Parameters
    ----------
    axis : "x" | "y" | "z" or (3,) vector (normalised internally)
    degrees : float

    Returns
    -------
    R : (3, 3) float64, rotating column vectors: ``x_new = R @ x``.
        Multiples of 90 degrees are exact (entries 0, +-1).
    """
    if isinstance(axis, str):
        k = np.zeros(3)
        k[axis_index(axis)] = 1.0
    else:
        k = unit_vector(axis, "rotation axis")
    deg = float(degrees)
    quarter = deg / 90.0
    if quarter == round(quarter):
        c, s = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][int(round(quarter)) % 4]
    else:
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return c * np.eye(3) + s * K + (1.0 - c) * np.outer(k, k)


def _rotation_of(rotation: Any) -> np.ndarray:
    """The (3, 3) matrix of a rotation given as a matrix, ``{"axis", "degrees"}`` or ``(axis, degrees)``."""
    if isinstance(rotation, Mapping):
        unknown = set(rotation) - {"axis", "degrees"}
        if unknown or not {"axis", "degrees"} <= set(rotation):
            raise MeshError(f"rotation must be {{'axis': .., 'degrees': ..}}, got {rotation!r}")
        return rotation_matrix(rotation["axis"], rotation["degrees"])
    if isinstance(rotation, (tuple, list)) and len(rotation) == 2:
        return rotation_matrix(rotation[0], rotation[1])
    R = np.asarray(rotation, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9) \
            or np.linalg.det(R) <= 0:
        raise MeshError("rotation matrix must be a proper 3x3 rotation")
    return R


def normalise(
    vertices: np.ndarray,
    *,
    rotation: Any = None,
    height: float | None = None,
    scale: float | None = None,
    axis: str = "y",
    center: str | None = "bbox",
    ground: bool = False,
) -> np.ndarray:
    """Rotate, scale and centre a vertex array (returns a new array).

    Steps, in order: rotate about the bounding-box centre; scale uniformly
    (``height``: make the extent along ``axis`` equal to it, or a plain
    ``scale`` factor); translate so the bounding-box centre (``"bbox"``) or the
    vertex mean (``"centroid"``) is at the origin (``None``: keep); finally,
    with ``ground=True``, shift along ``axis`` so the minimum is 0 (object
    standing on the ground plane).

    Parameters
    ----------
    vertices : (n, 3)
    rotation : None, (3, 3) matrix, ``{"axis": "x", "degrees": 180}`` or
        ``("x", 180)``.  E.g. upside down: ``{"axis": "x", "degrees": 180}``.
    height : float > 0, optional
    scale : float > 0, optional (not together with ``height``)
    axis : "x" | "y" | "z", the height / ground axis.
    center : "bbox" | "centroid" | None
    ground : bool

    Returns
    -------
    (n, 3) float64
    """
    v = as_vertices(vertices).copy()
    if len(v) == 0:
        raise MeshError("normalise: no vertices")
    require_finite(v, "normalise")
    ax = axis_index(axis)
    if rotation is not None:
        R = _rotation_of(rotation)
        c = 0.5 * (v.min(axis=0) + v.max(axis=0))
        v = (v - c) @ R.T + c
    if height is not None and scale is not None:
        raise MeshError("normalise: give height or scale, not both")
    if height is not None:
        h = finite_float(height, "height", positive=True)
        extent = v[:, ax].max() - v[:, ax].min()
        if extent <= 0:
            raise MeshError("normalise: zero extent along the height axis")
        v *= h / extent
    elif scale is not None:
        v *= finite_float(scale, "scale", positive=True)
    if center == "bbox":
        v -= 0.5 * (v.min(axis=0) + v.max(axis=0))
    elif center == "centroid":
        v -= v.mean(axis=0)
    elif center is not None:
        raise MeshError(f"center must be 'bbox', 'centroid' or None, got {center!r}")
    if ground:
        v[:, ax] -= v[:, ax].min()
    return v


def place(
    vertices: np.ndarray,
    scale: float = 1.0,
    rotate_axis: Sequence[float] | None = None,
    rotate_degrees: float = 0.0,
    translate: Sequence[float] | None = None,
) -> np.ndarray:
    """Scale about the origin, then rotate about the origin, then translate (a new array).

    Parameters
    ----------
    vertices : (n, 3)
    scale : float, uniform factor (1: none).
    rotate_axis : (3,) vector, needed when ``rotate_degrees`` is not 0.
    rotate_degrees : float, right-handed about ``rotate_axis`` (:func:`rotation_matrix`).
    translate : (3,) vector, optional.

    Returns
    -------
    (n, 3) float64
    """
    V = np.asarray(vertices, dtype=np.float64)
    if scale != 1.0:
        V = V * float(scale)
    if rotate_degrees:
        V = V @ rotation_matrix(rotate_axis, rotate_degrees).T
    if translate:
        V = V + np.asarray(translate, dtype=float)
    return V
