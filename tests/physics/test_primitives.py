"""Closest-point distances of edges and triangles from the colliders' cores, and their time of impact:
analytic cases per region, gradients against finite differences, a brute-force oracle (the minimum over a
dense sampling of the primitive), IPC-toolkit as an oracle where installed, and the conservative advance."""

import math

import numpy as np
import pytest
import torch

from latentsim.physics.barrier import barrier, barrier_derivatives
from latentsim.physics.colliders import Capsule, HalfSpace, Sphere, primitive_barriers
from latentsim.physics.primitives import (core_distance, plane_distance, point_segment_distance, point_triangle_distance,
                                          primitive_toi, segment_segment_distance, segment_triangle_distance)  # fmt: skip

F64 = torch.float64
TRI = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
COLLIDERS = {
    "half_space": HalfSpace((0.0, -0.5, 0.0), (0.0, 1.0, 0.0)),
    "sphere": Sphere((0.1, 0.0, -0.2), 0.3),
    "capsule": Capsule((-0.4, 0.0, 0.0), (0.4, 0.1, 0.0), 0.2),
}


def T(v):
    return torch.tensor(v, dtype=F64)


def _random(rng, *shape):
    return torch.as_tensor(rng.normal(size=shape), dtype=F64)


# -- analytic cases --------------------------------------------------------------------------------------
@pytest.mark.parametrize("p, d", [((0.5, 2.0, 0.0), 2.0),  # the segment's inside
                                  ((-3.0, 4.0, 0.0), 5.0),  # beyond a, its vertex
                                  ((4.0, 0.0, 3.0), math.sqrt(18.0))])  # beyond b  # fmt: skip
def test_point_segment_regions(p, d):
    assert point_segment_distance(T(p), T(((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)))).item() == pytest.approx(d, rel=1e-15)


def test_zero_length_segment_is_its_point():
    seg = T(((1.0, 2.0, 3.0), (1.0, 2.0, 3.0)))
    p = T((2.0, 2.0, 3.0))
    assert point_segment_distance(p, seg).item() == 1.0
    other = T(((0.0, 0.0, 0.0), (0.0, 4.0, 0.0)))
    assert segment_segment_distance(seg, other).item() == pytest.approx(math.hypot(1.0, 3.0), rel=1e-15)
    assert segment_segment_distance(other, seg).item() == pytest.approx(math.hypot(1.0, 3.0), rel=1e-15)
    assert segment_segment_distance(seg, seg).item() == 0.0
    assert segment_triangle_distance(seg, T(TRI)).item() == pytest.approx(point_triangle_distance(seg[0], T(TRI)).item(), rel=1e-15)
    seg.requires_grad_()
    (g,) = torch.autograd.grad(point_segment_distance(p, seg), seg)
    assert torch.equal(g, T(((-1.0, 0.0, 0.0), (0.0, 0.0, 0.0))))  # the point's, all on the start (s = 0)


@pytest.mark.parametrize("p, d", [((0.2, 0.3, 0.7), 0.7),  # above the face
                                  ((0.25, -0.5, -1.0), math.hypot(0.5, 1.0)),  # beside edge t0 t1
                                  ((1.0, 1.0, 0.5), math.sqrt(0.5 + 0.25)),  # beside the hypotenuse
                                  ((-1.0, -2.0, 2.0), 3.0),  # beyond vertex t0
                                  ((2.0, -1.0, 0.0), math.sqrt(2.0))])  # beyond vertex t1, in the plane  # fmt: skip
def test_point_triangle_regions(p, d):
    assert point_triangle_distance(T(p), T(TRI)).item() == pytest.approx(d, rel=1e-14)


def test_degenerate_triangle_is_its_edges():
    flat = T(((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, 0.0, 0.0)))
    assert point_triangle_distance(T((0.5, 1.0, 1.0)), flat).item() == pytest.approx(math.sqrt(2.0), rel=1e-15)


