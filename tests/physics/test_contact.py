"""The contact barrier against analytic colliders, tested as physics: zero beyond d_hat, C2 there,
derivatives against finite differences and the autograd oracle, symmetry, and the time of impact."""

import math

import numpy as np
import pytest
import torch

from latentsim.physics.base import autograd_gradient_hessian
from latentsim.physics.barrier import barrier, barrier_derivatives
from latentsim.physics.colliders import Capsule, HalfSpace, Sphere
from latentsim.physics.contact import ContactBarrier
from latentsim.physics.frame import Frame
from latentsim.solve.newton import max_step

F64 = torch.float64
COLLIDERS = {
    "half_space": HalfSpace((0.0, -0.5, 0.0), (0.0, 1.0, 0.0)),
    "sphere": Sphere((0.1, 0.0, -0.2), 0.3),
    "capsule": Capsule((-0.4, 0.0, 0.0), (0.4, 0.1, 0.0), 0.2),
}


def test_barrier_is_zero_beyond_d_hat_c2_there_and_infinite_at_contact():
    d_hat, kappa = 0.01, 3.0
    d = torch.tensor([d_hat, 1.5 * d_hat, 10.0], dtype=F64)
    assert torch.equal(barrier(d, d_hat, kappa), torch.zeros(3, dtype=F64))
    assert all(torch.equal(v, torch.zeros(3, dtype=F64)) for v in barrier_derivatives(d, d_hat, kappa))
    eps = torch.tensor([1e-7, 1e-5], dtype=F64)
    b, (db, d2b) = barrier(d_hat - eps, d_hat, kappa), barrier_derivatives(d_hat - eps, d_hat, kappa)
    # b, b', b'' -> 0 as d -> d_hat from below, as eps^3, eps^2 and eps (b'' ~ 6 kappa eps / d_hat): C2 at d_hat
    assert (b > 0).all() and (b <= 3 * kappa * eps**3 / d_hat).all() and (db < 0).all() and (db.abs() <= 4 * kappa * eps**2 / d_hat).all()
    assert (d2b > 0).all() and (d2b <= 7 * kappa * eps / d_hat).all()
    assert torch.isinf(barrier(torch.tensor([0.0, -1e-3], dtype=F64), d_hat, kappa)).all()
    small = barrier(torch.tensor([1e-6, 1e-9], dtype=F64), d_hat, kappa)
    assert small[1] > small[0] > 1e-4  # grows without bound as d -> 0


def test_barrier_derivatives_match_finite_differences():
    d_hat, kappa = 0.02, 5.0
    d = torch.linspace(0.001, 0.019, 37, dtype=F64)
    h = 1e-7
    db, d2b = barrier_derivatives(d, d_hat, kappa)
    fd1 = (barrier(d + h, d_hat, kappa) - barrier(d - h, d_hat, kappa)) / (2 * h)
    fd2 = (barrier_derivatives(d + h, d_hat, kappa)[0] - barrier_derivatives(d - h, d_hat, kappa)[0]) / (2 * h)
    assert torch.allclose(db, fd1, rtol=1e-6, atol=1e-9) and torch.allclose(d2b, fd2, rtol=1e-6, atol=1e-6)
    assert (db < 0).all() and (d2b > 0).all()


def _points_near(collider, n=40, seed=0):
    """Points outside ``collider`` within 0.08 of its surface (and a few beyond)."""
    g = torch.Generator().manual_seed(seed)
    x = 0.6 * (2 * torch.rand(4000, 3, generator=g, dtype=F64) - 1)
    d = collider.distance(x)
    keep = (d > 1e-3) & (d < 0.08)
    return x[keep][:n]


@pytest.mark.parametrize("name", COLLIDERS)
def test_distance_derivatives_match_autograd(name):
    c = COLLIDERS[name]
    x = _points_near(c)
    g, H = c.distance_derivatives(x)
    xa = x.clone().requires_grad_(True)
    ga = torch.autograd.grad(c.distance(xa).sum(), xa)[0]
    Ha = torch.stack([torch.autograd.functional.hessian(lambda y: c.distance(y), xi) for xi in x])
    assert torch.allclose(g, ga, atol=1e-12) and torch.allclose(H, Ha, atol=1e-10)


def _closed_form_against_oracle_and_differences(term, x, rtol):
    """The term's closed-form per-vertex gradient and exact Hessian at x against the autograd oracle (Hessian to
    ``rtol``), and the gradient against central differences of the total energy; returns them."""
    xe = term.gather(x)
    g, H = term.local_gradient_hessian(xe, project=False)
    go, Ho = autograd_gradient_hessian(term, xe, project=False)
    assert torch.allclose(g, go.reshape(g.shape), rtol=1e-9, atol=1e-9) and torch.allclose(H, Ho.reshape(H.shape), rtol=rtol, atol=rtol)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
    h = 1e-7
    fd = (term.energy(x + h * v) - term.energy(x - h * v)) / (2 * h)
    assert float((g * v).sum()) == pytest.approx(float(fd), rel=1e-6)
    return g, H


