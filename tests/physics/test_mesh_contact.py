"""A static triangle mesh as a collider (``physics.mesh_contact``): every vertex, edge and triangle of a surface held
off every face, edge and vertex of the mesh.

The Hessians in closed form against autograd, each term's derivatives against the autograd oracle of
:mod:`latentsim.physics.base`, its candidates missing no pair (the energy that of every pair), the IPC Toolkit as an
independent implementation of the distances (``ipctk``, its squared distances of each pair type), the time of impact
conservative, and the physics: a cloth dropped on a coarse ball mesh rests on it, no point of its surface within its
half thickness of the mesh on any frame (by the toolkit's distances and intersection test)."""

import math

import numpy as np
import pytest
import torch

from latentsim.physics.barrier import barrier
from latentsim.physics.base import autograd_gradient_hessian
from latentsim.physics.contact import ContactBarrier
from latentsim.physics.mesh_contact import TriangleMesh, mesh_barriers, unique_edges
from latentsim.physics.primitives import core_distance, distance_hessian, vertex_hessian

F64 = torch.float64


@pytest.fixture
def ball(icosphere):
    """``ball(radius, centre, levels=1)``: an icosphere (the tests' ``icosphere`` fixture) of ``radius`` about ``centre``."""

    def make(radius: float, centre, levels: int = 1):
        V, F = icosphere(levels)
        return np.asarray(centre, float) + radius * V, F

    return make


@pytest.mark.parametrize("m", [1, 2, 3])
def test_the_hessian_of_a_vertex_distance_from_a_point_segment_or_triangle_is_autograds(m):
    """In each region of the core (its corners, its edges, its face)."""
    gen = torch.Generator().manual_seed(5)
    core = torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.1, 0.0], [0.1, 0.5, 0.1]], dtype=F64)[:m]
    x = (torch.rand(300, 3, generator=gen, dtype=F64) - 0.5) * 1.6
    y = x.clone().requires_grad_(True)
    d = core_distance(core.expand(len(x), m, 3), y[:, None, :])
    (g,) = torch.autograd.grad(d.sum(), y)
    H = vertex_hessian(x, g, d.detach(), core.expand(len(x), m, 3))
    He = torch.stack([torch.autograd.functional.hessian(lambda f: core_distance(core[None], f[None, None, :])[0], xi) for xi in x])
    err = (H - He).abs().amax((1, 2)) / He.abs().amax((1, 2)).clamp_min(1e-3)
    assert float(err.max()) < 1e-9


def test_the_closed_form_hessian_takes_one_segment_per_primitive():
    gen = torch.Generator().manual_seed(6)
    axes = torch.rand(200, 2, 3, generator=gen, dtype=F64)
    xp = torch.rand(200, 2, 3, generator=gen, dtype=F64) + torch.tensor([0.3, 0.0, 0.0], dtype=F64)
    y = xp.clone().requires_grad_(True)
    d = core_distance(axes, y)
    (g,) = torch.autograd.grad(d.sum(), y)
    H = distance_hessian(xp, g, d.detach(), axes)
    one = torch.stack([distance_hessian(xp[i : i + 1], g[i : i + 1], d.detach()[i : i + 1], axes[i])[0] for i in range(len(xp))])
    assert torch.allclose(H, one, rtol=1e-12, atol=1e-12)
    He = torch.stack([torch.autograd.functional.hessian(lambda f: core_distance(axes[i], f.reshape(2, 3)), xp[i].reshape(-1)) for i in range(4)])
    assert torch.allclose(H[:4], He, rtol=1e-8, atol=1e-9)


def _cloth_over(ball, mesh_centre=(0.0, -0.05, 0.0), seed=0, n=5):
    """A small crumpled sheet of triangles just over an icosphere (some of its pairs within reach, most not)."""
    from latentsim.mesh import cloth_grid

    X, tris = cloth_grid(n, n, 0.1, 0.1, plane="xz")
    X = np.asarray(X, float)
    X[:, 1] += np.random.default_rng(seed).normal(0, 0.004, len(X))
    V, F = ball(0.05, mesh_centre)
    return torch.as_tensor(X), np.asarray(tris, np.int64), TriangleMesh(V, F, thickness=0.002)