@pytest.mark.parametrize("sb, d", [(((0.5, -1.0, 0.3), (0.5, 1.0, 0.3)), 0.3),  # crossing, skew: both insides
                                   (((-0.5, 0.2, 0.0), (3.0, 0.2, 0.0)), 0.2),  # parallel, overlapping
                                   (((2.0, 0.0, 1.0), (3.0, 0.0, 1.0)), math.sqrt(2.0)),  # parallel, apart
                                   (((3.0, 0.0, 0.0), (5.0, 0.0, 0.0)), 2.0),  # collinear
                                   (((1.5, -1.0, 0.0), (1.5, 1.0, 0.0)), 0.5),  # an end against an inside
                                   (((0.5, -1.0, 0.0), (0.5, 1.0, 0.0)), 0.0)])  # intersecting  # fmt: skip
def test_segment_segment_cases(sb, d):
    sa = T(((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)))
    assert segment_segment_distance(sa, T(sb)).item() == pytest.approx(d, rel=1e-14, abs=1e-15)
    assert segment_segment_distance(T(sb), sa).item() == pytest.approx(d, rel=1e-14, abs=1e-15)


@pytest.mark.parametrize("seg, d", [(((0.1, 0.1, 0.4), (0.3, 0.2, 0.4)), 0.4),  # parallel to the face, above it
                                    (((0.2, 0.2, -1.0), (0.2, 0.2, 1.0)), 0.0),  # piercing the face
                                    (((0.2, 0.2, 0.5), (0.3, 0.2, 2.0)), 0.5),  # an end above the face
                                    (((0.5, -0.3, -1.0), (0.5, -0.3, 1.0)), 0.3),  # beside edge t0 t1
                                    (((2.0, -1.0, 0.5), (2.0, 1.0, 0.5)), math.sqrt(1.25))])  # nearest to t1  # fmt: skip
def test_segment_triangle_cases(seg, d):
    assert segment_triangle_distance(T(seg), T(TRI)).item() == pytest.approx(d, rel=1e-14, abs=1e-15)


def test_edge_and_triangle_against_a_plane_are_their_nearest_vertex():
    rng = np.random.default_rng(3)
    col = COLLIDERS["half_space"]
    for k in (2, 3):
        xp = _random(rng, 50, k, 3)
        d = col.primitive_distance(xp)
        assert torch.equal(d, col.distance(xp).amin(-1))
        # and no point of the primitive is nearer: the minimum of an affine function over the hull is at a vertex
        w = torch.as_tensor(rng.dirichlet(np.ones(k), size=400), dtype=F64)
        inner = col.distance(torch.einsum("sk,pkc->psc", w, xp))
        assert (inner >= d[:, None] - 1e-12).all()
    assert plane_distance(T(TRI)[None], T((0.0, 0.0, -1.0)), T((0.0, 0.0, 1.0))).item() == 1.0


@pytest.mark.parametrize("name", ["sphere", "capsule"])
def test_a_vertex_as_a_primitive_is_the_colliders_distance(name):
    col = COLLIDERS[name]
    x = _random(np.random.default_rng(4), 200, 3)
    assert torch.allclose(col.primitive_distance(x[:, None, :]), col.distance(x), rtol=0, atol=1e-15)


def test_core_distance_rejects_other_shapes():
    with pytest.raises(ValueError, match="core_distance"):
        core_distance(torch.zeros(3, 3, dtype=F64), torch.zeros(3, 3, dtype=F64))