@pytest.mark.parametrize("name", COLLIDERS)
def test_barrier_term_gradient_and_hessian_against_its_oracle_and_finite_differences(name):
    c = COLLIDERS[name]
    x = _points_near(c)
    term = ContactBarrier(len(x), [c], d_hat=0.05, kappa=2.0)
    xe = term.gather(x)
    g, H = _closed_form_against_oracle_and_differences(term, x, rtol=1e-8)
    # projected: PSD, and equal where already PSD
    gp, Hp = term.local_gradient_hessian(xe, project=True)
    assert torch.linalg.eigvalsh(Hp).min() > -1e-9 and torch.equal(gp, g)
    if name == "half_space":
        assert torch.allclose(Hp, H)


@pytest.mark.parametrize("name", COLLIDERS)
def test_the_extended_barriers_closed_form_holds_inside_the_collider_too(name):
    """The finite continuation's gradient and Hessian (a projection's, a learned loss's) against the oracle, with
    vertices on both sides of the seam and inside the collider, where the plain barrier is infinite."""
    c = COLLIDERS[name]
    x = _points_near(c)
    n, _ = c.distance_derivatives(x)
    x = torch.cat([x, x - 0.03 * n])  # the same points moved 3 cm against the surface: many inside
    assert (c.distance(x) < 0).sum() >= 2
    term = ContactBarrier(len(x), [c], d_hat=0.05, kappa=2.0).extended(0.2)
    _closed_form_against_oracle_and_differences(term, x, rtol=1e-8)


def test_the_barrier_is_zero_beyond_d_hat_and_repels_inside_it():
    plane = HalfSpace((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    x = torch.tensor([[0.0, 0.0, 0.2], [0.3, -0.1, 0.004]], dtype=F64)
    term = ContactBarrier(2, [plane], d_hat=0.01, kappa=1.0)
    e = term.element_energy(x)
    g, _ = term.local_gradient_hessian(term.gather(x))
    assert e[0] == 0 and torch.equal(g[0], torch.zeros(3, dtype=F64)) and e[1] > 0
    assert g[1, 2] < 0 and g[1, :2].abs().max() == 0  # -g: a force along the normal, away from the plane


def test_symmetry_rigid_motions_of_scene_and_collider_together():
    """The barrier of a sphere is the same after rotating the points about its centre; a half-space's
    after sliding the points along its plane."""
    s = COLLIDERS["sphere"]
    x = _points_near(s)
    term = ContactBarrier(len(x), [s], d_hat=0.05, kappa=2.0)
    q = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(2), dtype=F64))[0]
    c = torch.tensor(s.centre, dtype=F64)
    assert torch.allclose(term.energy((x - c) @ q.T + c), term.energy(x), rtol=1e-12)
    p = COLLIDERS["half_space"]
    y = _points_near(p)
    plane = ContactBarrier(len(y), [p], d_hat=0.05, kappa=2.0)
    assert torch.allclose(plane.energy(y + torch.tensor([0.3, 0.0, -0.7], dtype=F64)), plane.energy(y), rtol=1e-12)


@pytest.mark.parametrize("name", COLLIDERS)
def test_time_of_impact_lands_on_the_surface_and_max_step_stays_outside(name):
    c = COLLIDERS[name]
    rng = np.random.default_rng(3)
    x = _points_near(c, n=200).numpy()
    dx = rng.normal(size=x.shape) * 0.3
    t = c.time_of_impact(x, dx)
    hit = np.isfinite(t)
    assert hit.any() and (~hit).any() and (t[hit] >= 0).all()
    on = torch.as_tensor(x[hit] + t[hit, None] * dx[hit])
    assert np.allclose(c.distance(on).numpy(), 0.0, atol=1e-10)
    # before its time of impact each path stays outside
    for frac in (0.25, 0.5, 0.99):
        tt = np.where(hit, frac * t, 5.0)
        assert (c.distance(torch.as_tensor(x + tt[:, None] * dx)).numpy() > 0).all()
    term = ContactBarrier(len(x), [c], d_hat=0.01, kappa=1.0)
    alpha = max_step([term], x, dx)  # what a line search starts from
    assert 0 < alpha < 1 and alpha == pytest.approx(0.9 * float(t[hit].min()))
    for s in np.linspace(0, alpha, 7):
        assert (c.distance(torch.as_tensor(x + s * dx)).numpy() > 0).all()
    assert max_step([term], x, np.zeros_like(x)) == 1.0


def test_the_extended_barrier_is_finite_inside_c2_at_the_seam_and_exact_above_it():
    d_hat, kappa, de = 0.01, 2.0, 0.001
    d = torch.tensor([-0.05, -1e-4, 0.0, 0.5 * de, 2 * de, 0.02], dtype=F64)
    b = barrier(d, d_hat, kappa, extend_below=de)
    assert torch.isfinite(b).all() and (b[:-1] > 0).all() and b[0] > b[1] > b[2] > b[3] > b[4] and b[-1] == 0
    assert torch.equal(b[4:], barrier(d[4:], d_hat, kappa))
    f = lambda v: float(barrier(torch.tensor([v], dtype=F64), d_hat, kappa, extend_below=de))
    slope = lambda v, h=1e-7: (f(v + h) - f(v - h)) / (2 * h)
    curve = lambda v, h=1e-6: (f(v + h) - 2 * f(v) + f(v - h)) / h**2
    below, above = de * (1 - 1e-4), de * (1 + 1e-4)  # value, slope and curvature continuous across d_e
    assert f(below) == pytest.approx(f(above), rel=1e-3) and slope(below) == pytest.approx(slope(above), rel=1e-3)
    assert curve(below) == pytest.approx(curve(above), rel=1e-2)
    term = ContactBarrier(1, [HalfSpace((0, 0, 0), (0, 0, 1))], d_hat, kappa).extended(0.1)
    assert term.extend_below == pytest.approx(de) and torch.isfinite(term.energy(torch.tensor([[0.0, 0.0, -1.0]], dtype=F64)))
    # a learned loss's barrier: reach and stiffness scaled, the seam a fraction of the new reach
    wide = ContactBarrier(1, [HalfSpace((0, 0, 0), (0, 0, 1))], d_hat, kappa).extended(0.5, d_hat_factor=10.0, kappa_factor=0.01)
    assert (wide.d_hat, wide.kappa, wide.extend_below) == pytest.approx((10 * d_hat, 0.01 * kappa, 5 * d_hat))
    x = torch.tensor([[0.0, 0.0, 0.05]], dtype=F64)
    assert float(wide.energy(x)) == pytest.approx(float(barrier(torch.tensor([0.05], dtype=F64), 10 * d_hat, 0.01 * kappa)))