def test_each_kind_of_pair_has_autograds_derivatives_and_its_candidates_miss_nothing(ball):
    x, tris, mesh = _cloth_over(ball)
    terms = mesh_barriers(mesh, tris, len(x), d_hat=0.01, kappa=1.0)
    assert [t.k for t in terms] == [1, 2, 3]
    for t in terms:
        xe = t.gather(x)
        e = t.local_energy(xe)  # every pair, in PyTorch alone
        assert int((e > 0).sum()) >= 3 and int((e == 0).sum()) >= 3, t.k
        assert torch.allclose(t.energy(x), e.sum(), rtol=1e-13, atol=0)  # the candidates: the same energy
        for project in (False, True):
            g, H = t.local_gradient_hessian(xe, project=project)
            ge, He = autograd_gradient_hessian(t, xe, project=project)
            assert torch.allclose(g, ge, rtol=1e-10, atol=1e-13 * float(ge.abs().max()))
            assert torch.allclose(H, He, rtol=1e-8, atol=1e-11 * float(He.abs().max())), (t.k, project)
    # every pair nearer than the reach is a candidate, at reaches from a hair to beyond the cells
    for t in terms:
        ye = t.gather(x).numpy()
        M = len(mesh.cores(t.k))
        I, J = np.repeat(np.arange(len(ye)), M), np.tile(np.arange(M), len(ye))
        d = mesh.distance(torch.as_tensor(ye[I]), J).numpy() + mesh.thickness
        for reach in (1e-4, 3e-3, 0.01, 0.05):
            i, j = mesh.candidates(ye, reach)
            within = set(zip(I[d < reach], J[d < reach]))
            assert within <= set(zip(i, j)), (t.k, reach)
        assert len(within) > 10  # (at the largest reach)
    # batched states, the sum of each state's own
    xs = torch.stack([x, x + 0.003])
    for t in terms:
        assert torch.allclose(t.energy(xs), torch.stack([t.energy(x), t.energy(x + 0.003)]), rtol=1e-14, atol=0)


def test_the_mesh_grids_pairs_are_the_brute_forces(ball):
    """Each kind's candidates are exactly the pairs nearer than the reach by the compiled distances (within its slack),
    i ascending and each i's j ascending, at reaches from a hair to beyond the mesh (every primitive scanned), with a
    vertex 1e7 m away (its edges and triangles span the whole mesh) and one not finite (no pairs), and at a
    thousandfold scale."""
    from latentsim.physics.kernels.distances import SLACK

    for scale in (1.0, 1000.0):
        x, tris, mesh = _cloth_over(ball, seed=3)
        x = x.clone()
        x[0] = torch.as_tensor([1e7, 0.0, 0.0])
        x[1, 1] = float("nan")
        x, mesh = x * scale, TriangleMesh(mesh.vertices * scale, mesh.faces)
        for t in mesh_barriers(mesh, tris, len(x), d_hat=0.01, kappa=1.0):
            ye = t.gather(x).numpy()
            M = len(mesh.cores(t.k))
            I, J = np.repeat(np.arange(len(ye)), M), np.tile(np.arange(M), len(ye))
            d = mesh.distance(torch.as_tensor(ye[I]), J).numpy()
            for reach in (1e-4 * scale, 3e-3 * scale, 0.02 * scale, 0.5 * scale):
                i, j = mesh.candidates(ye, reach)
                assert np.all(np.diff(i * M + j) > 0), (scale, t.k, reach)  # ascending, each pair once
                got = set(zip(i.tolist(), j.tolist()))
                assert set(zip(I[d < reach].tolist(), J[d < reach].tolist())) <= got, (scale, t.k, reach)
                near = d < reach * (1 + 10 * SLACK)
                assert got <= set(zip(I[near].tolist(), J[near].tolist())), (scale, t.k, reach)
                stencils = t.stencils.numpy()
                assert not np.isin(stencils[i], [1]).any()  # the vertex not finite pairs with nothing
            assert len(got) > 10  # (at the largest reach)


