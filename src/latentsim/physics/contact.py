"""Contact with analytic colliders: each vertex against each collider (and, by :class:`SurfaceBarrier`, each edge
or triangle of the surface against each curved one) through the log barrier of Incremental Potential Contact
(Li et al. 2020, Eq. 6),

    b(d) = -kappa (d - d_hat)^2 ln(d / d_hat)   for 0 < d < d_hat,   0 for d >= d_hat,

with d the signed distance of the vertex from the collider's surface.  b, b' and b'' all vanish at
d = d_hat (b is C2 there, as IPC requires of its barrier), b grows without bound as d -> 0+, and
b' < 0 < b'' on (0, d_hat): the barrier only ever pushes a vertex away.

The colliders are analytic shapes (:mod:`latentsim.physics.colliders`: half-spaces, spheres, capsules), each with
its signed distance, the distance's gradient and Hessian in closed form, and the time of impact along a
straight step (continuous collision detection against an analytic shape is a closed-form root), which a
line search uses to keep every iterate outside.  A collider is static, or *attached* to the prescribed
(Dirichlet) vertices: it then moves rigidly with the boundary-condition program, its pose at a frame the
rigid motion that carries the prescribed vertices' rest positions onto their targets (:func:`rigid_pose`).
A signed distance is invariant under rigid motion, so an attached collider's distance at a pose is its
rest shape's distance of the point carried back to the rest frame.  Friction is IPC's lagged friction
(Li et al. 2020, sec. 5), optional.

:class:`ContactBarrier` is an energy term of the contract of :mod:`latentsim.physics.base` (one vertex
per stencil), with its per-vertex gradient and PSD-projected Hessian in closed form; the autograd
oracle of the base class checks them.  It depends on the step's :class:`~latentsim.physics.frame.Frame`
(the targets that place an attached collider, the previous positions friction lags from): a solver
evaluates :meth:`ContactBarrier.at` the frame, the static barrier of that step, and its line search stops
short of :meth:`ContactBarrier.first_impact`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from latentsim.physics.barrier import barrier, barrier_derivatives
from latentsim.physics.base import EnergyTerm, project_psd
from latentsim.physics.mesh_contact import mesh_barriers
from latentsim.physics.colliders import Capsule, posed_colliders, rigid_pose
from latentsim.physics.primitives import distance_hessian, primitive_toi
from latentsim.physics.self_contact import SelfContact


#: how far (in d_hat) a mesh's distances are measured for :meth:`ContactBarrier.clearance`; beyond, "this or more"
MESH_REACH = 10.0


def friction_f0(s: torch.Tensor, eps: float) -> torch.Tensor:
    """IPC's smoothed friction potential of a tangential slip s >= 0 over a step (Li et al. 2020, Eq. 14):
    s^2 / eps - s^3 / (3 eps^2) + eps / 3 below eps, s above (C1 at eps; its derivative f1 rises from 0 to 1
    over the slip eps, the static-to-dynamic transition)."""
    return torch.where(s < eps, s * s / eps - s**3 / (3 * eps * eps) + eps / 3, s)


def friction_f1_over_s(s: torch.Tensor, eps: float) -> torch.Tensor:
    """f0'(s) / s: 2 / eps - s / eps^2 below eps (finite at s = 0), 1 / s above."""
    return torch.where(s < eps, 2 / eps - s / (eps * eps), 1 / torch.where(s < eps, torch.ones_like(s), s))