def _sampled_clearance(x, triangles, colliders, offset, n=12):
    """A second measure of the surface's clearance, independent of the closest-point code: the least signed distance
    from the colliders (grown by ``offset``, the half thickness) of points sampled on every triangle, a barycentric
    grid of n + 1 points to an edge, in closed form per shape (plane, ball)."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    w = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], -1) / n  # (S, 3)
    pts = np.einsum("sk,tkd->tsd", w, np.asarray(x)[np.asarray(triangles)]).reshape(-1, 3)
    least = np.inf
    for q in colliders:
        if q["type"] == "half_space":
            nrm = np.asarray(q["normal"], dtype=float) / np.linalg.norm(q["normal"])
            d = (pts - np.asarray(q["point"])) @ nrm
        else:
            d = np.linalg.norm(pts - np.asarray(q["centre"]), axis=1) - q["radius"]
        least = min(least, float(d.min()) - offset)
    return least


def _free_cloth_frames(arrays, material, dt, contact, frames, tolerance):
    """Step a free shell against ``contact`` from rest for ``frames`` frames; every frame's gradient of the
    potential (barrier and lagged friction included) by autograd of the PyTorch energies is within the
    solver's tolerance and no point of the surface is inside a collider, by the barrier's closest points and by
    points sampled on the triangles.  Yields (x, nearest approach of the surface, d_hat) per frame."""
    from latentsim.scene import build_potential
    from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

    pot = build_potential("shell", arrays, material, dt, [0, -9.81, 0], free_only=True, contact=contact)
    check = build_potential("shell", arrays, material, dt, [0, -9.81, 0], contact=contact)
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=tolerance))
    x2 = x1 = np.asarray(arrays["rest_positions"], dtype=np.float64).copy()
    for _ in range(frames):
        x, _ = solver.step(x1, x2, np.zeros((0, 3)))
        xt = torch.as_tensor(x).requires_grad_(True)
        (g,) = torch.autograd.grad(check(xt, torch.as_tensor(x1), torch.as_tensor(x2), penalty=False), xt)
        assert float(g.norm()) <= 1.5 * tolerance * solver.f_ref
        nearest = float(pot.contact.clearance(torch.as_tensor(x)))
        assert nearest > 0 and _sampled_clearance(x, arrays["triangles"], contact["colliders"], 0.5 * material["thickness"]) > 0
        yield x, nearest, pot.contact.d_hat
        x2, x1 = x1, x


@pytest.mark.parametrize("shape", ["half_space", "sphere"])
def test_a_cloth_dropped_on_a_collider_never_enters_it_and_every_frame_solves_its_equations_of_motion(shape):
    """Full space: a free cloth falls onto a half-space (and comes to rest on it, within d_hat) or onto a
    sphere (and slides off it); in every frame no point of the surface is inside, and the gradient of the incremental
    potential with the barrier, by autograd of the PyTorch energies, is within the solver's tolerance."""
    from latentsim.mesh import cloth_grid

    X, tris = cloth_grid(4, 4, 0.3, 0.3, plane="xz")
    X = np.asarray(X, dtype=np.float64)
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.zeros(0, dtype=np.int64)}
    material = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}
    colliders = {"half_space": {"type": "half_space", "point": [0, -0.05, 0], "normal": [0, 1, 0]},
                 "sphere": {"type": "sphere", "centre": [0.05, -0.12, 0.02], "radius": 0.1}}  # fmt: skip
    frames = list(_free_cloth_frames(arrays, material, 1 / 60, {"colliders": [colliders[shape]]}, 90, 1e-6))
    nearest, d_hat = [d for _, d, _ in frames], frames[0][2]
    assert min(nearest) < d_hat  # it touched, and never entered
    x1, x2 = frames[-1][0], frames[-2][0]
    if shape == "half_space":  # at rest on the plane, inside the barrier's reach
        assert 0 < nearest[-1] < d_hat and np.abs(x1 - x2).max() * 60 < 1e-3
    else:  # slid off: falling below the sphere's centre
        assert x1[:, 1].max() < -0.12


