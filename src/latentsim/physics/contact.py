"""Contact with analytic colliders: each vertex against each collider through the log barrier of
Incremental Potential Contact (Li et al. 2020, Eq. 6),

    b(d) = -kappa (d - d_hat)^2 ln(d / d_hat)   for 0 < d < d_hat,   0 for d >= d_hat,

with d the signed distance of the vertex from the collider's surface.  b, b' and b'' all vanish at
d = d_hat (b is C2 there, as IPC requires of its barrier), b grows without bound as d -> 0+, and
b' < 0 < b'' on (0, d_hat): the barrier only ever pushes a vertex away.

The colliders are static analytic shapes (:class:`HalfSpace`, :class:`Sphere`, :class:`Capsule`), each
with its signed distance, the distance's gradient and Hessian in closed form, and the time of impact
along a straight step (continuous collision detection against an analytic shape is a closed-form
root), which a line search uses to keep every iterate outside.

:class:`ContactBarrier` is an energy term of the contract of :mod:`latentsim.physics.base` (one vertex
per stencil), with its per-vertex gradient and PSD-projected Hessian in closed form; the autograd
oracle of the base class checks them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from latentsim.physics.base import EnergyTerm


def barrier(d: torch.Tensor, d_hat: float, kappa: float, extend_below: float | None = None) -> torch.Tensor:
    """b(d) elementwise; 0 for d >= d_hat; +inf for d <= 0 (inside or on the surface), or, with
    ``extend_below`` = d_e in (0, d_hat), below d_e its second-order Taylor expansion about d_e: finite
    and C2 everywhere, growing quadratically into the collider (what a learned loss needs: a decoded
    state that penetrates costs much, not infinity or NaN)."""
    inside = d < d_hat
    safe = torch.where(inside & (d > 0), d, torch.full_like(d, d_hat))
    b = -kappa * (safe - d_hat) ** 2 * torch.log(safe / d_hat)
    b = torch.where(inside, b, torch.zeros_like(d))
    if extend_below is None:
        return torch.where(d <= 0, torch.full_like(d, math.inf), b)
    de = torch.full_like(d, float(extend_below))
    b0 = barrier(de, d_hat, kappa)
    b1, b2 = barrier_derivatives(de, d_hat, kappa)
    return torch.where(d < de, b0 + b1 * (d - de) + 0.5 * b2 * (d - de) ** 2, b)


def barrier_derivatives(d: torch.Tensor, d_hat: float, kappa: float) -> tuple[torch.Tensor, torch.Tensor]:
    """b'(d) and b''(d) elementwise for d > 0 (0 for d >= d_hat)."""
    inside = (d < d_hat) & (d > 0)
    s = torch.where(inside, d, torch.full_like(d, d_hat))
    r = s - d_hat
    db = -kappa * (2 * r * torch.log(s / d_hat) + r**2 / s)
    d2b = -kappa * (2 * torch.log(s / d_hat) + 4 * r / s - r**2 / s**2)
    zero = torch.zeros_like(d)
    return torch.where(inside, db, zero), torch.where(inside, d2b, zero)


class Collider:
    """A static analytic shape: signed distance (positive outside), its gradient and Hessian, and
    the time of impact along a straight step."""

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


@dataclass(frozen=True)
class HalfSpace(Collider):
    """The half-space below the plane through ``point`` with unit outward ``normal``: d = n . (x - p)."""

    point: tuple
    normal: tuple

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


@dataclass(frozen=True)
class Capsule(Collider):
    """The points within ``radius`` of the segment from ``a`` to ``b``: d = dist(x, [a, b]) - r."""

    a: tuple
    b: tuple
    radius: float

    def __post_init__(self):
        if not float(self.radius) > 0:
            raise ValueError(f"capsule radius {self.radius!r}: give a positive number")
        if not np.linalg.norm(np.subtract(self.b, self.a)) > 0:
            raise ValueError(f"capsule from {self.a!r} to {self.b!r}: its ends must differ")
        object.__setattr__(self, "a", tuple(float(v) for v in self.a))
        object.__setattr__(self, "b", tuple(float(v) for v in self.b))

    def _closest(self, x):
        a, b = (torch.as_tensor(v, dtype=x.dtype, device=x.device) for v in (self.a, self.b))
        e = b - a
        s = (((x - a) * e).sum(-1) / (e * e).sum()).clamp(0.0, 1.0)
        return a + s[..., None] * e, s

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


