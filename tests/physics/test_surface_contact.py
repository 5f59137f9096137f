"""The surface's edges and triangles against the curved colliders (``SurfaceBarrier``), and the thickness.

Derivatives against autograd (the oracle of :mod:`latentsim.physics.base`) and finite differences, the reach filter
exact, the time of impact conservative, and the physics: a cloth dropped on a ball smaller than its cells goes in with
the vertices alone and stays out, by points sampled on its triangles, with the surface held."""

import numpy as np
import pytest
import torch

from latentsim.physics.base import autograd_gradient_hessian
from latentsim.physics.colliders import Capsule, HalfSpace, Sphere
from latentsim.physics.contact import ContactBarrier
from latentsim.physics.primitives import core_distance, distance_hessian, primitive_toi

F64 = torch.float64
CORES = {"point": torch.tensor([[0.1, 0.2, -0.1]], dtype=F64), "segment": torch.tensor([[-0.5, 0.1, 0.0], [0.6, -0.1, 0.2]], dtype=F64)}


@pytest.mark.parametrize("core,k", [("point", 2), ("point", 3), ("segment", 1), ("segment", 2), ("segment", 3)])
def test_the_closed_form_hessian_of_a_closest_point_distance_is_autograds(core, k):
    """In every region (vertex, edge, face; the axis' ends and inside), to rounding."""
    c = CORES[core]
    gen = torch.Generator().manual_seed(3)
    xp = (torch.rand(300, k, 3, generator=gen, dtype=F64) - 0.5) * 2
    y = xp.clone().requires_grad_(True)
    d = core_distance(c, y)
    (g,) = torch.autograd.grad(d.sum(), y)
    H = distance_hessian(xp, g, d.detach(), None if c.shape[0] == 1 else c)
    apart = d.detach() > 1e-3  # a segment through a triangle: no unique closest pair
    He = torch.stack([torch.autograd.functional.hessian(lambda f: core_distance(c, f.reshape(k, 3)), xp[i].reshape(-1)) for i in range(len(xp))])
    err = (H - He).abs().amax((1, 2)) / He.abs().amax((1, 2)).clamp_min(1e-12)
    assert apart.sum() > 200 and float(err[apart].max()) < 1e-9


def _surface(collider, k=3, n=60, seed=1):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=gen, dtype=F64) * 0.3
    prims = [[i + j for j in range(k)] for i in range(0, n - k, k)]
    barrier = ContactBarrier(n, [collider, HalfSpace((0, -1, 0), (0, 1, 0))], d_hat=0.08, kappa=1.0, primitives=prims)
    return x, barrier, barrier.terms()[1]


@pytest.mark.parametrize("k", [2, 3])
@pytest.mark.parametrize("shape", ["sphere", "capsule"])
def test_the_surface_barrier_derivatives_are_autograds_and_its_energy_its_stencils(k, shape):
    col = Sphere((0.15, -0.06, 0.15), 0.1) if shape == "sphere" else Capsule((0, -0.05, 0.15), (0.3, -0.05, 0.15), 0.06)
    x, barrier, term = _surface(col, k)
    assert [t.name for t in barrier.terms()] == ["contact_barrier", "surface_barrier"]
    xe = term.gather(x)
    assert (term.distances(x) < term.d_hat).sum() >= 3  # some within reach, some not
    for project in (False, True):
        g, H = term.local_gradient_hessian(xe, project=project)
        ge, He = autograd_gradient_hessian(term, xe, project=project)
        assert torch.allclose(g, ge, rtol=1e-10, atol=1e-14 * float(ge.abs().max()))
        assert torch.allclose(H, He, rtol=1e-9, atol=1e-12 * float(He.abs().max()))
    # the reach filter is exact: the energy of every state (batched) that of all its stencils
    xs = torch.stack([x, x + 0.01, x - 0.02])
    assert torch.allclose(term.energy(xs), term.local_energy(term.gather(xs)).sum(-1), rtol=1e-14, atol=0)
    # and a finite difference of the total
    xt = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(term.energy(xt), xt)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    h = 1e-6
    fd = (term.energy(x + h * v) - term.energy(x - h * v)) / (2 * h)
    assert float(fd) == pytest.approx(float((grad * v).sum()), rel=1e-6)