@pytest.mark.parametrize("attached", [False, True])
def test_the_simulation_stage_with_a_collider_and_the_independent_frame_check(tmp_path, attached):
    """A pinned cloth swung onto a ball through the simulation stage: the file records the resolved
    contact block and each frame's nearest approach; the independent check (autograd of the rebuilt
    potential, barrier included) finds every frame at the tolerance and no vertex inside.  Attached, the
    ball rides with the held corner (three vertices) as the program swings and turns it, and the cloth
    drapes on it all the way."""
    import importlib.util
    from pathlib import Path

    import h5py

    import latentsim.io as lio
    from latentsim.mesh import cloth_grid
    from latentsim.stages.simulate import simulate_scene

    X, tris = cloth_grid(5, 5, 0.2, 0.2, plane="xy")
    mesh_h5 = tmp_path / "mesh.h5"
    with lio.atomic_h5(mesh_h5) as f:
        f.attrs["model"] = "shell"
        held = np.array([29, 34, 35] if attached else [30, 35])
        for k, v in {"rest_positions": np.asarray(X), "triangles": np.asarray(tris), "dirichlet": held}.items():
            lio.write_dataset(f, k, v)
    ball = {"type": "sphere", "centre": [0.0, -0.03, 0.05], "radius": 0.035}
    segments = [dict(start=0, velocity=[0, 0, 0.2])]
    if attached:  # behind the cloth, pushing it as the held corner moves forward, then turning with it about the vertical
        ball = {"type": "sphere", "centre": [0.02, 0.0, -0.04], "radius": 0.035, "attached": True}
        segments = [dict(start=0, velocity=[0, 0, 0.2]), dict(start=15, angular_velocity=[0, 1.0, 0])]
    cfg = dict(model="shell", material={"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}, dt=1 / 30,
               gravity=[0, -9.81, 0], newton=dict(tolerance=1e-6), contact={"colliders": [ball]},
               sequences=[dict(name="s", split="train", frames=30, segments=segments)])  # fmt: skip
    out = tmp_path / "trajectories.h5"
    simulate_scene("contact", mesh_h5, cfg, out)
    spec = importlib.util.spec_from_file_location("check_frames", Path(__file__).resolve().parents[2] / "benchmarks" / "check_frames.py")
    check_frames = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check_frames)
    report = check_frames.check(out)
    with h5py.File(out) as f:
        near = f["sequences/s/min_contact_distance"][()]
        d_hat = float(__import__("json").loads(f.attrs["contact"])["d_hat"])
    assert report["frames"] == 29 and report["worst"] <= 1.0
    assert 0 < report["nearest"] == pytest.approx(near.min()) and near.min() < d_hat
    if not attached:  # the two held corners do not fix a pose for a collider attached to them: the stage says so
        cfg["contact"]["colliders"][0]["attached"] = True
        with pytest.raises(RuntimeError, match=r"scene 'contact': contact.colliders: .*three of them not on one line \(2 prescribed\)"):
            simulate_scene("contact", mesh_h5, cfg, tmp_path / "other.h5")
        assert not (tmp_path / "other.h5").exists()


def test_a_solver_whose_elastic_terms_miss_some_vertices_still_assembles_every_vertexs_barrier():
    """A reduced solver's cubature keeps a few elements: the barrier's per-vertex Hessian blocks must
    still have their places in the sparse pattern, and gradient and Hessian match autograd."""
    import dataclasses

    from latentsim.mesh import cloth_grid
    from latentsim.scene import build_potential
    from latentsim.solve.implicit_euler import ImplicitEuler

    X, tris = cloth_grid(3, 3, 0.3, 0.3, plane="xz")
    X = np.asarray(X, dtype=np.float64)
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.zeros(0, dtype=np.int64)}
    material = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}
    contact = {"colliders": [{"type": "half_space", "point": [0, -0.001, 0], "normal": [0, 1, 0]}], "d_hat": 0.01}
    pot = build_potential("shell", arrays, material, 1 / 60, [0, -9.81, 0], contact=contact)
    first = [t.weighted_subset(torch.arange(2), torch.ones(2, dtype=F64)) for t in pot.terms]  # two elements of each term
    sub = dataclasses.replace(pot, terms=first)
    touched = np.unique(np.concatenate([t.stencils.numpy().ravel() for t in first]))
    assert len(touched) < len(X)  # some vertices belong to no element left
    solver = ImplicitEuler(sub)
    x = X + np.array([0.0, 0.002, 0.0]) * np.random.default_rng(0).random((len(X), 1))  # inside the barrier's reach
    assert float(pot.contact.energy(torch.as_tensor(x))) > 0
    grad, U = solver.gradient_hessian(x, X, X, project=False)
    U = U.tocsr().toarray()
    H = U + U.T - np.diag(np.diag(U))
    xt = torch.as_tensor(x).reshape(-1)
    f = lambda v: sub(v.reshape(-1, 3), torch.as_tensor(X), torch.as_tensor(X), penalty=False)
    ga = torch.func.grad(f)(xt).numpy()
    Ha = torch.autograd.functional.hessian(f, xt).numpy()
    assert np.allclose(grad, ga, rtol=1e-7, atol=1e-9 * np.abs(ga).max())
    assert np.allclose(H, Ha, rtol=1e-6, atol=1e-8 * np.abs(Ha).max())