class ContactBarrier(EnergyTerm):
    """Every vertex against every collider: sum_i sum_c b(d_c(x_i)) (one vertex per stencil).

    Parameters
    ----------
    n_vertices : n; colliders : the static shapes; d_hat : activation distance [m]; kappa : stiffness.
    """

    name = "contact_barrier"

    def __init__(self, n_vertices: int, colliders, d_hat: float, kappa: float, extend_below: float | None = None):
        if not (d_hat > 0 and kappa > 0):
            raise ValueError(f"contact barrier: d_hat {d_hat!r} and kappa {kappa!r} must be positive")
        if extend_below is not None and not 0 < extend_below < d_hat:
            raise ValueError(f"contact barrier: extend_below {extend_below!r} must lie in (0, d_hat = {d_hat})")
        self.colliders = list(colliders)
        self.d_hat, self.kappa, self.extend_below = float(d_hat), float(kappa), extend_below
        self.stencils = torch.arange(int(n_vertices)).reshape(-1, 1)

    def extended(self, fraction: float = 0.1, d_hat_factor: float = 1.0, kappa_factor: float = 1.0) -> "ContactBarrier":
        """The barrier of activation distance ``d_hat_factor`` d_hat and stiffness ``kappa_factor``
        kappa, continued below ``fraction`` of that distance by its quadratic Taylor expansion
        (:func:`barrier`'s ``extend_below``): finite inside the colliders, for learned losses."""
        d_hat = d_hat_factor * self.d_hat
        return ContactBarrier(len(self.stencils), self.colliders, d_hat, kappa_factor * self.kappa, fraction * d_hat)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        x = xe[..., 0, :]
        total = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
        for c in self.colliders:
            total = total + barrier(c.distance(x), self.d_hat, self.kappa, self.extend_below)
        return total

    def distances(self, x: torch.Tensor) -> torch.Tensor:
        """The signed distance of every vertex from its nearest collider, x (..., n, 3) -> (..., n)."""
        return torch.stack([c.distance(x) for c in self.colliders]).amin(0)

    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True, hessian: bool = True):
        """Per vertex: g = b'(d) grad d and H = b''(d) grad d grad d^T + b'(d) Hess d, summed over the
        colliders, H clamped to its non-negative eigenvalues when ``project``; H is None without
        ``hessian`` (a line search's trial needs the gradient alone)."""
        x = xe[:, 0, :]
        g = torch.zeros_like(x)
        H = torch.zeros(x.shape + (3,), dtype=x.dtype, device=x.device)
        for c in self.colliders:
            d = c.distance(x)
            db, d2b = barrier_derivatives(d, self.d_hat, self.kappa)
            n, hd = c.distance_derivatives(x)
            g = g + db[:, None] * n
            if hessian:
                H = H + d2b[:, None, None] * n[:, :, None] * n[:, None, :] + db[:, None, None] * hd
        if not hessian:
            return g, None
        if project:
            w, V = torch.linalg.eigh(H)
            H = (V * w.clamp_min(0.0)[:, None, :]) @ V.transpose(1, 2)
        return g, H

    def first_impact(self, x: np.ndarray, dx: np.ndarray) -> float:
        """The first time t >= 0 at which a vertex of x + t dx (x, dx (n, 3)) reaches a collider; inf if none does."""
        x, dx = np.asarray(x, dtype=float).reshape(-1, 3), np.asarray(dx, dtype=float).reshape(-1, 3)
        return min((float(np.min(c.time_of_impact(x, dx), initial=np.inf)) for c in self.colliders), default=np.inf)

    def max_step(self, x: np.ndarray, dx: np.ndarray, safety: float = 0.9) -> float:
        """The largest step fraction alpha in (0, 1] that keeps every vertex outside every collider
        along x + t dx, t in [0, alpha]: ``safety`` times the first time of impact (as IPC's line
        search does), 1 when no vertex comes that close within the whole step."""
        return min(1.0, safety * self.first_impact(x, dx))