def test_compiled_selection_leaves_energy_gradient_and_distances_unchanged(ball, monkeypatch):
    """The pairs within reach are selected by a grid and compiled distances (``kernels.distances.grid_within``): over
    many states of a sheet over the ball, each kind's energy, gradient, least distance, and the solver's per-stencil
    gradient and Hessian equal, to the bit, those with every pair of the surface and the mesh measured in PyTorch."""
    from latentsim.physics import mesh_contact

    x, tris, mesh = _cloth_over(ball, seed=4)
    xs = torch.stack([x + 0.002 * k * torch.as_tensor([0.3, -1.0, 0.2], dtype=F64) for k in range(8)])

    def measured():
        out = []
        for t in mesh_barriers(mesh, tris, len(x), d_hat=0.01, kappa=1.0, extend_below=0.001):
            y = xs.clone().requires_grad_(True)
            e = t.energy(y)
            (g,) = torch.autograd.grad(e.sum(), y)
            out += [e.detach(), g, t.distances(xs, t.d_hat), *t.local_gradient_hessian(t.gather(xs[3]))]
        return out

    selected = measured()
    def every_pair(ye, grid, reach):
        return np.repeat(np.arange(len(ye)), len(grid.cores)), np.tile(np.arange(len(grid.cores)), len(ye))

    monkeypatch.setattr(mesh_contact, "grid_within", every_pair)
    everything = measured()
    assert all(torch.equal(a, b) for a, b in zip(selected, everything))
    assert all(int((e > 0).sum()) >= 4 for e in selected[::5]), [int((e > 0).sum()) for e in selected[::5]]


def test_the_pairs_energy_is_the_ipc_toolkits_distances_barrier(ball):
    """ipctk's squared distance of each vertex-face, edge-edge and face-vertex pair, brute force over all pairs."""
    ipctk = pytest.importorskip("ipctk")
    x, tris, mesh = _cloth_over(ball, seed=2)
    d_hat, kappa = 0.01, 1.0
    total = sum(float(t.energy(x)) for t in mesh_barriers(mesh, tris, len(x), d_hat, kappa))
    X, V = x.numpy(), mesh.vertices
    d2 = [ipctk.point_triangle_distance(X[v], *V[f]) for v in np.unique(tris) for f in mesh.faces]
    d2 += [ipctk.edge_edge_distance(*X[e], *V[o]) for e in unique_edges(tris) for o in mesh.edges]
    d2 += [ipctk.point_triangle_distance(V[v], *X[f]) for v in range(len(V)) for f in tris]
    d = torch.as_tensor(np.sqrt(np.asarray(d2))) - mesh.thickness
    oracle = float(barrier(d, d_hat, kappa).sum())
    assert oracle > 0 and math.isclose(total, oracle, rel_tol=1e-10)


def test_the_time_of_impact_stops_the_surface_at_its_thickness(ball):
    """A sheet pushed straight down into the mesh: stopped before any point comes within the thickness, and not long
    before (the toolkit's additive CCD stops at a fraction of the distance left)."""
    pytest.importorskip("ipctk")
    x, tris, mesh = _cloth_over(ball, mesh_centre=(0.013, -0.07, -0.007))
    lead = mesh_barriers(mesh, tris, len(x), 0.01, 1.0)[0]
    X = x.numpy()
    gap = min(float(t.distances(x, 1.0)) for t in mesh_barriers(mesh, tris, len(x), 0.01, 1.0))
    dx = np.tile([0.0, -0.05, 0.0], (len(X), 1))
    t = lead.first_impact(X, dx)
    assert 0 < t < 1
    after = min(float(u.distances(torch.as_tensor(X + t * dx), 1.0)) for u in mesh_barriers(mesh, tris, len(x), 0.01, 1.0))
    assert 0 < after < 0.5 * gap  # the surface (beyond the thickness) stopped outside, after closing half its gap
    assert lead.first_impact(X, -dx) == math.inf  # moving away
    assert mesh_barriers(mesh, tris, len(x), 0.01, 1.0)[1].first_impact(X, dx) == math.inf  # the vertices' term holds it