def _free_block_mesh(tmp_path, lift=0.0):
    """A 5 cm tet block (3 x 3 x 3 cells) with no Dirichlet vertex, as the mesh stage writes it."""
    import latentsim.io as lio
    from latentsim.mesh import beam_tets
    from latentsim.mesh.surface import surface_of

    X, tets = beam_tets(3, 3, 3, 0.05, 0.05, 0.05)
    X = np.asarray(X, dtype=np.float64) + [0.0, lift, 0.0]
    mesh_h5 = tmp_path / "mesh.h5"
    with lio.atomic_h5(mesh_h5) as f:
        f.attrs["model"] = "tets"
        for k, v in {"rest_positions": X, "tets": np.asarray(tets), "surface": surface_of(np.asarray(tets)),
                     "dirichlet": np.zeros(0, dtype=np.int64)}.items():  # fmt: skip
            lio.write_dataset(f, k, v)
    return mesh_h5, X


def _check_frames_module():
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("check_frames", Path(__file__).resolve().parents[2] / "benchmarks" / "check_frames.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_free_body_thrown_falls_as_implicit_euler_says_and_lands_on_the_ground(tmp_path):
    """A free block (dirichlet type free) thrown up with a spin through the simulation stage.  Before it
    touches the ground its centre of mass follows implicit Euler's free fall from the initial velocity
    exactly, c_t = c_0 + t dt v + t (t + 1) / 2 dt^2 g (internal forces sum to zero); it turns; it lands
    and no vertex is ever inside; the independent frame check, which starts frame 1 from the recorded
    initial velocity, finds every frame at the tolerance (and would not from rest)."""
    import h5py

    from latentsim.stages.simulate import simulate_scene

    mesh_h5, X = _free_block_mesh(tmp_path)
    dt, v0, w0 = 1 / 30, np.array([0.1, 0.5, 0.0]), np.array([0.0, 0.0, 4.0])
    cfg = dict(model="tets", material={"youngs_modulus": 2e5, "poisson_ratio": 0.3, "density": 1000.0}, dt=dt,
               gravity=[0, -9.81, 0], newton=dict(tolerance=1e-6),
               contact={"colliders": [{"type": "half_space", "point": [0.0, -0.2, 0.0], "normal": [0.0, 1.0, 0.0]}]},
               sequences=[dict(name="toss", split="train", frames=40, initial_velocity=v0.tolist(), initial_angular_velocity=w0.tolist())])  # fmt: skip
    out = tmp_path / "trajectories.h5"
    simulate_scene("free", mesh_h5, cfg, out)
    with h5py.File(out) as f:
        x, m = f["sequences/toss/positions"][()], f["masses"][()]
        near = f["sequences/toss/min_contact_distance"][()]
        assert f["sequences/toss"].attrs["initial_velocity"].tolist() == v0.tolist() + w0.tolist()
        d_hat = float(__import__("json").loads(f.attrs["contact"])["d_hat"])
    c = (m[:, None] * x).sum(1) / m.sum()
    free = np.arange(np.argmax(near <= d_hat))  # the frames before the barrier's first touch
    assert len(free) >= 6
    t = free[:, None]
    np.testing.assert_allclose(c[free], c[0] + t * dt * v0 + t * (t + 1) / 2 * dt**2 * np.array([0, -9.81, 0]), atol=1e-6)
    # the spin: the block's x edge has turned by about w dt t (less what the step's dissipation takes)
    e = x[free[-1], np.argmax(X[:, 0])] - x[free[-1], np.argmin(X[:, 0])]
    angle = np.arctan2(e[1], e[0]) - np.arctan2(*(X[np.argmax(X[:, 0])] - X[np.argmin(X[:, 0])])[[1, 0]])
    assert 0.8 * 4.0 * dt * free[-1] < angle < 1.05 * 4.0 * dt * free[-1]
    assert near.min() > 0 and near.min() < d_hat and x[-1, :, 1].min() < -0.2 + d_hat  # landed, never inside
    report = _check_frames_module().check(out)
    assert report["frames"] == 39 and report["worst"] <= 1.0
    with h5py.File(out, "r+") as f:  # the same frames judged as if the block had started at rest
        del f["sequences/toss"].attrs["initial_velocity"]
    assert _check_frames_module().check(out)["worst"] > 10.0


# --- colliders attached to the prescribed vertices ------------------------------------------------


def _rigid(seed):
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
    q = q * torch.sign(torch.linalg.det(q))  # a proper rotation
    return q, torch.randn(3, generator=g, dtype=F64)


REST_D = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1], [0.1, 0.02, 0.1]])


def test_rigid_pose_recovers_a_rigid_motion_of_the_prescribed_vertices_batched():
    from latentsim.physics.colliders import rigid_pose

    motions = [_rigid(s) for s in range(4)]
    c0 = REST_D.mean(0)
    targets = torch.stack([(torch.as_tensor(REST_D - c0) @ R.T) + t for R, t in motions])
    R, c = rigid_pose(REST_D, targets)
    for k, (Rk, tk) in enumerate(motions):
        assert torch.allclose(R[k], Rk, atol=1e-12) and torch.allclose(c[k], tk, atol=1e-12)
    # a planar set (the cantilever's clamped face) determines the pose as well
    flat = REST_D[:3]
    Rf, cf = rigid_pose(flat, (torch.as_tensor(flat - flat.mean(0)) @ motions[0][0].T) + motions[0][1])
    assert torch.allclose(Rf, motions[0][0], atol=1e-12)