# -- gradients against finite differences --------------------------------------------------------------
REGIONS = {  # (core, primitive): one of each region of the pair
    "point-edge inside": (((0.5, 1.0, 0.2),), ((0.0, 0.0, 0.0), (1.0, 0.1, 0.0))),
    "point-edge vertex": (((-0.5, 1.0, 0.2),), ((0.0, 0.0, 0.0), (1.0, 0.1, 0.0))),
    "point-triangle face": (((0.2, 0.3, 0.7),), TRI),
    "point-triangle edge": (((0.25, -0.5, -1.0),), TRI),
    "point-triangle vertex": (((-1.0, -2.0, 2.0),), TRI),
    "edge-edge insides": (((0.5, -1.0, 0.3), (0.6, 1.0, 0.35)), ((0.0, 0.0, 0.0), (1.0, 0.1, 0.0))),
    "edge-edge end-inside": (((1.5, -1.0, 0.0), (1.6, 1.0, 1.0)), ((0.0, 0.0, 0.0), (1.0, 0.1, 0.0))),
    "edge-edge ends": (((1.5, 1.0, 0.0), (2.6, 1.2, 1.0)), ((0.0, 0.0, 0.0), (1.0, 0.1, 0.0))),
    "edge-triangle end-face": (((0.2, 0.2, 0.5), (0.3, 0.25, 2.0)), TRI),
    "edge-triangle edges": (((0.5, -0.3, -1.0), (0.45, -0.35, 1.0)), TRI),
    "edge-triangle end-vertex": (((2.0, -1.0, 0.5), (2.5, -1.2, 0.8)), TRI),
}


@pytest.mark.parametrize("name", REGIONS)
def test_gradients_and_hessians_match_finite_differences(name):
    core, prim = (T(v).requires_grad_() for v in REGIONS[name])
    assert torch.autograd.gradcheck(core_distance, (core, prim), eps=1e-7, atol=1e-8, rtol=1e-6)
    assert torch.autograd.gradgradcheck(core_distance, (core, prim), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_gradients_match_finite_differences_on_random_geometry():
    rng = np.random.default_rng(5)
    for m, k in ((1, 2), (1, 3), (2, 2), (2, 3)):
        core, prim = _random(rng, 6, m, 3).requires_grad_(), _random(rng, 6, k, 3).requires_grad_()
        with torch.no_grad():
            assert (core_distance(core, prim) > 1e-3).all()  # away from the non-differentiable d = 0
        assert torch.autograd.gradcheck(core_distance, (core, prim), eps=1e-7, atol=1e-7, rtol=1e-6)



@pytest.mark.parametrize("core, prim, step", [
    (((0.3, 1e-9, 0.5),), TRI, (0.0, -2e-9, 0.0)),  # point-triangle: the face region into edge t0 t1's
    (((1.0 - 1e-9, -1.0, 0.3), (1.0 - 1e-9, 1.0, 0.4)), ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), (2e-9, 0.0, 0.0)),  # edge-edge: insides to an end
])  # fmt: skip
def test_gradient_is_continuous_across_a_region_boundary(core, prim, step):
    """C1: the gradient just before and just after the boundary agree to the step's order."""
    core, prim = T(core), T(prim)
    grads = []
    for shift in (0.0, 1.0):
        c = (core + shift * T(step)).requires_grad_()
        p = prim.clone().requires_grad_()
        grads.append(torch.cat([g.reshape(-1) for g in torch.autograd.grad(core_distance(c, p), (c, p))]))
    assert torch.allclose(grads[0], grads[1], rtol=0, atol=1e-7)

# -- brute force: the minimum over a dense sampling of the primitive ----------------------------------------
def _triangle_grid(tri: torch.Tensor, n: int) -> torch.Tensor:
    """The points of the barycentric grid of spacing 1/n, (T, 3, 3) -> (T, (n+1)(n+2)/2, 3)."""
    i, j = np.triu_indices(n + 1)
    w = torch.as_tensor(np.stack([n - j, j - i, i], -1) / n, dtype=F64)  # (S, 3), non-negative, rows sum to 1
    return torch.einsum("sk,tkc->tsc", w, tri)


def _segment_grid(seg: torch.Tensor, n: int) -> torch.Tensor:
    s = torch.linspace(0, 1, n + 1, dtype=F64)[:, None]
    return seg[..., None, 0, :] + s * (seg[..., None, 1, :] - seg[..., None, 0, :])