def test_a_cloth_dropped_on_a_ball_mesh_rests_on_it_with_no_point_within_its_half_thickness(ball):
    """The sheet held at its corners falls onto a coarse icosphere (80 faces, edges longer than the cloth's cells) under
    its middle: it reaches the mesh's barrier, and on no frame does any pair of the cloth's and the mesh's primitives come
    within the half thickness (the toolkit's distances, brute force) or cross (its intersection test); every step converges."""
    ipctk = pytest.importorskip("ipctk")
    from latentsim.mesh import cloth_grid
    from latentsim.scene import build_potential
    from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

    X, tris = cloth_grid(6, 6, 0.2, 0.2, plane="xz")
    X, tris = np.asarray(X, np.float64), np.asarray(tris, np.int64)
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.flatnonzero((np.abs(X[:, 0]) > 0.099) & (np.abs(X[:, 2]) > 0.099))}
    material = {"youngs_modulus": 1e4, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.002}
    V, F = ball(0.04, (0.01, -0.05, 0.005))
    mesh = TriangleMesh(V, F, thickness=0.001)
    pot = build_potential("shell", arrays, material, 1 / 30, [0, -9.81, 0], free_only=True, contact=None)
    d_hat = 0.002
    pot.contact = ContactBarrier(len(X), [], d_hat, kappa=100.0 * float(pot.masses.max()) * 9.81 / d_hat, primitives=tris, meshes=[mesh])
    assert [t.name for t in pot.contact.terms()] == ["contact_barrier"] + ["mesh_barrier"] * 3
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-6))
    n = len(X)
    cm = ipctk.CollisionMesh(np.asfortranarray(np.vstack([X, V])), np.asfortranarray(np.vstack([unique_edges(tris), mesh.edges + n]).astype(np.int32)),
                             np.asfortranarray(np.vstack([tris, F + n]).astype(np.int32)))  # fmt: skip
    cm.can_collide = ipctk.make_static_obstacle_filter(n)
    x2 = x1 = X.copy()
    nearest = []
    for _ in range(25):
        x, info = solver.step(x1, x2, X[arrays["dirichlet"]])
        assert info.gradient_norm <= 1e-6 * solver.f_ref  # converged, the mesh's barrier in the residual
        assert not ipctk.has_intersections(cm, np.asfortranarray(np.vstack([x, V])))
        d2 = [ipctk.point_triangle_distance(x[v], *V[f]) for v in range(n) for f in F]
        d2 += [ipctk.edge_edge_distance(*x[e], *V[o]) for e in unique_edges(tris) for o in mesh.edges]
        d2 += [ipctk.point_triangle_distance(V[v], *x[f]) for v in range(len(V)) for f in tris]
        nearest.append(math.sqrt(min(d2)))
        x2, x1 = x1, x
    assert min(nearest) > mesh.thickness  # never within the half thickness
    assert nearest[-1] < mesh.thickness + d_hat  # resting on the barrier
    assert x1[:, 1].min() < V[:, 1].max() - 0.005  # the cloth drapes over the ball (not held flat above it)


def test_inside_is_the_balls_inside_and_a_vertex_in_the_body_is_measured_by_its_depth(ball):
    V, F = ball(0.05, (0.01, 0.02, 0.03), levels=3)
    mesh = TriangleMesh(V, F, thickness=0.001)
    P = np.random.default_rng(3).uniform(-0.08, 0.08, (20000, 3)) + [0.01, 0.02, 0.03]
    r = np.linalg.norm(P - [0.01, 0.02, 0.03], axis=1)
    ins = mesh.inside(P)
    inner = 0.05 * np.cos(0.2)  # every point of the subdivided icosahedron lies between this and 0.05 from the centre
    assert ins[r < inner].all() and not ins[r > 0.05].any() and ins.sum() > 1000
    d = mesh.unsigned_distance(P[:500])
    assert np.all((d >= np.abs(r[:500] - 0.05) - 0.05 * (1 - np.cos(0.2)) - 1e-12) & (d <= np.abs(r[:500] - inner) + 0.05 * (1 - np.cos(0.2))))
    # a sheet with one vertex 2 cm inside the ball: the clearance is that depth (and the thickness); penetrations count it
    x, tris, _ = _cloth_over(ball, mesh_centre=(0.0, -0.08, 0.0))
    contact = ContactBarrier(len(x), [], 0.002, 1.0, primitives=tris, meshes=[mesh])
    x = x.clone()
    x[:, 1] += 0.1  # all well above the ball
    assert float(contact.clearance(x)) == pytest.approx(10 * 0.002)  # nothing within MESH_REACH d_hat: "that or more"
    x[12] = torch.tensor([0.01, 0.02, 0.03 + 0.03], dtype=F64)  # 2 cm inside the 5 cm ball
    depth = float(mesh.unsigned_distance(x[12:13].numpy())[0])
    assert 0.0195 < depth < 0.0201
    assert float(contact.clearance(x)) == pytest.approx(-depth - 0.001, rel=1e-12)
    count, deepest = contact.penetrations(x.numpy())[0]
    assert count >= 2 and deepest == pytest.approx(-depth - 0.001)  # the vertex, and its triangles through the surface
    assert float(contact.energy(x)) + sum(float(t.energy(x)) for t in contact.mesh_terms()) == math.inf


