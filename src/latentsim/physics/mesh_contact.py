"""Contact with a static triangle mesh (a character's body, a tool): IPC's barrier (Li et al. 2020, Eq. 6) summed
over the pairs of the surface's primitives and the mesh's within reach,

    sum over (vertex, mesh face) + (edge, mesh edge) + (triangle, mesh vertex) of b(d - thickness),

d the unsigned distance of the pair (:func:`~latentsim.physics.primitives.core_distance`: the mesh's face, edge or
vertex is the pair's static *core*), b :func:`~latentsim.physics.barrier.barrier`.  These three kinds of pairs hold
every point of the surface off every point of the mesh: the closest pair of two disjoint triangles (or of an edge and
a triangle) has a vertex of one against a face of the other, or an edge against an edge.  As in IPC's sum over pairs
a contact at a shared feature (a vertex over a mesh edge, both its faces near) counts once per pair: the barrier is
stiffer there, never weaker.

Each kind is one :class:`MeshBarrier` (an energy term of :mod:`latentsim.physics.base` whose stencils are the
surface's vertices, edges or triangles, so its Hessian blocks lie within the elastic stencils'): its candidates are
the mesh primitives in the cells of a uniform grid over the mesh that the stencil's box, grown by the reach, overlaps,
whose box comes within reach of it and whose distance from it, compiled (:mod:`latentsim.physics.kernels.distances`),
is within reach; its
distances, gradients (autograd) and Hessians (closed form, :func:`~latentsim.physics.primitives.distance_hessian`
and :func:`~latentsim.physics.primitives.vertex_hessian`) are the primitives module's.  The line search's time of
impact over all three kinds is the IPC Toolkit's (``ipctk``: its broad phase and additive continuous collision
detection, Li et al. 2021), held by the vertices' term.  The mesh is static and frictionless.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from latentsim.physics.barrier import barrier, barrier_derivatives
from latentsim.physics.base import EnergyTerm, project_psd
from latentsim.physics.kernels.distances import MeshGrid, grid_within
from latentsim.physics.primitives import core_distance, distance_hessian, vertex_hessian

__all__ = ["TriangleMesh", "MeshBarrier", "bounding_spheres", "mesh_barriers", "unique_edges"]


def unique_edges(triangles: np.ndarray) -> np.ndarray:
    """The edges (E, 2) of triangles (F, 3), each once, its vertices in increasing order."""
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def bounding_spheres(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (N, 3) and radius (N,) of a sphere around each primitive's vertices points (N, k, 3)."""
    c = points.mean(1)
    return c, np.linalg.norm(points - c[:, None, :], axis=-1).max(1)