def test_distances_are_the_minimum_over_a_dense_sampling():
    rng = np.random.default_rng(6)
    n, m = 120, 200
    tri, seg, core_seg, p = _random(rng, 30, 3, 3), _random(rng, 30, 2, 3), _random(rng, 30, 2, 3), _random(rng, 30, 3)
    tri_pts, seg_pts, core_pts = _triangle_grid(tri, n), _segment_grid(seg, m), _segment_grid(core_seg, m)
    h_tri = torch.linalg.vector_norm(tri - tri.roll(1, -2), dim=-1).amax(-1) / n  # a point of the triangle is this near a grid point
    h_seg = torch.linalg.vector_norm(seg[:, 1] - seg[:, 0], dim=-1) / (2 * m)
    h_core = torch.linalg.vector_norm(core_seg[:, 1] - core_seg[:, 0], dim=-1) / (2 * m)
    cases = [(point_triangle_distance(p, tri), (tri_pts - p[:, None]).norm(dim=-1).amin(-1), h_tri),
             (point_segment_distance(p, seg), (seg_pts - p[:, None]).norm(dim=-1).amin(-1), h_seg),
             (segment_segment_distance(core_seg, seg), torch.cdist(core_pts, seg_pts).amin((-1, -2)), h_core + h_seg),
             (segment_triangle_distance(core_seg, tri), torch.cdist(core_pts, tri_pts).amin((-1, -2)), h_core + h_tri)]  # fmt: skip
    for exact, sampled, h in cases:
        assert (exact <= sampled + 1e-12).all() and (sampled <= exact + h + 1e-12).all()


def test_piercing_segment_is_at_distance_zero_and_a_near_miss_is_not():
    tri = T(TRI)
    through = T(((0.3, 0.3, -1.0), (0.3, 0.3, 1.0)))
    assert segment_triangle_distance(through, tri).item() == 0.0
    miss = T(((0.6, 0.6, -1.0), (0.6, 0.6, 1.0)))  # crosses the plane just outside the hypotenuse
    assert segment_triangle_distance(miss, tri).item() == pytest.approx(0.1 * math.sqrt(2.0), rel=1e-14)


# -- IPC-toolkit as an oracle ------------------------------------------------------------------------------
def _ipc_cases(ipctk, rng, n=400):
    """(name, our distance, IPC-toolkit's squared distance, our autograd (gradient, Hessian) of d^2 over its 3k
    coordinates, IPC-toolkit's) on random geometry."""
    for _ in range(n):
        v = rng.normal(size=(4, 3))
        for name, ours, theirs, grad, hess, k in (
            ("point-edge", lambda y: point_segment_distance(y[0], y[1:3]), ipctk.point_edge_distance,
             ipctk.point_edge_distance_gradient, ipctk.point_edge_distance_hessian, 3),
            ("edge-edge", lambda y: segment_segment_distance(y[0:2], y[2:4]), ipctk.edge_edge_distance,
             ipctk.edge_edge_distance_gradient, ipctk.edge_edge_distance_hessian, 4),
            ("point-triangle", lambda y: point_triangle_distance(y[0], y[1:4]), ipctk.point_triangle_distance,
             ipctk.point_triangle_distance_gradient, ipctk.point_triangle_distance_hessian, 4),
        ):  # fmt: skip
            y = torch.as_tensor(v[:k], dtype=F64).reshape(-1)
            sq = lambda flat: ours(flat.reshape(k, 3)) ** 2  # noqa: E731
            g = torch.func.grad(sq)(y)
            H = torch.func.hessian(sq)(y)
            yield name, ours(y.reshape(k, 3)).item(), theirs(*v[:k]), (g, H), (grad(*v[:k]), hess(*v[:k]))