def test_the_half_space_is_left_to_the_vertices_and_thickness_grows_every_shape():
    x = torch.tensor([[0.0, 0.1, 0.0], [1.0, 0.1, 0.0], [0.0, 0.1, 1.0]], dtype=F64)
    floor = ContactBarrier(3, [HalfSpace((0, 0, 0), (0, 1, 0))], 0.2, 1.0, primitives=[[0, 1, 2]])
    assert floor.terms() == [floor]  # against a plane the nearest point of a triangle is a vertex
    for shape in (HalfSpace((0, 0, 0), (0, 1, 0)), Sphere((0.3, -0.5, 0.3), 0.4), Capsule((0, -0.5, 0), (1, -0.5, 0), 0.4)):
        grown = shape.thickened(0.03)
        assert torch.allclose(grown.primitive_distance(x[None]), shape.primitive_distance(x[None]) - 0.03, atol=1e-15)
        assert torch.allclose(grown.distance(x), shape.distance(x) - 0.03, atol=1e-15)
        assert shape.thickened(0.0) is shape


def test_the_surface_time_of_impact_is_conservative_and_its_filter_misses_nothing():
    """Over random steps: the first impact is that of every primitive's advancement (none left out by the reach
    bound), and at it every primitive keeps at least a tenth of its starting distance (less the advancement's 1%)."""
    col = Sphere((0.15, -0.06, 0.15), 0.1)
    x, barrier, term = _surface(col)
    gen = torch.Generator().manual_seed(5)
    st = term.stencils.numpy()
    for _ in range(20):
        dx = (torch.rand(x.shape, generator=gen, dtype=F64) - 0.5) * 0.4
        t = term.first_impact(x.numpy(), dx.numpy())
        every = primitive_toi(x.numpy()[st], dx.numpy()[st], col.primitive_distance)
        assert t == pytest.approx(float(every.min()), rel=1e-12) or (t == np.inf and not np.isfinite(every).any())
        if np.isfinite(t):
            d0 = col.primitive_distance(x[st])
            dt = col.primitive_distance((x + t * dx)[st])
            assert bool((dt >= 0.1 * d0 - 0.01 * 0.9 * d0 - 1e-12).all())


def _sampled_depth(x, triangles, centre, radius, n=10):
    """The deepest of points sampled on every triangle (a barycentric grid) into the ball: independent of the closest points."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    w = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], -1) / n
    pts = np.einsum("sk,tkd->tsd", w, x[triangles]).reshape(-1, 3)
    return float(np.maximum(radius - np.linalg.norm(pts - centre, axis=1), 0.0).max())


def test_a_cloth_dropped_on_a_small_ball_goes_in_with_its_vertices_alone_and_stays_out_with_its_triangles():
    """A ball smaller than the cloth's cells under the middle of a cell: the vertex barrier never sees it and the cloth
    sinks over it (the test would pass for the vertices if the ball were missed both ways); the surface barrier holds
    every sampled point of every triangle outside, at the cloth's half thickness."""
    from latentsim.mesh import cloth_grid
    from latentsim.scene import build_potential
    from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

    X, tris = cloth_grid(4, 4, 0.2, 0.2, plane="xz")
    X = np.asarray(X, dtype=np.float64)
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.flatnonzero((np.abs(X[:, 0]) > 0.099) & (np.abs(X[:, 2]) > 0.099))}
    material = {"youngs_modulus": 1e4, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.002}
    centre, radius = np.array([0.025, -0.03, 0.025]), 0.02  # under the middle of a 5 cm cell, 1 cm below the cloth
    depths = {}
    for thickness, label in ((0.0, "vertices"), (None, "surface")):
        contact = {"colliders": [{"type": "sphere", "centre": centre.tolist(), "radius": radius}], "thickness": thickness}
        pot = build_potential("shell", arrays, material, 1 / 30, [0, -9.81, 0], free_only=True, contact=contact)
        if label == "vertices":
            pot.contact = ContactBarrier(len(X), pot.contact.colliders, pot.contact.d_hat, pot.contact.kappa)
        solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-6))
        x2 = x1 = X.copy()
        deepest = 0.0
        for _ in range(30):
            x, _ = solver.step(x1, x2, X[arrays["dirichlet"]])
            deepest = max(deepest, _sampled_depth(x, np.asarray(tris), centre, radius + (0.0 if thickness == 0.0 else 0.001)))
            x2, x1 = x1, x
        depths[label] = deepest
    assert depths["vertices"] > 0.003  # the ball through the cell
    assert depths["surface"] == 0.0
