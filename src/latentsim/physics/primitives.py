"""Closest-point distances of a surface's edges and triangles from the analytic colliders, batched and
differentiable (PyTorch, float64), and a conservative time of impact along a straight motion.

A vertex-only contact misses a curved collider pressed into the inside of an edge or a triangle: no
vertex is near the ball, the surface between them is in it.  Each collider of
:mod:`latentsim.physics.contact` has a *core* - the sphere its centre (a point), the capsule its axis (a
segment) - and the signed distance of a primitive from the collider's surface is its distance from the
core minus the radius.  This module gives those distances for every pair of a core and a primitive,
:func:`core_distance`, made of

    ==========  ==========================  ==========================
    primitive   point (sphere's centre)     segment (capsule's axis)
    ==========  ==========================  ==========================
    vertex      |p - x|                     point_segment_distance
    edge        point_segment_distance      segment_segment_distance
    triangle    point_triangle_distance     segment_triangle_distance
    ==========  ==========================  ==========================

and :func:`plane_distance` for a half-space.  A signed distance from a plane is affine in the point, so its
minimum over a segment or a triangle (the convex hull of the vertices) is attained at a vertex: an edge or a
triangle against a half-space reduces to its vertices, which a vertex barrier already holds (a barrier of
the edges and triangles against a half-space would count those contacts twice).

Method.  Each distance is the minimum over candidate features, as in Ericson (Real-Time Collision
Detection, 2005, ch. 5) and IPC's distance types (Li et al. 2020): point-segment by the clamped projection;
point-triangle the plane distance where the point projects inside the triangle, else the nearest edge;
segment-segment the two lines' closest points where both fall inside the segments, else the nearest
endpoint-to-segment; segment-triangle zero where the segment pierces the triangle, else the nearest of its
endpoints against the triangle and of the triangle's edges against it (for disjoint convex sets a closest
pair lies on a boundary feature).  The interior candidate's value is measured between its closest points,
where the distance is stationary, so an error in the closest points' parameters enters only to second order.

Smoothness.  Inside each region a distance is smooth, and across a region boundary the candidates meet with
equal value and gradient: a distance is C1 (the gradient of its closest points' difference, autograd's
through the candidate that wins) wherever the closest pair is unique and the distance positive.  It is not
differentiable (a) at distance 0 (the core touches the primitive: deep inside the collider, where the barrier
is infinite), (b) for parallel segments, or a segment parallel to a triangle's face, whose closest pairs form
a line and the distance only C0 across parallelism, (c) for degenerate primitives (a zero-length edge is its
point; a triangle of zero area is its edges).  Edges within sin^2 = PARALLEL of parallel take the endpoint
candidates (an error below l^2 PARALLEL / (2 d) for edges of length l at distance d), as do triangles of
relative area below that.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

__all__ = ["closest_on_segment", "point_segment_distance", "point_triangle_distance", "segment_segment_distance",
           "segment_triangle_distance", "core_distance", "plane_distance", "primitive_toi", "distance_hessian", "vertex_hessian"]  # fmt: skip

#: squared sine below which two edges count as parallel, and a triangle's |n|^2 / (|e1|^2 |e2|^2) as zero area
PARALLEL = 1e-12


def _dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """u . v over the last axis, (..., 3) -> (...)."""
    return (u * v).sum(-1)


def _norm(v: torch.Tensor) -> torch.Tensor:
    """|v| over the last axis, (..., 3) -> (...)."""
    return torch.linalg.vector_norm(v, dim=-1)


def _safe(den: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """den where ok, 1 elsewhere: a denominator whose unused branch stays finite (and so do its gradients)."""
    return torch.where(ok, den, torch.ones_like(den))


def closest_on_segment(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The point of the segment [a, b] closest to p: q = a + s (b - a), s = clamp((p - a).e / e.e, 0, 1),
    e = b - a; s = 0 (q = a) for a zero-length segment.

    Parameters
    ----------
    p, a, b : (..., 3), broadcast together.

    Returns
    -------
    q : (..., 3) the closest point; s : (...) its parameter in [0, 1].
    """
    e = b - a
    ee = (e * e).sum(-1)
    ok = ee > 0
    s = torch.where(ok, ((p - a) * e).sum(-1) / _safe(ee, ok), torch.zeros_like(ee)).clamp(0.0, 1.0)
    return a + s[..., None] * e, s