class TriangleMesh:
    """A static triangle mesh, vertices (m, 3) [m] and faces (f, 3), that a surface is kept ``thickness`` [m] away from.

    Its primitives by the number of the surface's vertices they pair with: k = 1 its faces, k = 2 its edges, k = 3
    its vertices (:meth:`cores`), each with a uniform grid for :meth:`candidates` and a k-d tree over its bounding
    spheres' centres for :meth:`unsigned_distance` and the line search's quick test.
    """

    def __init__(self, vertices, faces, thickness: float = 0.0):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
        if not len(self.faces) or self.faces.min() < 0 or self.faces.max() >= len(self.vertices):
            raise ValueError(f"triangle mesh: {len(self.faces)} faces over {len(self.vertices)} vertices (give faces indexing them)")
        if not np.isfinite(self.vertices).all():
            raise ValueError("triangle mesh: its vertices are not all finite")
        if not thickness >= 0:
            raise ValueError(f"triangle mesh: thickness {thickness!r} must be >= 0")
        self.thickness = float(thickness)
        self.edges = unique_edges(self.faces)
        V = self.vertices
        self._cores = {1: V[self.faces], 2: V[self.edges], 3: V[:, None, :]}
        self._trees = {}
        for k in (1, 3):  # faces and vertices: unsigned_distance and first_impact's quick test
            c, r = bounding_spheres(self._cores[k])
            self._trees[k] = cKDTree(c), float(r.max())
        self._torch = {k: torch.as_tensor(v) for k, v in self._cores.items()}
        self._grids = {}

    def thickened(self, offset: float) -> "TriangleMesh":
        """The same mesh, the surface kept ``offset`` farther from it."""
        return TriangleMesh(self.vertices, self.faces, self.thickness + float(offset))

    def cores(self, k: int) -> torch.Tensor:
        """The mesh primitives that pair with a primitive of k vertices, (P, 4 - k, 3): faces, edges or vertices."""
        return self._torch[k]

    def candidates(self, ye: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """The pairs (i, j) of a primitive i of ye (N, k, 3) and a mesh primitive j of :meth:`cores` (k) that lie within
        ``reach`` of each other, with a slack (every pair nearer than ``reach`` is among them), i ascending and each i's
        j ascending: the mesh's uniform grid for its kind (built on first use), then boxes and distances, compiled
        (:func:`~latentsim.physics.kernels.distances.grid_within`)."""
        k = ye.shape[1]
        if k not in self._grids:
            spacing = float((self._cores[1].max(1) - self._cores[1].min(1)).max(1).mean())  # a face's mean extent
            self._grids[k] = MeshGrid(self._cores[k], spacing)
        return grid_within(ye, self._grids[k], reach)

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Whether each point (N, 3) lies inside the (closed) mesh: the parity of the faces a ray from it along +y
        crosses.  The faces are binned on a grid over (x, z), so a point meets only those over its cell; the ray starts
        a hair (1e-9 of the mesh's size) off the point in x and z, so that it passes through no edge or vertex but
        where the mesh is degenerate there."""
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        out = np.zeros(len(P), dtype=bool)
        box = np.flatnonzero(((P >= lo) & (P <= hi)).all(1))
        if not len(box):
            return out
        g = self._ray_grid()
        size = float(np.linalg.norm(hi - lo))
        q = P[box] + size * np.array([0.7e-9, 0.0, 0.3e-9])
        cell = np.clip(((q[:, [0, 2]] - g["lo"]) / g["h"]).astype(np.int64), 0, g["n"] - 1)
        c = cell[:, 0] * g["n"] + cell[:, 1]
        start, count = g["start"][c], g["count"][c]
        i = np.repeat(np.arange(len(q)), count)
        f = g["faces"][np.repeat(start - np.cumsum(count) + count, count) + np.arange(int(count.sum()))]
        T = self._cores[1][f][:, :, [0, 2]]  # the faces in (x, z)
        p = q[i][:, [0, 2]]

        def side(a, b):
            return (b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (p[:, 0] - a[:, 0])

        s0, s1, s2 = side(T[:, 0], T[:, 1]), side(T[:, 1], T[:, 2]), side(T[:, 2], T[:, 0])
        over = ((s0 > 0) & (s1 > 0) & (s2 > 0)) | ((s0 < 0) & (s1 < 0) & (s2 < 0))
        area = s0 + s1 + s2  # twice the projected area, signed: the barycentric weights are s1, s2, s0 over it
        Y = self._cores[1][f][:, :, 1]
        y = (s1 * Y[:, 0] + s2 * Y[:, 1] + s0 * Y[:, 2]) / np.where(area == 0, 1.0, area)
        hit = over & (y > q[i][:, 1])
        out[box] = np.bincount(i[hit], minlength=len(q)) % 2 == 1
        return out

    def _ray_grid(self) -> dict:
        """The faces binned over (x, z) for :meth:`inside`: each face in every cell its projection's box overlaps."""
        if getattr(self, "_grid", None) is None:
            T = self._cores[1][:, :, [0, 2]]
            lo, hi = T.min((0, 1)), T.max((0, 1))
            n = max(1, int(np.sqrt(len(T) / 2)))
            h = np.maximum((hi - lo) / n, 1e-300)
            a = np.clip(((T.min(1) - lo) / h).astype(np.int64), 0, n - 1)
            b = np.clip(((T.max(1) - lo) / h).astype(np.int64), 0, n - 1)
            cells, faces = [], []
            for f in range(len(T)):
                for u in range(a[f, 0], b[f, 0] + 1):
                    for v in range(a[f, 1], b[f, 1] + 1):
                        cells.append(u * n + v)
                        faces.append(f)
            cells, faces = np.asarray(cells), np.asarray(faces)
            order = np.argsort(cells, kind="stable")
            count = np.bincount(cells, minlength=n * n)
            self._grid = {"lo": lo, "h": h, "n": n, "faces": faces[order], "count": count, "start": np.cumsum(count) - count}
        return self._grid

    def unsigned_distance(self, points: np.ndarray) -> np.ndarray:
        """Each point's (N, 3) distance from the mesh's surface: over the faces within its nearest vertex's distance plus
        the largest face's reach (the nearest face is among them)."""
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not len(P):
            return np.zeros(0)
        d_v, _ = self._trees[3][0].query(P)  # (the tree over the vertices)
        tree, r_max = self._trees[1]
        hits = tree.query_ball_point(P, d_v + r_max)
        counts = np.fromiter(map(len, hits), dtype=np.int64, count=len(P))
        i = np.repeat(np.arange(len(P)), counts)
        j = np.fromiter(itertools.chain.from_iterable(hits), dtype=np.int64, count=int(counts.sum()))
        with torch.no_grad():
            d = core_distance(self.cores(1)[torch.as_tensor(j)], torch.as_tensor(P[i])[:, None, :]).numpy()
        out = np.full(len(P), np.inf)
        np.minimum.at(out, i, d)
        return out

    def distance(self, xp: torch.Tensor, j) -> torch.Tensor:
        """The signed distance (unsigned less the thickness) of each primitive xp (P, k, 3) from mesh primitive j (P,)."""
        return core_distance(self.cores(xp.shape[-2])[torch.as_tensor(j)].to(xp), xp) - self.thickness


class MeshBarrier(EnergyTerm):
    """The barrier of one kind of pair (module docstring) between a surface's primitives ``stencils`` (E, k) - its
    vertices (k = 1), edges (2) or triangles (3) - and a :class:`TriangleMesh`; ``d_hat``, ``kappa``,
    ``extend_below`` as :func:`~latentsim.physics.barrier.barrier`'s.

    ``surface`` (edges, triangles of the whole surface, for the vertices' term): the term then also holds the line
    search's :meth:`first_impact` for every kind of pair (the IPC Toolkit's additive CCD); the other kinds' terms
    leave it to that one (their :meth:`first_impact` is inf).
    """

    name = "mesh_barrier"

    def __init__(self, mesh: TriangleMesh, stencils, d_hat: float, kappa: float, extend_below: float | None = None, surface=None):
        self.mesh = mesh
        self.stencils = torch.as_tensor(np.asarray(stencils, dtype=np.int64))
        if self.stencils.ndim != 2 or self.stencils.shape[1] not in (1, 2, 3):
            raise ValueError(f"mesh barrier: stencils of shape {tuple(self.stencils.shape)} (give vertices, edges or triangles)")
        self.k = int(self.stencils.shape[1])
        self.d_hat, self.kappa, self.extend_below = float(d_hat), float(kappa), extend_below
        self.surface = surface
        self._ccd_mesh = None

    def _pairs(self, ye: torch.Tensor, reach: float):
        """The pairs (state-and-stencil flat index, mesh primitive) of ye (..., E, k, 3) whose signed distance is below
        ``reach``: the candidates (:meth:`TriangleMesh.candidates`) measured, without gradients, and the nearer kept."""
        flat = ye.detach().reshape(-1, self.k, 3)
        i, j = self.mesh.candidates(flat.cpu().numpy(), reach + self.mesh.thickness)
        if len(i):
            with torch.no_grad():
                keep = (self.mesh.distance(flat[torch.as_tensor(i)], j) < reach).numpy()
            i, j = i[keep], j[keep]
        return i, j

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """Per stencil, the barrier summed over every mesh primitive, xe (..., E, k, 3) -> (..., E): all pairs, in PyTorch
        alone (the autograd oracle's); :meth:`energy` evaluates only the candidates."""
        cores = self.mesh.cores(self.k).to(xe)
        M = len(cores)
        ye = xe[..., None, :, :].expand(*xe.shape[:-2], M, self.k, 3)
        d = core_distance(cores.expand(*xe.shape[:-2], M, 4 - self.k, 3), ye) - self.mesh.thickness
        return barrier(d, self.d_hat, self.kappa, self.extend_below).sum(-1)

    def energy(self, x: torch.Tensor, frame=None) -> torch.Tensor:
        """Total energy, x (..., n, 3) -> (...), over the candidate pairs within reach (the others' energy is 0)."""
        ye = self.gather(x)
        i, j = self._pairs(ye, self.d_hat)
        E = ye.shape[-3]
        out = torch.zeros(int(np.prod(ye.shape[:-3], dtype=np.int64)), dtype=x.dtype, device=x.device)
        if len(i):
            it = torch.as_tensor(i)
            b = barrier(self.mesh.distance(ye.reshape(-1, self.k, 3)[it], j), self.d_hat, self.kappa, self.extend_below)
            out = out.index_add(0, it // E, b)
        return out.reshape(ye.shape[:-3])

    def distances(self, x: torch.Tensor, reach: float) -> torch.Tensor:
        """The least signed distance of each state's stencils from the mesh, x (..., n, 3) -> (...): ``reach`` where no
        pair is nearer than it (the distance is then ``reach`` or more)."""
        ye = self.gather(x)
        i, j = self._pairs(ye, reach)
        E = ye.shape[-3]
        out = torch.full((int(np.prod(ye.shape[:-3], dtype=np.int64)),), float(reach), dtype=x.dtype)
        if len(i):
            d = self.mesh.distance(ye.reshape(-1, self.k, 3)[torch.as_tensor(i)], j).detach()
            out = out.scatter_reduce(0, torch.as_tensor(i // E), d, reduce="amin")
        return out.reshape(ye.shape[:-3])

    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True, hessian: bool = True):
        """Per stencil (E, 3k) and (E, 3k, 3k), its pairs' b'(d) grad d and b''(d) grad d grad d^T + b'(d) Hess d
        summed (PSD-projected per stencil when ``project``), zero for a stencil with no pair within reach."""
        E, k, _ = xe.shape
        g = torch.zeros(E, 3 * k, dtype=xe.dtype)
        H = torch.zeros(E, 3 * k, 3 * k, dtype=xe.dtype) if hessian else None
        i, j = self._pairs(xe, self.d_hat)
        if not len(i):
            return g, H
        it = torch.as_tensor(i)
        y = xe.detach()[it].clone().requires_grad_(True)
        with torch.enable_grad():
            d = self.mesh.distance(y, j)
            (grad_d,) = torch.autograd.grad(d.sum(), y)
        d = d.detach()
        db, d2b = barrier_derivatives(d, self.d_hat, self.kappa, self.extend_below)
        gd = grad_d.reshape(len(i), 3 * k)
        g.index_add_(0, it, db[:, None] * gd)
        if hessian:
            core, rho = self.mesh.cores(k)[torch.as_tensor(j)], d + self.mesh.thickness
            if k == 1:
                Hd = vertex_hessian(y.detach()[:, 0, :], grad_d[:, 0, :], rho, core)
            else:
                Hd = distance_hessian(y.detach(), grad_d, rho, core if k == 2 else None)
            H.index_add_(0, it, d2b[:, None, None] * gd[:, :, None] * gd[:, None, :] + db[:, None, None] * Hd)
            if project:
                near = torch.unique(it)
                H[near] = project_psd(H[near])
        return g, H

    def first_impact(self, x: np.ndarray, dx: np.ndarray, frame=None) -> float:
        """The largest fraction t of the step x -> x + dx (n, 3) over which no point of the surface comes within the
        mesh's thickness of it (the IPC Toolkit's collision-free step size, its additive CCD conservative by a tenth
        of the distance), inf where the whole step is free; inf for a term without the ``surface``."""
        if self.surface is None:
            return math.inf
        import ipctk

        # a step along which no primitive's bounding sphere, swept, comes within the thickness of a face's is free
        edges, faces = self.surface
        prim = np.asarray(faces if len(faces) else edges if len(edges) else np.arange(len(x))[:, None], dtype=np.int64)
        c, r = bounding_spheres(np.asarray(x, dtype=np.float64)[prim])
        tree, r_max = self.mesh._trees[1]
        sweep = float(np.sqrt((np.asarray(dx, dtype=np.float64) ** 2).sum(-1).max(initial=0.0)))
        if not any(map(len, tree.query_ball_point(c, r + r_max + self.mesh.thickness + sweep))):
            return math.inf
        n = len(x)
        V0 = np.asfortranarray(np.concatenate([np.asarray(x, dtype=np.float64), self.mesh.vertices]))
        V1 = np.asfortranarray(np.concatenate([np.asarray(x, dtype=np.float64) + dx, self.mesh.vertices]))
        if self._ccd_mesh is None or self._ccd_mesh[0] != n:  # (the toolkit's mesh of both surfaces, built once)
            E = np.concatenate([np.asarray(edges, dtype=np.int64).reshape(-1, 2), self.mesh.edges + n]).astype(np.int32)
            F = np.concatenate([np.asarray(faces, dtype=np.int64).reshape(-1, 3), self.mesh.faces + n]).astype(np.int32)
            cm = ipctk.CollisionMesh(V0, np.asfortranarray(E), np.asfortranarray(F))
            cm.can_collide = ipctk.make_static_obstacle_filter(n)
            self._ccd_mesh = (n, cm)
        t = ipctk.compute_collision_free_stepsize(self._ccd_mesh[1], V0, V1, self.mesh.thickness, None, ipctk.AdditiveCCD())
        return math.inf if t >= 1.0 else float(t)


def mesh_barriers(mesh: TriangleMesh, primitives, n_vertices: int, d_hat: float, kappa: float,
                  extend_below: float | None = None) -> list[MeshBarrier]:  # fmt: skip
    """The terms that hold a surface off ``mesh``: its vertices against the faces, its edges against the edges and (a
    surface of triangles) its triangles against the vertices.  ``primitives``: the surface's edges (P, 2) (a strand)
    or triangles (P, 3), its vertices those they use; None: every one of the ``n_vertices`` alone, against the faces."""
    if primitives is None:
        none = (np.zeros((0, 2), np.int64), np.zeros((0, 3), np.int64))
        return [MeshBarrier(mesh, np.arange(n_vertices)[:, None], d_hat, kappa, extend_below, surface=none)]
    prim = np.asarray(primitives, dtype=np.int64)
    if prim.ndim != 2 or prim.shape[1] not in (2, 3) or (len(prim) and (prim.min() < 0 or prim.max() >= n_vertices)):
        raise ValueError(f"mesh contact: primitives of shape {prim.shape} over {n_vertices} vertices (give edges or triangles)")
    edges = prim if prim.shape[1] == 2 else unique_edges(prim)
    faces = prim if prim.shape[1] == 3 else np.zeros((0, 3), np.int64)
    verts = np.unique(prim)[:, None]
    terms = [MeshBarrier(mesh, verts, d_hat, kappa, extend_below, surface=(edges, faces)), MeshBarrier(mesh, edges, d_hat, kappa, extend_below)]
    if len(faces):
        terms.append(MeshBarrier(mesh, faces, d_hat, kappa, extend_below))
    return terms
