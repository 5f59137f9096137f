"""The analytic colliders of contact (:mod:`latentsim.physics.contact`): :class:`HalfSpace`, :class:`Sphere` and
:class:`Capsule`, each with its signed distance, the distance's gradient and Hessian in closed form, the distance of a
surface's edges and triangles (:meth:`Collider.primitive_distance`) and the time of impact along a straight step
(continuous collision detection against an analytic shape is a closed-form root).  A collider is static, or *attached*
to the prescribed (Dirichlet) vertices: its pose at a frame is the rigid motion that carries their rest positions onto
their targets (:func:`rigid_pose`, :func:`posed_colliders`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from latentsim.physics.barrier import barrier
from latentsim.physics.primitives import closest_on_segment, core_distance, plane_distance


def primitive_barriers(x: torch.Tensor, edges, triangles, collider: "Collider", d_hat: float, kappa: float,
                       extend_below: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Per-primitive barrier energies of a surface against one collider: b(d_e) for each edge and b(d_t) for each
    triangle (:func:`barrier` of :meth:`Collider.primitive_distance`), x (..., n, 3), edges (E, 2) and triangles
    (T, 3) vertex indices -> ((..., E), (..., T)).  Against a :class:`HalfSpace` each is its nearest vertex's."""
    out = []
    for idx in (edges, triangles):
        idx = torch.as_tensor(np.asarray(idx), dtype=torch.int64, device=x.device)
        out.append(barrier(collider.primitive_distance(x[..., idx, :]), d_hat, kappa, extend_below))
    return out[0], out[1]


def rigid_pose(rest: np.ndarray, targets) -> tuple[torch.Tensor, torch.Tensor]:
    """The rigid motion x -> R (x - c_0) + c that best carries ``rest`` (m, 3) onto ``targets`` (..., m, 3)
    in least squares (Kabsch: c_0 and c the centroids, R from the SVD of the cross-covariance, a proper
    rotation), exact when the targets are a rigid motion of the rest positions, as a boundary-condition
    program's are.  Returns R (..., 3, 3) and c (..., 3) in the targets' dtype (float64 for numpy input)."""
    targets = torch.as_tensor(targets)
    if not targets.is_floating_point():
        targets = targets.to(torch.float64)
    rest = torch.as_tensor(np.asarray(rest, dtype=float), dtype=targets.dtype, device=targets.device)
    c0, c = rest.mean(0), targets.mean(-2)
    cov = (rest - c0).transpose(0, 1) @ (targets - c[..., None, :])  # (..., 3, 3): sum_i p_i q_i^T
    U, _, Vh = torch.linalg.svd(cov)
    V = Vh.transpose(-1, -2)
    sign = torch.sign(torch.linalg.det(V @ U.transpose(-1, -2)))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    D = torch.ones(sign.shape + (3,), dtype=targets.dtype, device=targets.device)
    D[..., 2] = sign
    return (V * D[..., None, :]) @ U.transpose(-1, -2), c


def posed_colliders(colliders, attached, rest_dirichlet, targets) -> list:
    """The colliders where they stand when the prescribed vertices (rest positions ``rest_dirichlet``
    (m, 3)) are at ``targets`` (m, 3): each ``attached`` one carried by their rigid motion
    (:func:`rigid_pose`), the static ones as they are."""
    if not any(attached):
        return list(colliders)
    rest = np.asarray(rest_dirichlet, dtype=float)
    R, c = rigid_pose(rest, np.asarray(targets, dtype=float))
    R, c0, c = R.numpy(), rest.mean(0), c.numpy()
    return [col.moved(R, c0, c) if a else col for col, a in zip(colliders, attached)]