def test_distances_gradients_and_hessians_match_ipctk():
    """Distances to 1e-12 relative; the gradient of d^2 to 1e-10 and its Hessian to 1e-8, relative to their norms
    (IPC-toolkit's Hessian is exact within a region, not PSD-projected)."""
    ipctk = pytest.importorskip("ipctk")
    worst = {}
    for name, d, d2, (g, H), (g_ref, H_ref) in _ipc_cases(ipctk, np.random.default_rng(7)):
        errs = (abs(d - math.sqrt(d2)) / math.sqrt(d2), float(np.linalg.norm(g.numpy() - g_ref) / np.linalg.norm(g_ref)),
                float(np.linalg.norm(H.numpy() - H_ref) / np.linalg.norm(H_ref)))  # fmt: skip
        worst[name] = tuple(max(a, b) for a, b in zip(worst.get(name, (0, 0, 0)), errs))
    print("worst relative differences from ipctk (distance, gradient, Hessian):", worst)
    for d_err, g_err, h_err in worst.values():
        assert d_err < 1e-12 and g_err < 1e-10 and h_err < 1e-8


def test_segment_triangle_matches_ipctk_features():
    """Where the segment does not pierce the triangle, its distance is the least of IPC-toolkit's point-triangle
    (its ends) and edge-edge (the triangle's edges) distances."""
    ipctk = pytest.importorskip("ipctk")
    rng = np.random.default_rng(8)
    worst = 0.0
    for _ in range(300):
        v = rng.normal(size=(5, 3))
        d = segment_triangle_distance(torch.as_tensor(v[:2]), torch.as_tensor(v[2:])).item()
        ref = min([ipctk.point_triangle_distance(v[i], *v[2:]) for i in (0, 1)]
                  + [ipctk.edge_edge_distance(v[0], v[1], v[2 + j], v[2 + (j + 1) % 3]) for j in range(3)])  # fmt: skip
        if d == 0.0:  # pierces: the segment crosses the triangle's plane inside it
            continue
        worst = max(worst, abs(d - math.sqrt(ref)) / math.sqrt(ref))
    assert worst < 1e-12


def test_barrier_matches_ipctk():
    """ipctk's barrier is b(d) = -(d - d_hat)^2 ln(d / d_hat) of whatever distance it is given (IPC-toolkit applies it
    to squared distances with d_hat^2); ours is kappa times it, applied to the signed distance itself."""
    ipctk = pytest.importorskip("ipctk")
    d_hat, kappa = 0.02, 3.5
    d = torch.linspace(1e-5, 0.03, 301, dtype=F64)
    ours = (barrier(d, d_hat, kappa),) + barrier_derivatives(d, d_hat, kappa)
    for f, b in zip((ipctk.barrier, ipctk.barrier_first_derivative, ipctk.barrier_second_derivative), ours):
        ref = torch.tensor([kappa * f(float(v), d_hat) if v < d_hat else 0.0 for v in d], dtype=F64)
        assert torch.allclose(b, ref, rtol=1e-12, atol=1e-14 * ref.abs().max().item())


# -- per-primitive barriers ----------------------------------------------------------------------------------
def test_a_triangle_over_a_ball_is_in_the_barrier_where_its_vertices_are_not():
    """The issue's case: a cloth triangle draped over a ball, its vertices beyond d_hat, its middle within it."""
    ball = Sphere((0.0, 0.0, 0.0), 0.1)
    x = T(((-0.2, -0.2, 0.101), (0.3, -0.2, 0.101), (-0.2, 0.3, 0.101)))
    d_hat, kappa = 0.01, 1.0
    assert (ball.distance(x) > d_hat).all() and (barrier(ball.distance(x), d_hat, kappa) == 0).all()
    e_edges, e_tri = primitive_barriers(x, [[0, 1], [1, 2], [2, 0]], [[0, 1, 2]], ball, d_hat, kappa)
    assert e_edges.shape == (3,) and e_tri.shape == (1,)
    assert e_tri.item() == pytest.approx(barrier(T([0.001]), d_hat, kappa).item(), rel=1e-12)
    assert (e_edges == 0).all()  # the edges pass beyond d_hat too: only the triangle sees the ball
    plane = HalfSpace((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))  # against a plane, every primitive is its nearest vertex
    e_edges, e_tri = primitive_barriers(x[None], [[0, 1]], [[0, 1, 2]], plane, d_hat, kappa)
    assert e_edges.shape == (1, 1) and torch.allclose(e_tri, barrier(T([[0.001]]), d_hat, kappa), rtol=1e-9)