@pytest.mark.parametrize("name", COLLIDERS)
def test_an_attached_collider_is_its_rest_shape_carried_by_the_prescribed_vertices_motion(name):
    """Rigid-motion invariance: with the prescribed vertices carried by (R, t), the attached collider's
    distance of x is the rest shape's distance of x carried back, and the moved shape's distance of x;
    the barrier's energy with the frame's targets equals the posed (static) barrier's, batched over frames."""
    col = COLLIDERS[name]
    x_rest = _points_near(col, n=60)
    term = ContactBarrier(len(x_rest), [col], d_hat=0.05, kappa=2.0, attached=[True], rest_dirichlet=REST_D)
    assert term.moving and not ContactBarrier(1, [col], 0.05, 2.0).moving
    c0 = torch.as_tensor(REST_D.mean(0))
    xs, targets = [], []
    for seed in range(3):
        R, t = _rigid(seed)
        xs.append((x_rest - c0) @ R.T + t)
        targets.append((torch.as_tensor(REST_D) - c0) @ R.T + t)
        moved = col.moved(R.numpy(), c0.numpy(), t.numpy())
        assert torch.allclose(moved.distance(xs[-1]), col.distance(x_rest), atol=1e-12)
        posed = term.posed(targets[-1].numpy())
        assert not posed.moving and torch.allclose(posed.energy(xs[-1]), term.energy(x_rest, Frame(torch.as_tensor(REST_D))), rtol=1e-10)
    X, XD = torch.stack(xs), torch.stack(targets)
    assert torch.allclose(term.distances(X, XD), col.distance(x_rest).expand(3, -1), atol=1e-12)
    assert torch.allclose(term.energy(X, Frame(XD)), term.energy(x_rest[None], Frame(torch.as_tensor(REST_D)[None])).expand(3), rtol=1e-10)
    with pytest.raises(ValueError, match="Dirichlet targets"):
        term.energy(X)


def test_an_attached_collider_needs_a_pose_the_prescribed_vertices_determine():
    line = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]])
    for rest in (line, REST_D[:2], None):
        with pytest.raises(ValueError, match="three of them not on one line"):
            ContactBarrier(5, [COLLIDERS["sphere"]], 0.05, 2.0, attached=[True], rest_dirichlet=rest)
    with pytest.raises(ValueError, match="2 attached flags for 1 colliders"):
        ContactBarrier(5, [COLLIDERS["sphere"]], 0.05, 2.0, attached=[True, False], rest_dirichlet=REST_D)


def test_first_impact_over_a_frame_follows_the_collider_as_it_moves():
    """A point carried with the collider never meets it; a still point that a translating sphere sweeps
    over is met at the fraction of the step where it lies on the sphere's surface."""
    step = lambda before, after: Frame(targets=after, targets_prev=before)
    ball = Sphere((0.0, 0.0, 0.0), 0.1)
    term = ContactBarrier(1, [ball], 0.01, 1.0, attached=[True], rest_dirichlet=REST_D + [0.0, 0.5, 0.0])
    shift = np.array([0.4, 0.0, 0.0])
    carried = np.array([[0.15, 0.0, 0.0]])
    assert term.first_impact(carried, shift[None], step(REST_D + [0.0, 0.5, 0.0], REST_D + [0.4, 0.5, 0.0])) == np.inf
    still = np.array([[0.3, 0.0, 0.0]])
    t = term.first_impact(still, np.zeros((1, 3)), step(REST_D + [0.0, 0.5, 0.0], REST_D + [0.4, 0.5, 0.0]))
    assert t == pytest.approx(0.5)  # the ball's surface reaches x = 0.3 when its centre is at 0.2
    # a static collider beside it is still tested along the straight step
    both = ContactBarrier(1, [ball, HalfSpace((0, -0.1, 0), (0, 1, 0))], 0.01, 1.0, attached=[True, False], rest_dirichlet=REST_D)
    assert both.first_impact(still, [[0.0, -0.4, 0.0]], step(REST_D, REST_D)) == pytest.approx(0.25)


def test_a_cloth_carried_by_a_tray_that_moves_with_its_held_corner():
    """Full space with an attached collider: a cloth held at one corner (three vertices) over a plane attached
    to them; the program lifts the corner and tilts it.  The plane lifts the cloth with it: in every frame no
    vertex is below the plane where the program carries it, every frame solves its equations of motion by
    autograd of the potential with that frame's targets, and at the end the whole cloth is far above the
    plane's rest height, where a static plane would have held it."""
    from latentsim.mesh import cloth_grid
    from latentsim.scene import bc_parameters, build_potential, dirichlet_trajectory
    from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

    X, tris = cloth_grid(4, 4, 0.3, 0.3, plane="xz")
    X = np.asarray(X, dtype=np.float64)
    corner = int(np.argmin(X[:, 0] + X[:, 2]))
    near = np.argsort(np.linalg.norm(X - X[corner], axis=1))[:3]  # the corner and its two neighbours
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.sort(near)}
    material = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}
    tray = {"type": "half_space", "point": [0.0, float(X[:, 1].min()) - 0.02, 0.0], "normal": [0, 1, 0], "attached": True}
    contact = {"colliders": [tray]}
    dt = 1 / 60
    pot = build_potential("shell", arrays, material, dt, [0, -9.81, 0], free_only=True, contact=contact)
    check = build_potential("shell", arrays, material, dt, [0, -9.81, 0], contact=contact)
    assert pot.contact.moving
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-6))
    tol = 1e-6 * solver.f_ref
    frames = 80
    seq = {"segments": [{"start": 20, "velocity": [0, 0.5, 0]}, {"start": 50, "angular_velocity": [0.8, 0, 0]}, {"start": 65}]}
    XD = dirichlet_trajectory(X[arrays["dirichlet"]], bc_parameters(seq, frames), dt)
    free = np.setdiff1d(np.arange(len(X)), arrays["dirichlet"])
    x2 = x1 = X.copy()
    nearest = []
    for t in range(1, frames):
        x, _ = solver.step(x1, x2, XD[t])
        xt = torch.as_tensor(x).requires_grad_(True)
        (g,) = torch.autograd.grad(check(xt, torch.as_tensor(x1), torch.as_tensor(x2), targets=torch.as_tensor(XD[t]), penalty=False), xt)
        assert float(g[free].norm()) <= 1.5 * tol
        nearest.append(float(pot.contact.distances(torch.as_tensor(x), XD[t]).min()))
        x2, x1 = x1, x
    assert min(nearest) > 0 and min(nearest) < pot.contact.d_hat  # it rested on the tray, and never went through
    # the corner rose 0.25 m (then tilted the tray by 0.2 rad): the whole cloth rose with the tray, where a static
    # tray would have held the cloth hanging from the corner at the tray's rest height
    assert x1[:, 1].min() > tray["point"][1] + 0.15