def test_the_simulation_stage_reads_a_mesh_collider_from_its_file_and_records_it(tmp_path, ball):
    """A user's own OBJ under the cloth: read, placed, its surface in the trajectories file, from which the barrier is
    rebuilt; a mesh the rest cloth starts inside is named by its config key."""
    import h5py

    from latentsim.config import with_defaults
    from latentsim.scene import contact_from_artefact
    from latentsim.stages.mesh import prepare_mesh
    from latentsim.stages.simulate import SimulationError, simulate_scene

    V, F = ball(1.0, (0.0, 0.0, 0.0))
    obj = tmp_path / "ball.obj"
    obj.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in V) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    mesh_h5 = tmp_path / "mesh.h5"
    grid = with_defaults("mesh", {"generator": "cloth_grid", "nx": 5, "ny": 5, "width": 0.2, "height": 0.2, "plane": "xz"}, "test")
    prepare_mesh("cloth", "shell", grid, with_defaults("dirichlet", {"type": "indices", "indices": [0, 5, 30, 35]}, "test"), {}, mesh_h5)
    entry = {"type": "mesh", "file": "ball.obj", "scale": 0.04, "translate": [0.0, -0.045, 0.0]}
    cfg = dict(model="shell", material={"youngs_modulus": 1e4, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.002}, dt=1 / 30,
               gravity=[0, -9.81, 0], newton=dict(tolerance=1e-6), sequences=[dict(name="s", split="train", frames=12)],
               contact={"colliders": [entry], "d_hat": 0.002}, mesh_sources={"local_dir": str(tmp_path)})  # fmt: skip
    out = tmp_path / "trajectories.h5"
    simulate_scene("cloth", mesh_h5, cfg, out)
    with h5py.File(out, "r") as f:
        assert f["collider0_vertices"].shape == (len(V), 3) and np.allclose(f["collider0_vertices"][()], 0.04 * V + [0, -0.045, 0])
        barrier = contact_from_artefact(f)
        x = f["sequences/s/positions"][()]
        d = f["sequences/s/min_contact_distance"][()]
    assert len(barrier.meshes) == 1 and barrier.meshes[0].thickness == 0.001  # half the cloth's thickness
    assert np.allclose(barrier.clearance(torch.as_tensor(x)).numpy(), d) and d.min() > 0 and d.min() < 0.002  # it reached the ball, outside
    entry["translate"] = [0.0, -0.02, 0.0]  # the ball through the rest cloth
    with pytest.raises(SimulationError, match=r"initial penetration: .* collider 0 \(mesh\) of contact\.colliders \(config key 'scenes\.cloth\.contact\.colliders\.0'"):
        simulate_scene("cloth", mesh_h5, cfg, tmp_path / "t2.h5")
    entry["file"] = "missing.obj"
    with pytest.raises(SimulationError, match=r"scenes\.cloth\.contact\.colliders\.0\.file.*missing\.obj"):
        simulate_scene("cloth", mesh_h5, cfg, tmp_path / "t3.h5")


def test_a_surface_of_vertices_alone_is_held_off_the_mesh_and_its_impacts_found(ball):
    """Without primitives (the vertices alone) one term: the vertices against the faces, with the line search's impacts."""
    V, F = ball(0.05, (0.0, 0.0, 0.0))
    contact = ContactBarrier(3, [], 0.001, 1.0, meshes=[TriangleMesh(V, F)])
    (term,) = contact.mesh_terms()
    x = np.array([[0.0, 0.06, 0.0], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3]])
    dx = np.zeros_like(x)
    dx[0, 1] = -0.05  # into the ball
    t = term.first_impact(x, dx)
    gap = float(term.distances(torch.as_tensor(x), 1.0))
    assert 0.8 * 0.9 * gap / 0.05 < t < gap / 0.05
    dx[0, 1] = 0.05  # away from it: free
    assert term.first_impact(x, dx) == math.inf