def point_segment_distance(p: torch.Tensor, seg: torch.Tensor) -> torch.Tensor:
    """d = |p - q|, q the point of the segment closest to p (:func:`closest_on_segment`).

    p (..., 3), seg (..., 2, 3) -> (...).
    """
    q, _ = closest_on_segment(p, seg[..., 0, :], seg[..., 1, :])
    return _norm(p - q)


def _inside_triangle(p: torch.Tensor, t0, t1, t2, n: torch.Tensor) -> torch.Tensor:
    """Whether p's projection on the triangle's plane lies in the triangle (closed): ((t_j - t_i) x (p - t_i)) . n >= 0
    for its three edges, n = (t1 - t0) x (t2 - t0)."""
    cross = torch.linalg.cross
    return ((_dot(cross(t1 - t0, p - t0), n) >= 0) & (_dot(cross(t2 - t1, p - t1), n) >= 0)
            & (_dot(cross(t0 - t2, p - t2), n) >= 0))  # fmt: skip


def _triangle_normal(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n = (t1 - t0) x (t2 - t0), |n|^2, and whether the triangle has area (|n|^2 > PARALLEL |e1|^2 |e2|^2)."""
    t0, t1, t2 = tri.unbind(-2)
    e1, e2 = t1 - t0, t2 - t0
    n = torch.linalg.cross(e1, e2)
    nn = _dot(n, n)
    return n, nn, nn > PARALLEL * _dot(e1, e1) * _dot(e2, e2)


def _edges(tri: torch.Tensor) -> torch.Tensor:
    """The triangle's three edges (t0, t1), (t1, t2), (t2, t0): (..., 3, 3) -> (..., 3, 2, 3)."""
    return torch.stack([tri, tri.roll(-1, dims=-2)], dim=-2)


def point_triangle_distance(p: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """d = |(p - t0) . n| / |n| where p projects inside the triangle (face region, n = (t1 - t0) x (t2 - t0)),
    else min_i point_segment_distance(p, edge_i) (edge and vertex regions).

    p (..., 3), tri (..., 3, 3) -> (...).
    """
    n, nn, area = _triangle_normal(tri)
    t0, t1, t2 = tri.unbind(-2)
    face = area & _inside_triangle(p, t0, t1, t2, n)
    d_face = _dot(p - t0, n).abs() / torch.sqrt(_safe(nn, face))
    d_edge = point_segment_distance(p[..., None, :], _edges(tri)).amin(-1)
    return torch.where(face, d_face, d_edge)


def segment_segment_distance(sa: torch.Tensor, sb: torch.Tensor) -> torch.Tensor:
    """d = |A(s) - B(t)| at the two lines' closest points A(s) = a0 + s ea, B(t) = b0 + t eb where both lie
    inside their segments (0 <= s, t <= 1), the edges not parallel (|ea x eb|^2 > PARALLEL |ea|^2 |eb|^2);
    else the least of the four endpoint-to-segment distances.  The lines' parameters solve
    [ea.ea, -ea.eb; ea.eb, -eb.eb] [s; t] = [-ea.r; -eb.r], r = a0 - b0, by Cramer's rule.

    sa, sb (..., 2, 3) -> (...).
    """
    a0, a1 = sa.unbind(-2)
    b0, b1 = sb.unbind(-2)
    ea, eb, r = a1 - a0, b1 - b0, a0 - b0
    aa, bb, ab, ar, br = _dot(ea, ea), _dot(eb, eb), _dot(ea, eb), _dot(ea, r), _dot(eb, r)
    den = aa * bb - ab * ab
    s_num, t_num = ab * br - ar * bb, aa * br - ab * ar
    interior = (den > PARALLEL * aa * bb) & (s_num >= 0) & (s_num <= den) & (t_num >= 0) & (t_num <= den)
    den = _safe(den, interior)
    d_in = _norm(a0 + (s_num / den)[..., None] * ea - b0 - (t_num / den)[..., None] * eb)
    ends = torch.stack([point_segment_distance(a0, sb), point_segment_distance(a1, sb),
                        point_segment_distance(b0, sa), point_segment_distance(b1, sa)], -1).amin(-1)  # fmt: skip
    return torch.where(interior, d_in, ends)


def _pierces(seg: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """Whether the segment crosses the triangle's inside: its ends strictly on opposite sides of the plane
    (h0 h1 < 0, h_i = (x_i - t0) . n) and the crossing x0 + h0 / (h0 - h1) (x1 - x0) inside the triangle."""
    n, _, area = _triangle_normal(tri)
    t0, t1, t2 = tri.unbind(-2)
    x0, x1 = seg.unbind(-2)
    h0, h1 = _dot(x0 - t0, n), _dot(x1 - t0, n)
    cross = h0 * h1 < 0
    c = x0 + (h0 / _safe(h0 - h1, cross))[..., None] * (x1 - x0)
    return area & cross & _inside_triangle(c, t0, t1, t2, n)


def segment_triangle_distance(seg: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """d = 0 where the segment pierces the triangle, else the least of point_triangle_distance(x_i, tri) for its
    ends and segment_segment_distance(seg, edge_j) for the triangle's edges.

    seg (..., 2, 3), tri (..., 3, 3) -> (...).
    """
    ends = point_triangle_distance(seg, tri[..., None, :, :]).amin(-1)
    edges = segment_segment_distance(seg[..., None, :, :], _edges(tri)).amin(-1)
    d = torch.minimum(ends, edges)
    return torch.where(_pierces(seg, tri), torch.zeros_like(d), d)


def _point_point(p: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """d = |p - x|, p and x (..., 1, 3) -> (...)."""
    return _norm(p[..., 0, :] - x[..., 0, :])


#: (core's vertices, primitive's vertices) -> the distance of the pair, core first
_PAIRS: dict[tuple[int, int], Callable] = {
    (1, 1): _point_point,
    (1, 2): lambda c, x: point_segment_distance(c[..., 0, :], x),
    (1, 3): lambda c, x: point_triangle_distance(c[..., 0, :], x),
    (2, 1): lambda c, x: point_segment_distance(x[..., 0, :], c),
    (2, 2): segment_segment_distance,
    (2, 3): segment_triangle_distance,
    (3, 1): lambda c, x: point_triangle_distance(x[..., 0, :], c),
}


def core_distance(core: torch.Tensor, xp: torch.Tensor) -> torch.Tensor:
    """The unsigned distance between a collider's core and a primitive: min |c - x| over c in the core (a point,
    m = 1, or a segment, m = 2) and x in the primitive (a vertex k = 1, an edge k = 2, a triangle k = 3), by the
    function of the module's table; a sphere's or capsule's signed distance is this minus its radius.  A triangle
    core (m = 3, a mesh collider's face) pairs with a vertex.

    core (..., m, 3), xp (..., k, 3) -> (...).
    """
    key = (core.shape[-2], xp.shape[-2])
    if key not in _PAIRS:
        raise ValueError(f"core_distance: a core of {key[0]} and a primitive of {key[1]} vertices (give m in 1, 2 and k in 1, 2, 3)")
    return _PAIRS[key](core, xp)


def plane_distance(xp: torch.Tensor, point: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """d = min_i n . (x_i - p), the signed distance of a primitive (vertex, edge or triangle) from the plane through
    p with unit normal n: an affine function's minimum over a convex hull is at a vertex, so this is exact.

    xp (..., k, 3), point and normal (3,) or broadcastable to (..., 3) -> (...).
    """
    return ((xp - point[..., None, :]) * normal[..., None, :]).sum(-1).amin(-1)


def primitive_toi(x, dx, distance: Callable[[torch.Tensor], torch.Tensor], safety: float = 0.1, rtol: float = 1e-2,
                  max_iter: int = 1000) -> torch.Tensor:  # fmt: skip
    """The first fraction t of the straight motion x_i + t dx_i of each primitive's vertices at which its distance
    from a static collider falls to ``safety`` times its start, d(t) = safety d(0), by conservative advancement
    (the additive CCD of Li et al. 2021 against a static shape).

    Every point of a primitive is a fixed convex combination of its vertices, so it moves by at most
    L = max_i |dx_i| per unit t, and the distance from a static set (a signed distance from a surface too) is
    1-Lipschitz in the point: d(t + tau) >= d(t) - L tau.  From t = 0 each step advances
    tau = (d(t) - safety d(0)) / L, which cannot cross the target; the advance stops where d(t) is within
    ``rtol`` (d(0) - safety d(0)) of the target (returning that t), or where it passes t = 1 (no impact in the
    step: inf).  The distance stays at or above safety d(0) > 0 over [0, t]: t is conservative, at most the true
    fraction.  Near a head-on approach (the distance falling at the rate L) one step lands on the target; a
    grazing approach (falling at r L, r << 1) takes about ln(1 / rtol) / r steps, and after ``max_iter`` the t
    reached is returned (still conservative).

    Parameters
    ----------
    x, dx : (..., k, 3) the primitives' vertices at the start and their displacements over the step (tensors or
        arrays; computed in float64, without gradients).
    distance : (N, k, 3) -> (N,), the primitives' signed distances from the collider (e.g. a collider's
        ``primitive_distance``).
    safety : the fraction of the starting distance that counts as impact, in [0, 1); rtol : see above.

    Returns
    -------
    (...) float64: t in (0, 1) where the target is reached, inf where it is not within the step, 0 where the
    primitive starts on or inside the collider.
    """
    x, dx = (torch.as_tensor(v, dtype=torch.float64) for v in (x, dx))
    shape, k = x.shape[:-2], x.shape[-2]
    x, dx = x.reshape(-1, k, 3), torch.broadcast_to(dx, shape + (k, 3)).reshape(-1, k, 3)
    with torch.no_grad():
        d0 = distance(x)
        speed = _norm(dx).amax(-1)
        out = torch.where(d0 <= 0, torch.zeros_like(d0), torch.full_like(d0, math.inf))
        t, d, gap = torch.zeros_like(d0), d0.clone(), (1 - safety) * d0
        target = safety * d0
        active = (d0 > 0) & (speed > 0)
        for _ in range(max_iter):
            idx = active.nonzero()[:, 0]
            if len(idx) == 0:
                break
            t_new = t[idx] + (d[idx] - target[idx]) / speed[idx]
            moving = t_new < 1  # the rest pass the step's end with no impact: inf
            idx, t_new = idx[moving], t_new[moving]
            active[:] = False
            t[idx] = t_new
            d[idx] = distance(x[idx] + t_new[:, None, None] * dx[idx])
            reached = d[idx] - target[idx] <= rtol * gap[idx]
            out[idx[reached]] = t[idx[reached]]
            active[idx[~reached]] = True
        out[active] = t[active]
    return out.reshape(shape)


def distance_hessian(xp: torch.Tensor, grad: torch.Tensor, rho: torch.Tensor, axis: torch.Tensor | None = None,
                     active_tol: float = 1e-12) -> torch.Tensor:  # fmt: skip
    """The Hessian of the distance rho = min |q - p| between a core (a point, or the segment ``axis``) and a primitive's
    closest point p = sum_i w_i x_i, from the gradient the distance already has (its envelope, grad_i = -w_i n).

    The distance is the value of an inner minimum over the closest point's barycentric weights w (and the axis'
    parameter s, q = a + s e), f(x, u) = |q(u) - p(x, u)|; where the minimiser is unique its Hessian in x is
    f_xx - f_xu B (B^T f_uu B)^+ B^T f_ux (the implicit function theorem on the inner minimum), B the directions of
    u left free by the active feature (the weights above ``active_tol`` moving among themselves, s inside (0, 1)).
    With v = q - p, n = v / |v| and P = (I - n n^T) / |v|: f_{x_i x_j} = w_i w_j P, f_{x_i w_j} = -delta_ij n +
    w_i P x_j, f_{w_i w_j} = x_i^T P x_j, f_{x_i s} = -w_i P e, f_{w_i s} = -x_i^T P e, f_ss = e^T P e.

    Parameters
    ----------
    xp : (N, k, 3) the primitives' vertices; grad : (N, k, 3) the distance's gradient there (autograd's of
        :func:`core_distance`); rho : (N,) the unsigned distance (> 0); axis : None (the core a point), or (2, 3) the
        segment's ends (or (N, 2, 3), one segment per primitive).  Where rho is 0 (the core touches the primitive) the Hessian is returned as 0.

    Returns
    -------
    (N, 3k, 3k) float64.
    """
    N, k, _ = xp.shape
    n = -grad.sum(1)  # the weights sum to 1
    w = -(grad * n[:, None, :]).sum(-1)  # (N, k)
    eye = torch.eye(3, dtype=xp.dtype, device=xp.device)
    P = (eye - n[:, :, None] * n[:, None, :]) / torch.where(rho > 0, rho, torch.ones_like(rho))[:, None, None]
    P = torch.where((rho > 0)[:, None, None], P, torch.zeros_like(P))  # touching: no unique closest pair, left at 0
    f_xx = (w[:, :, None, None, None] * w[:, None, :, None, None] * P[:, None, None]).permute(0, 1, 3, 2, 4).reshape(N, 3 * k, 3 * k)
    Px = torch.einsum("nab,njb->nja", P, xp)  # (N, k, 3): P x_j
    f_xw = (w[:, :, None, None] * Px[:, None, :, :]).permute(0, 1, 3, 2)  # (N, k_i, 3, k_j): w_i P x_j
    f_xw = f_xw - torch.eye(k, dtype=xp.dtype)[None, :, None, :] * n[:, None, :, None]
    f_xw = f_xw.reshape(N, 3 * k, k)
    f_ww = torch.einsum("nia,nja->nij", xp, Px)
    active = w > active_tol
    last = (active * torch.arange(1, k + 1)).argmax(-1)  # the last active weight: the others move against it
    cols = active & (torch.arange(k)[None, :] != last[:, None])
    B = torch.diag_embed(cols.to(xp.dtype))
    B[torch.arange(N)[:, None], last[:, None], torch.arange(k)[None, :]] -= cols.to(xp.dtype)
    if axis is not None:
        a, b = axis[..., 0, :], axis[..., 1, :]
        e = b - a
        p = (w[:, :, None] * xp).sum(1)
        s = ((p + rho[:, None] * n - a) * e).sum(-1) / (e * e).sum(-1)
        Pe = P @ e if e.ndim == 1 else (P @ e[:, :, None])[:, :, 0]
        f_xs = (-w[:, :, None] * Pe[:, None, :]).reshape(N, 3 * k, 1)
        f_ws = -(xp * Pe[:, None, :]).sum(-1)[:, :, None]
        f_ss = (e * Pe).sum(-1)[:, None, None]
        f_xw = torch.cat([f_xw, f_xs], -1)
        f_ww = torch.cat([torch.cat([f_ww, f_ws], -1), torch.cat([f_ws.transpose(1, 2), f_ss], -1)], 1)
        free_s = ((s > active_tol) & (s < 1 - active_tol)).to(xp.dtype)
        B = torch.cat([torch.cat([B, torch.zeros(N, k, 1, dtype=xp.dtype)], -1), torch.zeros(N, 1, k + 1, dtype=xp.dtype)], 1)
        B[:, k, k] = free_s
    M = B.transpose(1, 2) @ f_ww @ B
    C = f_xw @ B
    return f_xx - C @ torch.linalg.pinv(M) @ C.transpose(1, 2)


def vertex_hessian(x: torch.Tensor, grad: torch.Tensor, rho: torch.Tensor, core: torch.Tensor, active_tol: float = 1e-12) -> torch.Tensor:
    """The Hessian in the vertex x of its distance rho = min |x - q| from a static core (a point, segment or triangle,
    q its closest point), from the distance's gradient n = (x - q) / rho: (I - n n^T - Q) / rho, Q the projector onto
    the directions of the core's feature that holds q (none for a corner, the edge's for an edge, the plane's for a
    face: there the distance is a plane's, and its Hessian 0).  Those directions are orthogonal to n.

    x (N, 3), grad (N, 3), rho (N,) > 0 (where 0 the Hessian is returned as 0), core (N, m, 3) -> (N, 3, 3) float64.
    """
    N, m, _ = core.shape
    q = x - rho[:, None] * grad
    # the closest point's weights on the core: least squares in the core's own frame (exact where q lies on it)
    base = core[:, :1, :]
    D = (core[:, 1:, :] - base).transpose(1, 2)  # (N, 3, m - 1)
    u = (torch.linalg.pinv(D) @ (q - base[:, 0, :])[:, :, None])[:, :, 0] if m > 1 else q.new_zeros(N, 0)
    w = torch.cat([1 - u.sum(-1, keepdim=True), u], -1)  # (N, m)
    active = w > active_tol
    last = (active * torch.arange(1, m + 1)).argmax(-1)
    # the feature's directions: each other active corner less the last active one
    dirs = (core - core[torch.arange(N), last][:, None, :]) * (active & (torch.arange(m)[None, :] != last[:, None]))[:, :, None]
    E = dirs.transpose(1, 2)  # (N, 3, m)
    Q = E @ torch.linalg.pinv(E)
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    H = (eye - grad[:, :, None] * grad[:, None, :] - Q) / torch.where(rho > 0, rho, torch.ones_like(rho))[:, None, None]
    return torch.where((rho > 0)[:, None, None], H, torch.zeros_like(H))