def test_attached_collider_entries_are_placed_per_frame_and_penetration_is_measured_there():
    """What the report draws and measures: an attached entry carried by the frame's prescribed positions
    (a point moved, a normal turned), a static entry as it is; a rollout that keeps its place relative
    to a moving ball never enters it, one that stays where the ball arrives does."""
    from latentsim.scene import contact_barrier, posed_collider_entries
    from latentsim.report.metrics import penetration

    R, t = _rigid(5)
    c0 = REST_D.mean(0)
    targets = (REST_D - c0) @ R.numpy().T + t.numpy()
    entries = [{"type": "sphere", "centre": [0.3, 0.0, 0.0], "radius": 0.1, "attached": True},
               {"type": "half_space", "point": [0, -1.0, 0], "normal": [0, 1, 0], "attached": True},
               {"type": "sphere", "centre": [2.0, 0.0, 0.0], "radius": 0.1}]  # fmt: skip
    ball, plane, still = posed_collider_entries(entries, REST_D, targets)
    assert np.allclose(ball["centre"], R.numpy() @ (np.array([0.3, 0.0, 0.0]) - c0) + t.numpy())
    assert np.allclose(plane["normal"], R.numpy() @ [0, 1, 0]) and still == entries[2]
    assert posed_collider_entries(entries[2:], REST_D, targets) == entries[2:]
    # a ball carried 0.5 m along x over 11 frames by the prescribed vertices (indices 0-3 of 5 vertices)
    rest = np.vstack([REST_D, [[0.3, 0.15, 0.0]]])  # the fifth, 5 cm above the ball
    contact = contact_barrier({"colliders": entries[:1], "d_hat": 0.01, "kappa": 1.0}, 5, rest, [0, 1, 2, 3], 1 / 30)
    shifts = np.linspace(0, 0.5, 11)[:, None, None] * [1.0, 0.0, 0.0]
    XD = REST_D[None] + shifts
    riding = rest[None] + shifts
    staying = riding.copy()
    staying[:, 4] = rest[4] - [0.0, 0.1, 0.0] + [0.25, 0.0, 0.0]  # 5 cm above the ball's centre when it reaches x = 0.55
    assert penetration(contact, riding, 1.0, -1, XD) == {"max_penetration": 0.0, "penetrating_frames": 0}
    out = penetration(contact, staying, 1.0, -1, XD)
    assert out["max_penetration"] == pytest.approx(0.05) and out["penetrating_frames"] > 0


# --- lagged friction ------------------------------------------------------------------------------


def test_friction_potential_is_c1_at_the_slip_and_its_derivative_rises_from_zero_to_one():
    from latentsim.physics.contact import friction_f0, friction_f1_over_s

    eps = 1e-3
    s = torch.tensor([0.0, 0.3e-3, eps * (1 - 1e-9), eps * (1 + 1e-9), 5e-3], dtype=F64, requires_grad=True)
    f0 = friction_f0(s, eps)
    (f1,) = torch.autograd.grad(f0.sum(), s)
    assert f1[0] == 0 and f1[2] == pytest.approx(1.0) and f1[3] == pytest.approx(1.0) and f1[4] == 1.0
    f0 = f0.detach()
    assert float(f0[2]) == pytest.approx(float(f0[3]))  # continuous at eps, and equal to s above
    assert float(f0[4]) == pytest.approx(5e-3)
    assert torch.allclose(friction_f1_over_s(s.detach()[1:], eps) * s.detach()[1:], f1[1:], rtol=1e-9)