# -- time of impact ----------------------------------------------------------------------------------------------
AIM = {"half_space": (0.0, -0.6, 0.0), "sphere": (0.1, 0.0, -0.2), "capsule": (0.0, 0.05, 0.0)}


def _motions(k, aim, rng, n=40):
    """Primitives of k vertices about 0.9 above ``aim`` (the upper half of a sphere about it) moving through it
    (a translation and a turn), (n, k, 3) twice."""
    u = _random(rng, n, 3)
    u[:, 1] = u[:, 1].abs()
    u = 0.9 * u / u.norm(dim=-1, keepdim=True)
    x = T(aim) + u[:, None, :] + 0.15 * _random(rng, n, k, 3)
    dx = -1.5 * u[:, None, :] + 0.3 * _random(rng, n, k, 3)
    return x, dx


@pytest.mark.parametrize("name", COLLIDERS)
@pytest.mark.parametrize("k", [2, 3])
def test_time_of_impact_is_conservative(name, k):
    col = COLLIDERS[name]
    x, dx = _motions(k, AIM[name], np.random.default_rng(9 + k))
    d0 = col.primitive_distance(x)
    x, dx, d0 = x[d0 > 1e-3], dx[d0 > 1e-3], d0[d0 > 1e-3]
    safety = 0.1
    t = primitive_toi(x, dx, col.primitive_distance, safety=safety)
    hit = torch.isfinite(t)
    assert hit.sum() >= len(t) // 2 and ((t[hit] > 0) & (t[hit] < 1)).all()
    s = torch.linspace(0, 1, 2001, dtype=F64)
    path = col.primitive_distance(x[:, None] + s[None, :, None, None] * dx[:, None])  # (N, S)
    target = safety * d0
    # at the returned fraction the distance is positive, at or above the target, and within rtol of it
    d_t = col.primitive_distance(x[hit] + t[hit][:, None, None] * dx[hit])
    assert (d_t > 0).all() and (d_t >= target[hit] * (1 - 1e-9)).all() and (d_t <= target[hit] + 0.011 * d0[hit]).all()
    # no earlier crossing on the dense sampling, and where none was found the whole step stays above the target
    before = torch.where(s[None, :] <= torch.where(hit, t, torch.ones_like(t))[:, None], path, torch.full_like(path, math.inf))
    assert (before.amin(-1) >= target * (1 - 1e-9)).all()
    assert (path[~hit].amin(-1) >= target[~hit] * (1 - 1e-9)).all()


def test_time_of_impact_edge_cases():
    ball = Sphere((0.0, 0.0, 0.0), 0.1)
    x = T(((-0.2, 0.0, 0.3), (0.2, 0.0, 0.3)))[None]
    head_on = primitive_toi(x, T([[[0.0, 0.0, -0.4]] * 2]), ball.primitive_distance, safety=0.1)
    assert head_on.item() == pytest.approx(0.45, rel=1e-12)  # distance 0.2 falls to 0.02 over 0.18 at speed 0.4
    away = primitive_toi(x, T([[[0.0, 0.0, 0.4]] * 2]), ball.primitive_distance)
    still = primitive_toi(x, torch.zeros(1, 2, 3, dtype=F64), ball.primitive_distance)
    inside = primitive_toi(T(((-0.2, 0.0, 0.05), (0.2, 0.0, 0.05)))[None], T([[[0.0, 0.0, 1.0]] * 2]), ball.primitive_distance)
    assert math.isinf(away.item()) and math.isinf(still.item()) and inside.item() == 0.0
    # the edge's middle meets the ball before either vertex would: the vertex CCD alone misses it
    assert np.isinf(ball.time_of_impact(x[0].numpy(), np.tile([0.0, 0.0, -0.4], (2, 1)))).all()