class ContactBarrier(EnergyTerm):
    """Every vertex against every collider: sum_i sum_c b(d_c(x_i)) (one vertex per stencil).

    Parameters
    ----------
    n_vertices : n; colliders : the shapes (at rest); d_hat : activation distance [m]; kappa : stiffness.
    extend_below : see :func:`barrier`.
    attached : one flag per collider (default: none attached): an attached collider moves rigidly with
        the prescribed vertices, its pose at a frame :func:`rigid_pose` of ``rest_dirichlet`` onto that
        frame's targets.
    rest_dirichlet : (m, 3) the prescribed vertices' rest positions; needed (at least three of them, not on
        one line, so that the pose is determined) when a collider is attached.
    friction : the coefficient mu of IPC's lagged friction (0: frictionless); slip : the tangential slip over a
        step [m] below which friction is static (eps_v h in IPC's terms).

    Friction (Li et al. 2020, sec. 5) is lagged over a step: each vertex's normal force lambda = -b'(d) and
    tangent plane are those at the start of the step, and its energy mu lambda f0(|u|) of the slip u, the
    step's displacement relative to the collider projected on that plane (:func:`friction_f0`).  Where the
    step starts is the frame's: its ``x_prev`` (and ``targets_prev``, the prescribed positions then, for an
    attached collider), to :meth:`energy`, or :meth:`at` for a solver's step.
    anchors : the lagged friction of one step, per collider (y_prev, lambda, tangent projector), as
        :meth:`at` computes them; None (the default) for a barrier of no particular step.
    primitives : None (vertices only), or the surface's edges (P, 2) or triangles (P, 3): each is then also
        kept out of every curved collider by a :class:`SurfaceBarrier` (:meth:`terms`), so that no point of the
        surface comes within the barrier's reach unseen (against a half-space the vertices are the nearest points).
    meshes : static :class:`~latentsim.physics.mesh_contact.TriangleMesh` colliders (a body, a tool), each held off
        every vertex, edge and triangle of the surface by the terms of :func:`~latentsim.physics.mesh_contact.mesh_barriers`
        (:meth:`terms`; frictionless).
    self_contact : None, or the thickness [m] two parts of the surface (its ``primitives``) keep apart: its parts are
        then held off each other by a :class:`~latentsim.physics.self_contact.SelfContact` term (:meth:`terms`).

    With an attached collider the barrier depends on the frame: :meth:`energy` and :meth:`distances` take
    the frame's ``targets``, and :meth:`posed` gives the static barrier of one frame (what a solver's
    step, its closed-form derivatives and its line search work with).
    """

    name = "contact_barrier"

    def __init__(self, n_vertices: int, colliders, d_hat: float, kappa: float, extend_below: float | None = None,
                 attached=None, rest_dirichlet=None, friction: float = 0.0, slip: float | None = None, anchors=None,
                 primitives=None, meshes=(), self_contact: float | None = None):  # fmt: skip
        if not (d_hat > 0 and kappa > 0):
            raise ValueError(f"contact barrier: d_hat {d_hat!r} and kappa {kappa!r} must be positive")
        if not (friction >= 0 and (friction == 0 or (slip is not None and slip > 0))):
            raise ValueError(f"contact barrier: friction {friction!r} must be >= 0, and with friction the slip {slip!r} positive")
        self.friction, self.slip = float(friction), (None if slip is None else float(slip))
        self.anchors = None if anchors is None else tuple(anchors)  # one step's lagged friction (at)
        if extend_below is not None and not 0 < extend_below < d_hat:
            raise ValueError(f"contact barrier: extend_below {extend_below!r} must lie in (0, d_hat = {d_hat})")
        self.colliders = list(colliders)
        self.attached = tuple(bool(a) for a in attached) if attached is not None else (False,) * len(self.colliders)
        if len(self.attached) != len(self.colliders):
            raise ValueError(f"contact barrier: {len(self.attached)} attached flags for {len(self.colliders)} colliders")
        self.rest_dirichlet = None
        if any(self.attached):
            rest = np.asarray(rest_dirichlet if rest_dirichlet is not None else np.zeros((0, 3)), dtype=float).reshape(-1, 3)
            spread = np.linalg.svd(rest - rest.mean(0), compute_uv=False) if len(rest) else np.zeros(3)
            if len(rest) < 3 or not spread[1] > 1e-9 * max(spread[0], 1e-300):
                raise ValueError(f"contact barrier: an attached collider moves with the prescribed vertices, and their pose needs at "
                                 f"least three of them not on one line ({len(rest)} prescribed)")  # fmt: skip
            self.rest_dirichlet = rest
        self.d_hat, self.kappa, self.extend_below = float(d_hat), float(kappa), extend_below
        self.stencils = torch.arange(int(n_vertices)).reshape(-1, 1)
        self.primitives = None if primitives is None else torch.as_tensor(np.asarray(primitives, dtype=np.int64))
        if self.primitives is not None and (self.primitives.ndim != 2 or self.primitives.shape[1] not in (2, 3)):
            raise ValueError(f"contact barrier: primitives of shape {tuple(self.primitives.shape)}: give edges (P, 2) or triangles (P, 3)")
        self.meshes = tuple(meshes)
        self._mesh_terms = None
        if self_contact is not None and (self.primitives is None or not self_contact >= 0):
            raise ValueError(f"contact barrier: self-contact (thickness {self_contact!r}) needs the surface's primitives and a thickness >= 0")
        self.self_contact, self._self_term = self_contact, None

    def terms(self) -> list:
        """The terms of E_total this contact adds: this barrier (the vertices against the analytic colliders, and
        friction), the :class:`SurfaceBarrier` of its primitives where a collider is curved, each mesh's and the
        surface's against itself (``self_contact``)."""
        out = [self]
        if self.primitives is not None and any(c.curved for c in self.colliders):
            out.append(SurfaceBarrier(self))
        return out + self.mesh_terms() + ([self.self_term()] if self.self_contact is not None else [])

    def self_term(self):
        """The :class:`~latentsim.physics.self_contact.SelfContact` of the surface (``self_contact`` set)."""
        if self._self_term is None:
            n, prim = len(self.stencils), self.primitives.numpy()
            self._self_term = SelfContact(n, prim, self.d_hat, self.kappa, self.self_contact, self.extend_below)
        return self._self_term

    def _like(self, **changes) -> "ContactBarrier":
        """A barrier of this one's settings but ``changes`` (the constructor's keyword arguments)."""
        kw = dict(colliders=self.colliders, d_hat=self.d_hat, kappa=self.kappa, extend_below=self.extend_below, friction=self.friction,
                  slip=self.slip, primitives=self.primitives, meshes=self.meshes, self_contact=self.self_contact)  # fmt: skip
        return ContactBarrier(len(self.stencils), **{**kw, **changes})

    def mesh_terms(self) -> list:
        """The terms holding the surface (its ``primitives``, or the vertices alone) off each of the ``meshes``."""
        if self._mesh_terms is None:
            prim = None if self.primitives is None else self.primitives.numpy()
            self._mesh_terms = [t for m in self.meshes for t in mesh_barriers(m, prim, len(self.stencils), self.d_hat, self.kappa, self.extend_below)]
        return self._mesh_terms

    @property
    def moving(self) -> bool:
        """Whether a collider is attached (the barrier then depends on the frame's targets)."""
        return any(self.attached)

    def extended(self, fraction: float = 0.1, d_hat_factor: float = 1.0, kappa_factor: float = 1.0) -> "ContactBarrier":
        """The barrier of activation distance ``d_hat_factor`` d_hat and stiffness ``kappa_factor``
        kappa, continued below ``fraction`` of that distance by its quadratic Taylor expansion
        (:func:`barrier`'s ``extend_below``): finite inside the colliders, for learned losses."""
        d_hat = d_hat_factor * self.d_hat
        return self._like(d_hat=d_hat, kappa=kappa_factor * self.kappa, extend_below=fraction * d_hat, attached=self.attached, rest_dirichlet=self.rest_dirichlet)

    def posed(self, targets) -> "ContactBarrier":
        """The static barrier of one frame: every attached collider carried to its pose at ``targets`` (m, 3),
        the prescribed vertices' positions; this barrier itself when none is attached."""
        if not self.moving:
            return self
        return self._like(colliders=posed_colliders(self.colliders, self.attached, self.rest_dirichlet, targets))

    def at(self, frame) -> "ContactBarrier":
        """The static barrier of a solver's step (:meth:`posed` at the frame's ``targets``) with its lagged
        friction: for each collider and vertex the anchor (where the vertex stood at the step's start, the
        frame's ``x_prev``, carried with an attached collider from its pose at the frame's ``targets_prev`` to
        its pose at ``targets``), the normal force lambda = -b'(d) and the tangent projector there.
        Frictionless, just :meth:`posed` (this barrier itself with no collider attached)."""
        targets, step = frame.targets, self.posed(frame.targets)
        if self.friction == 0:
            return step
        targets_prev, x_prev = frame.targets_prev, torch.as_tensor(np.asarray(frame.x_prev, dtype=float))
        anchors = [x_prev] * len(self.colliders)
        if self.moving:  # x_prev carried back to the rest frame at the step's start, then out to the pose at its end
            back = self._to_rest(x_prev, targets_prev)
            R, c = rigid_pose(self.rest_dirichlet, np.asarray(targets, dtype=float))
            c0 = torch.as_tensor(self.rest_dirichlet.mean(0))
            carried = (back - c0) @ R.transpose(-1, -2) + c
            anchors = [carried if a else x_prev for a in self.attached]
        anchors = [(a,) + self._lagged(col, a) for col, a in zip(step.colliders, anchors)]
        return self._like(colliders=step.colliders, anchors=anchors)

    def _lagged(self, col, y_prev: torch.Tensor):
        """lambda (...,) and the tangent projector (..., 3, 3) of collider ``col`` at the step's start y_prev."""
        with torch.no_grad():
            db, _ = barrier_derivatives(col.distance(y_prev), self.d_hat, self.kappa)
            n, _ = col.distance_derivatives(y_prev)
            P = torch.eye(3, dtype=y_prev.dtype, device=y_prev.device) - n[..., :, None] * n[..., None, :]
        return -db, P

    def _friction(self, y, y_prev, lam, P) -> torch.Tensor:
        """Per vertex mu lambda f0(|P (y - y_prev)|), the lagged friction of one collider, y (..., n, 3) -> (..., n)."""
        u = (P @ (y - y_prev)[..., None])[..., 0]
        return self.friction * lam * friction_f0(torch.sqrt((u * u).sum(-1) + 1e-300), self.slip)

    def _signed_distances(self, x: torch.Tensor, targets) -> list[torch.Tensor]:
        """Each collider's signed distance of every vertex, x (..., n, 3) -> [(..., n)]; an attached
        collider's at its pose of ``targets`` (..., m, 3) (the same leading shape as x, or none), by
        carrying x back to the rest frame."""
        return [col.distance(y) for col, y in zip(self.colliders, self._frames(x, targets))]

    def _to_rest(self, x: torch.Tensor, targets) -> torch.Tensor:
        """x (..., n, 3) carried back to the attached colliders' rest frame from their pose at ``targets``."""
        if targets is None:
            raise ValueError("contact barrier: an attached collider's distance needs the frame's Dirichlet targets")
        targets = torch.as_tensor(targets, dtype=x.dtype, device=x.device)
        R, c = rigid_pose(self.rest_dirichlet, targets)
        c0 = torch.as_tensor(self.rest_dirichlet.mean(0), dtype=x.dtype, device=x.device)
        return (x - c[..., None, :]) @ R + c0  # R^T (x - c) + c0, row-wise

    def _frames(self, x: torch.Tensor, targets) -> list[torch.Tensor]:
        """x as each collider sees it: carried back to the rest frame for an attached one, as it is for a static one."""
        if not self.moving:
            return [x] * len(self.colliders)
        back = self._to_rest(x, targets)
        return [back if a else x for a in self.attached]

    def energy(self, x: torch.Tensor, frame=None) -> torch.Tensor:
        """Total barrier energy, x (..., n, 3) -> (...); the frame's ``targets`` (..., m, 3), its prescribed
        positions, needed with an attached collider.  With friction, also the lagged friction of the step from
        the frame's ``x_prev`` (the prescribed positions then: its ``targets_prev``), or of :meth:`at`'s step
        (whose energy needs no frame)."""
        targets, x_prev, targets_prev = (None, None, None) if frame is None else (frame.targets, frame.x_prev, frame.targets_prev)
        if self.anchors is not None or (not self.moving and (self.friction == 0 or x_prev is None)):
            return super().energy(x)
        frames = self._frames(x, targets)
        zero = torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)  # (no analytic collider: only meshes)
        e = sum((barrier(col.distance(y), self.d_hat, self.kappa, self.extend_below).sum(-1) for col, y in zip(self.colliders, frames)), zero)
        if self.friction > 0 and x_prev is not None:
            x_prev = torch.as_tensor(x_prev, dtype=x.dtype, device=x.device)
            for col, y, y_prev in zip(self.colliders, frames, self._frames(x_prev, targets_prev)):
                e = e + self._friction(y, y_prev, *self._lagged(col, y_prev)).sum(-1)
        return e

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        x = xe[..., 0, :]
        total = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
        for c in self.colliders:
            total = total + barrier(c.distance(x), self.d_hat, self.kappa, self.extend_below)
        if self.anchors is not None:  # a solver step's lagged friction, spread over the vertices
            for y_prev, lam, P in self.anchors:
                total = total + self._friction(x, y_prev, lam, P)
        return total

    def distances(self, x: torch.Tensor, targets=None) -> torch.Tensor:
        """The signed distance of every vertex from its nearest collider, x (..., n, 3) -> (..., n);
        ``targets`` as in :meth:`energy`."""
        if not self.colliders:
            return torch.full(x.shape[:-1], math.inf, dtype=x.dtype, device=x.device)
        return torch.stack(self._signed_distances(x, targets)).amin(0)

    def _all_distances(self, x: torch.Tensor, targets) -> list[torch.Tensor]:
        """Per collider, the signed distances of every vertex and then (a curved collider) of every primitive, (..., n [+ P]);
        then per mesh the least over its pairs (:data:`MESH_REACH` d_hat where none is nearer) and each vertex's, minus its depth
        and the thickness where it is inside the mesh (:meth:`~latentsim.physics.mesh_contact.TriangleMesh.inside`), else inf,
        (..., 1 + n); with ``self_contact``, last, the least distance between two parts of the surface (..., 1)."""
        out = []
        for col, y in zip(self.colliders, self._frames(x, targets)):
            d = col.distance(y)
            if self.primitives is not None and col.curved:
                d = torch.cat([d, col.primitive_distance(y[..., self.primitives, :])], -1)
            out.append(d)
        terms = self.mesh_terms()
        for mesh in self.meshes:
            d = torch.stack([t.distances(x, MESH_REACH * self.d_hat) for t in terms if t.mesh is mesh]).amin(0)
            # a vertex inside the body: its depth, the distance from the surface, less the thickness
            pts = x.detach().reshape(-1, 3).cpu().numpy()
            inside = np.flatnonzero(mesh.inside(pts))
            v = torch.full((len(pts),), math.inf, dtype=x.dtype)
            v[inside] = -torch.as_tensor(mesh.unsigned_distance(pts[inside]), dtype=x.dtype) - mesh.thickness
            out.append(torch.cat([d[..., None], v.reshape(x.shape[:-1])], -1))
        if self.self_contact is not None:  # the surface against itself, as a mesh: the least over its pairs
            out.append(self.self_term().distances(x, MESH_REACH * self.d_hat)[..., None])
        return out

    def clearance(self, x: torch.Tensor, targets=None) -> torch.Tensor:
        """The least signed distance of the surface from the colliders, x (..., n, 3) -> (...): over the vertices and,
        with ``primitives``, over every edge's or triangle's closest point (negative: some point of the surface is inside).
        ``targets`` as in :meth:`energy`."""
        return torch.stack([d.amin(-1) for d in self._all_distances(x, targets)]).amin(0)

    def penetrations(self, x, targets=None) -> list[tuple[int, float]]:
        """Per collider, how many vertices (and, with ``primitives``, edges or triangles) of x (n, 3) lie inside it or
        touch its surface (signed distance <= 0, where the barrier is infinite) and the smallest signed distance (per
        mesh, and for the surface against itself: 1 where a pair is within the thickness, and the least distance);
        ``targets`` as in :meth:`energy`."""
        x = torch.as_tensor(np.asarray(x, dtype=float))
        return [(int((d <= 0).sum()), float(d.min())) for d in self._all_distances(x, targets)]

    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True, hessian: bool = True):
        """Per vertex: g = b'(d) grad d and H = b''(d) grad d grad d^T + b'(d) Hess d, summed over the
        colliders, H clamped to its non-negative eigenvalues when ``project``; H is None without
        ``hessian`` (a line search's trial needs the gradient alone)."""
        x = xe[:, 0, :]
        g = torch.zeros_like(x)
        H = torch.zeros(x.shape + (3,), dtype=x.dtype, device=x.device)
        for c in self.colliders:
            d = c.distance(x)
            db, d2b = barrier_derivatives(d, self.d_hat, self.kappa, self.extend_below)
            n, hd = c.distance_derivatives(x)
            g = g + db[:, None] * n
            if hessian:
                H = H + d2b[:, None, None] * n[:, :, None] * n[:, None, :] + db[:, None, None] * hd
        for y_prev, lam, P in self.anchors or ():
            # mu lambda f0(|u|), u = P (x - y_prev): g = mu lambda f1(s)/s P u; H = mu lambda (f1/s P + (f1' - f1/s) / s^2 (Pu)(Pu)^T), PSD
            u = (P @ (x - y_prev)[:, :, None])[:, :, 0]
            s = torch.sqrt((u * u).sum(-1) + 1e-300)
            k = self.friction * lam * friction_f1_over_s(s, self.slip)
            g = g + k[:, None] * u
            if hessian:
                eps = self.slip
                curv = torch.where(s < eps, -1.0 / (eps * eps * s), -1.0 / s**3)  # (f1' - f1/s) / s^2
                H = H + k[:, None, None] * P + (self.friction * lam * curv)[:, None, None] * u[:, :, None] * u[:, None, :]
        if not hessian:
            return g, None
        if project:
            w, V = torch.linalg.eigh(H)
            H = (V * w.clamp_min(0.0)[:, None, :]) @ V.transpose(1, 2)
        return g, H

    def first_impact(self, x: np.ndarray, dx: np.ndarray, frame=None) -> float:
        """The first fraction t >= 0 of the step x -> x + dx (x, dx (n, 3)) at which a vertex reaches a collider
        (where the energy turns infinite: a line search stops short of it); inf if none does.  The colliders
        where they stand (:meth:`posed` first when one is attached), or, with a ``frame``, every attached one
        moving over the step from its pose at the frame's ``targets_prev`` to its pose at its ``targets``: each
        vertex's path taken straight in the collider's rest frame (exact for a translation; for a turn, a
        straight path between the carried-back ends, which a solver's step of a small rotation follows closely)."""
        paths = self.paths(x, dx, frame)
        return min((float(np.min(c.time_of_impact(*p), initial=np.inf)) for c, p in zip(self.colliders, paths)), default=np.inf)

    def paths(self, x, dx, frame=None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per collider, the step x -> x + dx (n, 3) as a start and a displacement in the frame it is tested in: as given,
        or, for an attached collider with a ``frame``, straight between the ends carried back to its rest frame from its
        poses at the frame's ``targets_prev`` and ``targets`` (:meth:`first_impact`)."""
        x, dx = np.asarray(x, dtype=float).reshape(-1, 3), np.asarray(dx, dtype=float).reshape(-1, 3)
        if frame is None or not self.moving:
            return [(x, dx)] * len(self.colliders)
        ends = ((x, frame.targets_prev), (x + dx, frame.targets))
        back = [self._to_rest(torch.as_tensor(y), np.asarray(targets, dtype=float)).numpy() for y, targets in ends]
        return [(back[0], back[1] - back[0]) if a else (x, dx) for a in self.attached]


class SurfaceBarrier(EnergyTerm):
    """The edges or triangles of a surface against the curved colliders of a :class:`ContactBarrier`:
    sum_p sum_c b(d_c(p)), d_c(p) the signed distance of primitive p's closest point from collider c
    (:meth:`~latentsim.physics.colliders.Collider.primitive_distance`), one primitive per stencil.

    A vertex-only barrier lets a ball or a capsule into the inside of an edge or a triangle where no vertex is
    near it; this term holds every point of the surface out.  A primitive's distance is at most its vertices',
    so a contact at a vertex is held by the vertex barrier and by each primitive that meets there (IPC's sum over
    pairs counts such duplicates alike; Li et al. 2020): the barrier is stiffer there, never weaker.  Half-spaces
    are left to the vertex barrier (against a plane the nearest point of a primitive is a vertex).  Friction
    acts on the vertices only (:class:`ContactBarrier`).

    Everything but the stencils is the contact's: its colliders (posed with the prescribed vertices when
    attached), ``d_hat``, ``kappa``, ``extend_below``.  Only the primitives (of each state) that may lie within
    ``d_hat`` are evaluated: a distance is 1-Lipschitz, so a primitive is no nearer than its nearest vertex less its
    longest edge (:meth:`_bound`), and one farther than that contributes exactly nothing.  The gradient is b'(d) grad d, grad d by autograd of
    the closest-point distances (:mod:`latentsim.physics.primitives`; C1 wherever the closest pair is unique, where
    it is the closest point's barycentric weights times the unit normal, -w_i n).  The Hessian is b''(d) grad d
    grad d^T + b'(d) Hess d, Hess d in closed form from that gradient
    (:func:`~latentsim.physics.primitives.distance_hessian`; autograd's, its test oracle, costs about as much as the
    rest of a cloth's Newton iteration), eigenvalue-clamped when projected.
    """

    name = "surface_barrier"

    def __init__(self, contact: ContactBarrier):
        self.contact = contact
        self.stencils = contact.primitives
        self.curved = [i for i, c in enumerate(contact.colliders) if c.curved]
        self.d_hat, self.kappa, self.extend_below = contact.d_hat, contact.kappa, contact.extend_below

    def at(self, frame) -> "SurfaceBarrier":
        """The static term of one step: the contact's colliders posed at the frame's targets."""
        return SurfaceBarrier(self.contact.posed(frame.targets)) if self.contact.moving else self

    def _distances(self, xe: torch.Tensor, colliders) -> list[torch.Tensor]:
        """Each curved collider's signed distance of every primitive, xe (..., P, k, 3) -> [(..., P)]."""
        return [colliders[i].primitive_distance(xe) for i in self.curved]

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(xe.shape[:-2], dtype=xe.dtype, device=xe.device)
        for d in self._distances(xe, self.contact.colliders):
            total = total + barrier(d, self.d_hat, self.kappa, self.extend_below)
        return total

    def _bound(self, ye: torch.Tensor, col) -> torch.Tensor:
        """A bound below each primitive's distance from collider ``col``, ye (..., P, k, 3) -> (..., P): its nearest
        vertex's distance less its longest edge."""
        with torch.no_grad():
            edge = torch.linalg.vector_norm(ye - ye.roll(1, dims=-2), dim=-1).amax(-1)
            return col.distance(ye).amin(-1) - edge

    def energy(self, x: torch.Tensor, frame=None) -> torch.Tensor:
        """Total energy, x (..., n, 3) -> (...); with an attached collider, at its pose of the frame's ``targets``.
        Only the pairs of a state and a primitive within reach of a collider are evaluated (the others' energy is 0)."""
        frames = self.contact._frames(x, None if frame is None else frame.targets)
        total = torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device).reshape(-1)
        for i in self.curved:
            col = self.contact.colliders[i]
            ye = frames[i][..., self.stencils, :]
            pairs = (self._bound(ye, col) < self.d_hat).reshape(-1).nonzero()[:, 0]  # (state, primitive) flattened
            if len(pairs):
                flat = ye.reshape(-1, *ye.shape[-2:])[pairs]
                b = barrier(col.primitive_distance(flat), self.d_hat, self.kappa, self.extend_below)
                total = total.index_add(0, pairs // ye.shape[-3], b)
        return total.reshape(x.shape[:-2])

    def distances(self, x: torch.Tensor, targets=None) -> torch.Tensor:
        """The signed distance of every primitive from its nearest curved collider, x (..., n, 3) -> (..., P)."""
        frames = self.contact._frames(x, targets)
        return torch.stack([self.contact.colliders[i].primitive_distance(frames[i][..., self.stencils, :]) for i in self.curved]).amin(0)

    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True, hessian: bool = True):
        """Per primitive (E, 3k) and (E, 3k, 3k) (None without ``hessian``; PSD-projected when ``project``), of the
        primitives within reach of a collider; zero for the rest."""
        E, k, _ = xe.shape
        g = torch.zeros(E, 3 * k, dtype=xe.dtype, device=xe.device)
        H = torch.zeros(E, 3 * k, 3 * k, dtype=xe.dtype, device=xe.device) if hessian else None
        near = torch.zeros(E, dtype=torch.bool)
        for i in self.curved:
            near |= self._bound(xe, self.contact.colliders[i]) < self.d_hat
        idx = near.nonzero()[:, 0]
        if not len(idx):
            return g, H
        y = xe[idx].detach().clone().requires_grad_(True)
        for i in self.curved:
            with torch.enable_grad():
                d = self.contact.colliders[i].primitive_distance(y)
                (grad_d,) = torch.autograd.grad(d.sum(), y)  # the primitives are independent: each one's grad d
            col, d = self.contact.colliders[i], d.detach()
            db, d2b = barrier_derivatives(d, self.d_hat, self.kappa, self.extend_below)
            gd = grad_d.reshape(len(idx), 3 * k)
            g[idx] += db[:, None] * gd
            if hessian:
                axis = torch.as_tensor((col.a, col.b), dtype=y.dtype) if isinstance(col, Capsule) else None
                Hd = distance_hessian(y.detach(), grad_d, d + float(col.radius), axis)
                H[idx] += d2b[:, None, None] * gd[:, :, None] * gd[:, None, :] + db[:, None, None] * Hd
        if hessian and project:
            H[idx] = project_psd(H[idx])
        return g, H

    def first_impact(self, x: np.ndarray, dx: np.ndarray, frame=None) -> float:
        """The first fraction t of the step x -> x + dx (n, 3) at which a primitive comes to a tenth of its starting
        distance from a curved collider (:func:`~latentsim.physics.primitives.primitive_toi`, conservative: the true
        impact is later); inf if none does within the step.  Moving colliders as :meth:`ContactBarrier.first_impact`."""
        c = self.contact
        starts = c.paths(x, dx, frame)
        st = self.stencils.numpy()
        t = math.inf
        for i in self.curved:
            y, dy = starts[i]
            ye, dye = torch.as_tensor(y[st]), torch.as_tensor(dy[st])
            # a primitive at least lb away moving at most `speed` over the step cannot close 0.9 of its distance, the
            # advancement's target, where 0.9 lb > speed: left out
            lb = self._bound(ye, c.colliders[i])
            can = 0.9 * lb <= torch.linalg.vector_norm(dye, dim=-1).amax(-1)
            if bool(can.any()):
                toi = primitive_toi(ye[can], dye[can], c.colliders[i].primitive_distance)
                t = min(t, float(toi.min()))
        return t