@pytest.mark.parametrize("name", COLLIDERS)
def test_friction_gradient_and_hessian_against_the_oracle_finite_differences_and_the_lagged_energy(name):
    """A solver step's barrier with friction (anchored at x_prev, slips below and above the static slip):
    closed-form per-vertex gradient and Hessian against autograd and central differences, PSD without
    projection; its energy equals the potential's path, which lags the friction from x_prev itself."""
    c = COLLIDERS[name]
    x_prev = _points_near(c)
    slide = torch.randn(x_prev.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    n, _ = c.distance_derivatives(x_prev)
    slide = slide - (slide * n).sum(-1, keepdim=True) * n  # along the surface, with a little off it
    slide = slide / slide.norm(dim=-1, keepdim=True) + 0.1 * n
    x = x_prev + slide * torch.linspace(1e-5, 1e-2, len(x_prev), dtype=F64)[:, None]  # slips below and above 1e-3
    term = ContactBarrier(len(x), [c], d_hat=0.05, kappa=2.0, friction=0.4, slip=1e-3)
    step = term.at(Frame(np.zeros((0, 3)), x_prev.numpy(), targets_prev=np.zeros((0, 3))))
    assert float(step.energy(x)) > float(ContactBarrier(len(x), [c], d_hat=0.05, kappa=2.0).energy(x))  # friction adds
    assert float(step.energy(x)) == pytest.approx(float(term.energy(x, Frame(x_prev=x_prev))), rel=1e-12)
    xe = step.gather(x)
    _closed_form_against_oracle_and_differences(step, x, rtol=1e-6)
    # friction alone is PSD in closed form (the barrier's part needs the projection for curved colliders)
    flat = ContactBarrier(len(x), [HalfSpace((0, -0.5, 0), (0, 1, 0))], d_hat=0.05, kappa=2.0, friction=0.4, slip=1e-3)
    _, Hf = flat.at(Frame(np.zeros((0, 3)), x_prev.numpy(), targets_prev=np.zeros((0, 3)))).local_gradient_hessian(xe, project=False)
    assert torch.linalg.eigvalsh(Hf).min() > -1e-9


def test_friction_with_an_attached_collider_counts_the_slip_relative_to_it():
    """A vertex resting on an attached plane and carried with it has no slip (no friction energy), one left
    behind as the plane moves has the plane's displacement as its slip."""
    plane = HalfSpace((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    term = ContactBarrier(1, [plane], d_hat=0.01, kappa=1.0, attached=[True], rest_dirichlet=REST_D, friction=0.5, slip=1e-4)
    x_prev = torch.tensor([[0.3, 0.004, 0.0]], dtype=F64)
    shift = torch.tensor([0.02, 0.0, 0.0], dtype=F64)
    D0, D1 = torch.as_tensor(REST_D), torch.as_tensor(REST_D) + shift
    no_friction = ContactBarrier(1, [plane], d_hat=0.01, kappa=1.0, attached=[True], rest_dirichlet=REST_D)
    carried, left = x_prev + shift, x_prev
    base = float(no_friction.energy(carried, Frame(D1)))
    frame = Frame(D1, x_prev, targets_prev=D0)
    lam = -float(barrier_derivatives(torch.tensor([0.004], dtype=F64), 0.01, 1.0)[0])
    assert float(term.energy(carried, frame)) == pytest.approx(base + 0.5 * lam * 1e-4 / 3, rel=1e-9)
    assert float(term.energy(left, frame)) == pytest.approx(base + 0.5 * lam * 0.02, rel=1e-9)
    step = term.at(Frame(D1.numpy(), x_prev.numpy(), targets_prev=REST_D))
    assert float(step.energy(left)) == pytest.approx(float(term.energy(left, frame)), rel=1e-12)


@pytest.mark.parametrize("mu", [0.0, 0.2, 0.8])
def test_a_cloth_on_an_incline_slides_as_coulomb_friction_says_or_sticks(mu):
    """Analytic benchmark: a free cloth lying on a plane inclined at tan(theta) = 0.5 accelerates down it at
    g (sin theta - mu cos theta) when mu < tan(theta) (frictionless: g sin theta) and stays put when mu > tan
    theta (creeping at most the static slip's speed); every frame outside the plane and at the tolerance by
    autograd of the potential, whose friction lags from the previous frame."""
    from latentsim.mesh import cloth_grid

    theta = math.atan(0.5)
    down = np.array([math.cos(theta), -math.sin(theta), 0.0])  # along the slope, downwards
    normal = np.array([math.sin(theta), math.cos(theta), 0.0])
    X, tris = cloth_grid(3, 3, 0.1, 0.1, plane="xz")
    X = np.asarray(X, dtype=np.float64)
    X = X[:, 0:1] * down + X[:, 2:3] * np.array([0.0, 0.0, 1.0]) + (5e-4 + 2e-4) * normal  # on the plane (its surface half its 1 mm thickness off), inside d_hat
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.zeros(0, dtype=np.int64)}
    material = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}
    contact = {"colliders": [{"type": "half_space", "point": [0, 0, 0], "normal": normal.tolist()}], "d_hat": 5e-4}
    if mu:
        contact["friction"] = mu
    dt = 1 / 100
    along = [float(x.mean(0) @ down) for x, _, _ in _free_cloth_frames(arrays, material, dt, contact, 60, 1e-8)]
    s = np.asarray(along) - float(X.mean(0) @ down)
    accel = (s[-1] - 2 * s[-21] + s[-41]) / (20 * dt) ** 2  # over the last 0.4 s (a constant acceleration's second difference)
    want = 9.81 * (math.sin(theta) - mu * math.cos(theta))
    if want > 0:
        assert accel == pytest.approx(want, rel=0.03)
    else:  # it sticks: at most the static slip's creep, 1e-3 m/s, in 0.6 s
        assert abs(s[-1]) < 0.6 * 1e-3