class Collider:
    """An analytic shape: signed distance (positive outside), its gradient and Hessian, the time of
    impact along a straight step, and the shape carried by a rigid motion (:meth:`moved`)."""

    #: the fields that are points (carried by the whole motion) and directions (turned only)
    points: tuple = ()
    directions: tuple = ()

    def moved(self, R, c0, c) -> "Collider":
        """The shape carried by the rigid motion x -> R (x - c0) + c (R (3, 3), c0 and c (3,))."""
        R, c0, c = (np.asarray(v, dtype=float) for v in (R, c0, c))
        new = {k: tuple(R @ (np.asarray(getattr(self, k)) - c0) + c) for k in self.points}
        new.update({k: tuple(R @ np.asarray(getattr(self, k))) for k in self.directions})
        return dataclasses.replace(self, **new)

    def distance(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """x (..., 3) -> signed distance (...)."""
        raise NotImplementedError

    def distance_derivatives(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # pragma: no cover - abstract
        """x (..., 3) -> gradient (..., 3) and Hessian (..., 3, 3) of the signed distance."""
        raise NotImplementedError

    def time_of_impact(self, x: np.ndarray, dx: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """The first t >= 0 at which x + t dx reaches the surface, per vertex (x, dx (n, 3), points
        outside); inf where the straight line never does, 0 for a point on or inside the surface."""
        raise NotImplementedError

    def primitive_distance(self, xp: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """xp (..., k, 3), vertices (k = 1), edges (k = 2) or triangles (k = 3) -> the signed distance of each
        one's closest point from the surface (...) (:mod:`latentsim.physics.primitives`)."""
        raise NotImplementedError

    def thickened(self, offset: float) -> "Collider":
        """The shape grown by ``offset`` >= 0 along its outward normal (each signed distance less by ``offset``):
        a collider as a surface of that half-thickness sees it (a shell's half thickness, a strand's radius)."""
        if not offset > 0:
            return self
        if isinstance(self, HalfSpace):
            return dataclasses.replace(self, point=tuple(np.asarray(self.point) + float(offset) * np.asarray(self.normal)))
        return dataclasses.replace(self, radius=float(self.radius) + float(offset))

    @property
    def curved(self) -> bool:
        """Whether a surface's edge or triangle can come nearer than its vertices (not against a plane)."""
        return not isinstance(self, HalfSpace)


@dataclass(frozen=True)
class HalfSpace(Collider):
    """The half-space below the plane through ``point`` with unit outward ``normal``: d = n . (x - p)."""

    point: tuple
    normal: tuple
    points = ("point",)
    directions = ("normal",)

    def __post_init__(self):
        n = np.asarray(self.normal, dtype=float)
        if n.shape != (3,) or not np.linalg.norm(n) > 0:
            raise ValueError(f"half-space normal {self.normal!r}: give a non-zero 3-vector")
        object.__setattr__(self, "normal", tuple(n / np.linalg.norm(n)))
        object.__setattr__(self, "point", tuple(float(v) for v in self.point))

    def distance(self, x):
        n, p = (torch.as_tensor(v, dtype=x.dtype, device=x.device) for v in (self.normal, self.point))
        return ((x - p) * n).sum(-1)

    def distance_derivatives(self, x):
        n = torch.as_tensor(self.normal, dtype=x.dtype, device=x.device)
        return n.expand(x.shape), torch.zeros(x.shape + (3,), dtype=x.dtype, device=x.device)

    def time_of_impact(self, x, dx):
        n, p = np.asarray(self.normal), np.asarray(self.point)
        d, rate = (x - p) @ n, dx @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(rate < 0, d / -rate, np.inf)
        return t

    def primitive_distance(self, xp):
        """The least vertex's distance (:func:`~latentsim.physics.primitives.plane_distance`): against a plane an
        edge or triangle is no nearer than its nearest vertex."""
        n, p = (torch.as_tensor(v, dtype=xp.dtype, device=xp.device) for v in (self.normal, self.point))
        return plane_distance(xp, p, n)


def _sphere_toi(rel: np.ndarray, dx: np.ndarray, r: float) -> np.ndarray:
    """The first t >= 0 with |rel + t dx| = r for points outside (|rel| >= r), per row; inf if none."""
    a = (dx * dx).sum(-1)
    b = 2 * (rel * dx).sum(-1)
    c = (rel * rel).sum(-1) - r * r
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.sqrt(np.maximum(disc, 0.0))
        t = np.where((disc >= 0) & (b < 0) & (a > 0), (2 * c) / (-b + q), np.inf)  # the smaller root, stably
    return np.where(c <= 0, 0.0, t)


@dataclass(frozen=True)
class Sphere(Collider):
    """A ball of ``radius`` about ``centre``: d = |x - c| - r."""

    centre: tuple
    radius: float
    points = ("centre",)

    def __post_init__(self):
        if not float(self.radius) > 0:
            raise ValueError(f"sphere radius {self.radius!r}: give a positive number")
        object.__setattr__(self, "centre", tuple(float(v) for v in self.centre))

    def distance(self, x):
        c = torch.as_tensor(self.centre, dtype=x.dtype, device=x.device)
        return torch.linalg.vector_norm(x - c, dim=-1) - float(self.radius)

    def distance_derivatives(self, x):
        c = torch.as_tensor(self.centre, dtype=x.dtype, device=x.device)
        rel = x - c
        rho = torch.linalg.vector_norm(rel, dim=-1, keepdim=True)
        n = rel / rho
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        return n, (eye - n[..., :, None] * n[..., None, :]) / rho[..., None]

    def time_of_impact(self, x, dx):
        return _sphere_toi(x - np.asarray(self.centre), dx, float(self.radius))

    def primitive_distance(self, xp):
        """d = dist(c, primitive) - r (:func:`~latentsim.physics.primitives.core_distance`, the core the centre)."""
        c = torch.as_tensor(self.centre, dtype=xp.dtype, device=xp.device)
        return core_distance(c[None, :], xp) - float(self.radius)


@dataclass(frozen=True)
class Capsule(Collider):
    """The points within ``radius`` of the segment from ``a`` to ``b``: d = dist(x, [a, b]) - r."""

    a: tuple
    b: tuple
    radius: float
    points = ("a", "b")

    def __post_init__(self):
        if not float(self.radius) > 0:
            raise ValueError(f"capsule radius {self.radius!r}: give a positive number")
        if not np.linalg.norm(np.subtract(self.b, self.a)) > 0:
            raise ValueError(f"capsule from {self.a!r} to {self.b!r}: its ends must differ")
        object.__setattr__(self, "a", tuple(float(v) for v in self.a))
        object.__setattr__(self, "b", tuple(float(v) for v in self.b))

    def _closest(self, x):
        a, b = (torch.as_tensor(v, dtype=x.dtype, device=x.device) for v in (self.a, self.b))
        return closest_on_segment(x, a, b)

    def distance(self, x):
        q, _ = self._closest(x)
        return torch.linalg.vector_norm(x - q, dim=-1) - float(self.radius)

    def distance_derivatives(self, x):
        q, s = self._closest(x)
        rel = x - q
        rho = torch.linalg.vector_norm(rel, dim=-1, keepdim=True)
        n = rel / rho
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        H = (eye - n[..., :, None] * n[..., None, :]) / rho[..., None]
        # along the segment's inside the distance does not change with the axial coordinate
        e = torch.as_tensor(np.subtract(self.b, self.a) / np.linalg.norm(np.subtract(self.b, self.a)), dtype=x.dtype, device=x.device)
        axial = ((s > 0) & (s < 1)).to(x.dtype)[..., None, None]
        H = H - axial * (e[:, None] * e[None, :]) / rho[..., None]
        return n, H

    def time_of_impact(self, x, dx):
        a, b, r = np.asarray(self.a), np.asarray(self.b), float(self.radius)
        e = (b - a) / np.linalg.norm(b - a)
        length = np.linalg.norm(b - a)
        # the two end caps (balls), then the side (an infinite cylinder, its hits kept where they fall on the segment)
        t = np.minimum(_sphere_toi(x - a, dx, r), _sphere_toi(x - b, dx, r))
        rel, d_perp = x - a, dx - np.outer(dx @ e, e)
        rel_perp = rel - np.outer(rel @ e, e)
        side = _sphere_toi(rel_perp, d_perp, r)
        along = (rel @ e) + np.where(np.isfinite(side), side, 0.0) * (dx @ e)
        return np.minimum(t, np.where(np.isfinite(side) & (along >= 0) & (along <= length), side, np.inf))

    def primitive_distance(self, xp):
        """d = dist([a, b], primitive) - r (:func:`~latentsim.physics.primitives.core_distance`, the core the axis)."""
        axis = torch.as_tensor((self.a, self.b), dtype=xp.dtype, device=xp.device)
        return core_distance(axis, xp) - float(self.radius)
