"""IPC's log barrier (Li et al. 2020, Eq. 6) of a distance d from a collider's surface,

    b(d) = -kappa (d - d_hat)^2 ln(d / d_hat)   for 0 < d < d_hat,   0 for d >= d_hat,

and its first two derivatives, elementwise: what every contact term (:mod:`latentsim.physics.contact`,
:mod:`latentsim.physics.mesh_contact`) sums over its pairs.
"""

from __future__ import annotations

import math

import torch

__all__ = ["barrier", "barrier_derivatives"]


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


def barrier_derivatives(d: torch.Tensor, d_hat: float, kappa: float, extend_below: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """b'(d) and b''(d) elementwise for d > 0 (0 for d >= d_hat); with ``extend_below`` = d_e, those of
    :func:`barrier`'s quadratic continuation below d_e (b'(d_e) + b''(d_e) (d - d_e) and b''(d_e)), for every d."""
    inside = (d < d_hat) & (d > 0)
    s = torch.where(inside, d, torch.full_like(d, d_hat))
    r = s - d_hat
    db = -kappa * (2 * r * torch.log(s / d_hat) + r**2 / s)
    d2b = -kappa * (2 * torch.log(s / d_hat) + 4 * r / s - r**2 / s**2)
    zero = torch.zeros_like(d)
    db, d2b = torch.where(inside, db, zero), torch.where(inside, d2b, zero)
    if extend_below is None:
        return db, d2b
    e1, e2 = barrier_derivatives(torch.full_like(d, float(extend_below)), d_hat, kappa)
    below = d < extend_below
    return torch.where(below, e1 + e2 * (d - extend_below), db), torch.where(below, e2, d2b)
