"""Scenes as data: the boundary-condition program and the physical model.

A scene is a mesh (``results/mesh/{scene}/mesh.h5``), a model (``rods``,
``shell`` or ``tets``), a material, a time step, gravity, a Dirichlet vertex
set and a list of sequences, each driving the Dirichlet set by a rigid-motion
program.  Nothing about a particular scene is code.

Boundary-condition program
--------------------------
The Dirichlet vertices move rigidly: at frame t their positions are

    x*_D(t) = R(t) (X_D - c_0) + c(t),
    c(t) = c(t-1) + v_t dt,       R(t) = exp(dt [w_t]_x) R(t-1),

starting from rest (c(0) = c_0, the centroid of X_D; R(0) = I).  The linear
velocity v_t [m/s] and angular velocity w_t [rad/s] are piecewise constant:
``segments`` is a list of ``{start, velocity, angular_velocity}`` and each
segment holds from its ``start`` frame on; ``reverse_every`` = N flips the sign
of both every N frames.  The boundary-condition parameters stored per frame,
and fed to the latent integrator, are p_t = [v_t, w_t] (k = 6).
"""

from __future__ import annotations

import json

import numpy as np
import torch

from latentsim.mesh.build import collider_mesh
from latentsim.mesh.surface import surface_of
from latentsim.physics import rods, shells, tets
from latentsim.physics.materials import MATERIALS, material_model
from latentsim.physics.colliders import Capsule, HalfSpace, Sphere, posed_colliders
from latentsim.physics.contact import ContactBarrier
from latentsim.physics.mesh_contact import TriangleMesh
from latentsim.physics.incremental_potential import ElasticPotential, IncrementalPotential

BC_DIM = 6


def _rotation(w: np.ndarray, dt: float) -> np.ndarray:
    """exp(dt [w]_x) by Rodrigues' formula."""
    theta = float(np.linalg.norm(w)) * dt
    if theta < 1e-15:
        return np.eye(3)
    k = np.asarray(w, dtype=float) / np.linalg.norm(w)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def bc_parameters(sequence: dict, frames: int) -> np.ndarray:
    """Per-frame p_t = [v_t, w_t], (frames, 6); p_0 = 0 (the scene starts at rest)."""
    segments = sorted(sequence.get("segments", []), key=lambda s: s.get("start", 0))
    reverse = int(sequence.get("reverse_every", 0) or 0)
    p = np.zeros((frames, BC_DIM))
    for t in range(1, frames):
        active = None
        for seg in segments:
            if seg.get("start", 0) <= t:
                active = seg
        if active is None:
            continue
        v = np.asarray(active.get("velocity", [0, 0, 0]), dtype=float)
        w = np.asarray(active.get("angular_velocity", [0, 0, 0]), dtype=float)
        sign = -1.0 if reverse and ((t - 1) // reverse) % 2 == 1 else 1.0
        p[t, :3] = sign * v
        p[t, 3:] = sign * w
    return p


def initial_velocity(sequence: dict) -> np.ndarray | None:
    """A free body's rigid velocity at frame 0, [v, w] (6,), from a sequence's ``initial_velocity`` and
    ``initial_angular_velocity``; None when it sets neither (the scene starts at rest)."""
    keys = ("initial_velocity", "initial_angular_velocity")
    if not any(k in sequence for k in keys):
        return None
    return np.concatenate([np.asarray(sequence.get(k, [0.0, 0.0, 0.0]), dtype=float) for k in keys])


def previous_positions(x0: np.ndarray, masses: np.ndarray, velocity, dt: float) -> np.ndarray:
    """x_{-1}, the state one time step before frame 0 (n, 3): x_0 itself at rest (``velocity`` None), else
    x_0 - dt (v + w x (x_0 - c)) with c the centre of mass, so that frame 1's inertia starts the body with
    the rigid velocity [v, w]."""
    x0 = np.asarray(x0, dtype=float)
    if velocity is None:
        return x0.copy()
    m = np.asarray(masses, dtype=float)
    c = (m[:, None] * x0).sum(0) / m.sum()
    v = velocity[:3] + np.cross(velocity[3:], x0 - c)
    return x0 - dt * v


def dirichlet_trajectory(rest_D: np.ndarray, p: np.ndarray, dt: float) -> np.ndarray:
    """Prescribed positions (T, m, 3) of the Dirichlet vertices from p (T, 6)."""
    rest_D = np.asarray(rest_D, dtype=float)
    if len(rest_D) == 0:  # a free body: nothing prescribed
        return np.zeros((len(p), 0, 3))
    c0 = rest_D.mean(axis=0)
    local = rest_D - c0
    c = c0.copy()
    R = np.eye(3)
    out = np.empty((len(p),) + rest_D.shape)
    out[0] = rest_D
    for t in range(1, len(p)):
        c = c + p[t, :3] * dt
        R = _rotation(p[t, 3:], dt) @ R
        out[t] = local @ R.T + c
    return out


def dirichlet_step(xD_prev: torch.Tensor, p: torch.Tensor, dt) -> torch.Tensor:
    """One step of the boundary-condition program, batched: the prescribed positions at frame t
    from those at frame t-1, ``p`` = p_t and the time step ``dt``.

    The Dirichlet set's centroid is c(t-1), so x*_D(t) = exp(dt [w_t]_x) (x*_D(t-1) - c(t-1)) +
    c(t-1) + v_t dt, the step :func:`dirichlet_trajectory` takes.

    xD_prev : (B, m, 3); p : (B, 6); dt : float or (B,) -> (B, m, 3) in xD_prev's dtype.
    """
    dtype = xD_prev.dtype
    p = p.to(dtype)
    h = torch.as_tensor(dt, dtype=dtype, device=xD_prev.device).reshape(-1, 1)
    c = xD_prev.mean(-2, keepdim=True)
    rot = p[:, 3:] * h
    theta = torch.linalg.vector_norm(rot, dim=-1)
    k = rot / theta.clamp_min(1e-300)[:, None]
    K = torch.zeros(p.shape[0], 3, 3, dtype=dtype, device=xD_prev.device)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - K.transpose(1, 2)
    s, co = torch.sin(theta)[:, None, None], (1.0 - torch.cos(theta))[:, None, None]
    R = torch.eye(3, dtype=dtype, device=xD_prev.device) + s * K + co * (K @ K)
    return (xD_prev - c) @ R.transpose(1, 2) + c + (p[:, :3] * h)[:, None, :]


# --- the physical model -------------------------------------------------------


def build_elastic(model: str, arrays: dict, material: dict, free_only: bool = False) -> ElasticPotential:
    """ElasticPotential of a scene (its elastic terms, lumped masses, Dirichlet set) from its mesh
    arrays and material: the elastic energy alone, with no time step or gravity.

    Parameters
    ----------
    model : 'rods' | 'shell' | 'tets'
    arrays : dict with 'rest_positions' (n,3), 'dirichlet' (m,), and the
        element arrays of the model: 'edges' and 'triples' (rods), 'triangles'
        (shell), 'tets'.
    material : youngs_modulus [Pa], poisson_ratio, density [kg/m^3], and
        radius [m] (rods) or thickness [m] (shell); optionally ``model``, a
        material of ``physics.materials`` ('stvk', the default; 'stvk_nm': the
        Neural Modes authors' membrane, hinge and tets, ``physics.stvk_nm``;
        'neohookean', tets only: stable neo-Hookean, ``physics.neohookean``;
        see ``materials.materials_of``) and, for stvk_nm shells, ``bending_stiffness``
        kB [N m] (default D/2).
    free_only : drop the elastic stencils whose vertices are all Dirichlet.
        Their energy is then a constant, so the full-space solver (which
        prescribes the Dirichlet vertices exactly) loses nothing; losses and
        metrics, where decoded Dirichlet vertices may move, need them all.
        Masses always come from every element.
    """
    X = torch.as_tensor(np.asarray(arrays["rest_positions"], dtype=np.float64))
    fixed = np.zeros(len(X), dtype=bool)
    fixed[np.asarray(arrays["dirichlet"], dtype=np.int64)] = True

    def active(stencils):
        """The stencils the solver needs: all of them, or those touching a free vertex."""
        if not free_only:
            return stencils
        keep = ~fixed[np.asarray(stencils)].all(axis=1)
        return stencils[torch.as_tensor(keep)]

    law = material_model(model, material)
    stencils, masses = _model_stencils(model, arrays, X, material)
    terms = MATERIALS[law][model].terms(X, {k: active(v) for k, v in stencils.items()}, material)
    return ElasticPotential(
        terms=terms,
        masses=torch.as_tensor(masses, dtype=torch.float64),
        dirichlet=torch.as_tensor(np.asarray(arrays["dirichlet"], dtype=np.int64)),
    )


def _model_stencils(model: str, arrays: dict, X: torch.Tensor, material: dict):
    """The stencils of a model kind (``materials.MODEL_STENCILS``) from its element arrays, and its
    lumped masses (from every element)."""
    rho = float(material["density"])
    if model == "rods":
        edges = torch.as_tensor(np.asarray(arrays["edges"], dtype=np.int64))
        triples = torch.as_tensor(np.asarray(arrays["triples"], dtype=np.int64))
        return {"edges": edges, "triples": triples}, rods.lumped_masses_rods(X, edges, rho, float(material["radius"]))
    if model == "shell":
        tris = torch.as_tensor(np.asarray(arrays["triangles"], dtype=np.int64))
        masses = shells.lumped_masses_shell(X, tris, rho, float(material["thickness"]))
        return {"triangles": tris, "hinges": shells.hinges_from_triangles(tris)}, masses
    T = torch.as_tensor(np.asarray(arrays["tets"], dtype=np.int64))
    return {"tets": T}, tets.lumped_masses(X, T, rho)


def build_potential(model: str, arrays: dict, material: dict, dt: float, gravity, w_bc: float = 1e5, free_only: bool = False,
                    contact: dict | None = None):  # fmt: skip
    """IncrementalPotential of a scene: :func:`build_elastic` (same arguments) with the time
    step ``dt`` [s], ``gravity`` (3,) [m/s^2], the Dirichlet penalty weight ``w_bc`` and the
    colliders of ``contact`` (a scene's ``contact`` block, :func:`contact_settings`)."""
    elastic = build_elastic(model, arrays, material, free_only=free_only)
    g = torch.as_tensor(np.asarray(gravity, dtype=np.float64))
    barrier = None
    if contact and contact.get("colliders"):
        c = contact_settings(contact, arrays["rest_positions"], elastic.masses.numpy(), g.numpy(), own_thickness(model, material))
        barrier = contact_barrier(c, elastic.n_vertices, arrays["rest_positions"], arrays.get("dirichlet", ()), dt, surface_primitives(model, arrays),
                                  collider_meshes(arrays))  # fmt: skip
    return IncrementalPotential(
        terms=elastic.terms,
        masses=elastic.masses,
        dirichlet=elastic.dirichlet,
        dt=float(dt),
        g=g,
        w_bc=float(w_bc),
        contact=barrier,
    )


#: IPC's velocity below which friction is static [m/s], where a scene's ``contact.friction_velocity`` is unset
FRICTION_VELOCITY = 1e-3

#: the analytic colliders a scene's ``contact.colliders`` may list, by ``type``
COLLIDERS = {"half_space": (HalfSpace, ("point", "normal")), "sphere": (Sphere, ("centre", "radius")), "capsule": (Capsule, ("a", "b", "radius"))}


def collider(q: dict):
    """The collider of one ``contact.colliders`` entry (``type`` and the shape's keys) at rest."""
    cls, keys = COLLIDERS[q["type"]]
    return cls(*(q[k] for k in keys))


#: a mesh collider's surface, as a scene's arrays (and its trajectories file) hold it: the entry's index in ``contact.colliders``
COLLIDER_MESH_KEYS = ("collider{}_vertices", "collider{}_triangles")


def collider_meshes(arrays) -> dict:
    """The mesh colliders' surfaces that ``arrays`` (a dict, or an open h5py.File) hold, {index in contact.colliders: (V, F)}."""
    out = {}
    for key in arrays.keys():
        if key.startswith("collider") and key.endswith("_vertices"):
            i = int(key[len("collider") : -len("_vertices")])
            out[i] = tuple(np.asarray(arrays[k.format(i)][()]) for k in COLLIDER_MESH_KEYS)
    return out


def load_collider_meshes(contact: dict | None, sources: dict, scene: str) -> dict:
    """The arrays of a scene's mesh colliders (:data:`COLLIDER_MESH_KEYS`), each read from its ``file``
    (:func:`~latentsim.mesh.collider_mesh`); none for a scene without."""
    out = {}
    for i, q in enumerate((contact or {}).get("colliders") or ()):
        if q["type"] == "mesh":
            V, F = collider_mesh(q, sources, where=f"scenes.{scene}.contact.colliders.{i}")
            out.update(zip((k.format(i) for k in COLLIDER_MESH_KEYS), (V, F)))
    return out


def own_thickness(model: str, material: dict) -> float:
    """How far a scene's surface reaches beyond its vertices, where ``contact.thickness`` is unset: half a
    shell's ``material.thickness``, a strand's ``material.radius``, 0 for a solid (its vertices are its surface)."""
    if model == "shell":
        return 0.5 * float(material["thickness"])
    if model == "rods":
        return float(material["radius"])
    return 0.0


def surface_primitives(model: str, arrays: dict):
    """The primitives of a model's surface that contact holds out of a curved collider: a strand's edges (P, 2), a
    shell's triangles, a solid's boundary triangles (its ``surface``, or those of its tets) (P, 3)."""
    if model == "rods":
        return np.asarray(arrays["edges"], dtype=np.int64)
    if model == "shell":
        return np.asarray(arrays["triangles"], dtype=np.int64)
    if "surface" in arrays:
        return np.asarray(arrays["surface"], dtype=np.int64)
    return surface_of(np.asarray(arrays["tets"], dtype=np.int64))


def contact_barrier(contact: dict, n_vertices: int, rest_positions, dirichlet, dt: float, primitives=None, meshes=None) -> ContactBarrier:
    """The barrier of a resolved ``contact`` block (:func:`contact_settings`): its colliders, thickened by its
    ``thickness`` (absent: 0; :meth:`~latentsim.physics.colliders.Collider.thickened`), those with
    ``attached: true`` moving rigidly with the prescribed vertices ``dirichlet`` (indices into
    ``rest_positions``), its friction (static below a slip of ``friction_velocity`` times the time step
    ``dt``), and the surface's ``primitives`` (:func:`surface_primitives`; None: the vertices alone).  A ``mesh`` entry's
    surface is ``meshes`` {its index: (V, F)} (:func:`collider_meshes`); the barrier lists the analytic colliders, then the meshes.
    ``self_contact: true``: the surface is also held off itself, its parts twice the thickness apart."""
    analytic = [q for q in contact["colliders"] if q["type"] != "mesh"]
    attached = [bool(q.get("attached", False)) for q in analytic]
    rest_D = np.asarray(rest_positions, dtype=float)[np.asarray(dirichlet, dtype=np.int64)] if any(attached) else None
    mu = float(contact.get("friction", 0.0))
    slip = float(contact.get("friction_velocity", FRICTION_VELOCITY)) * float(dt) if mu > 0 else None
    try:
        thickness = float(contact.get("thickness", 0.0))
        shapes = [collider(q).thickened(thickness) for q in analytic]
        bodies = []
        for i, q in enumerate(contact["colliders"]):
            if q["type"] == "mesh":
                if i not in (meshes or {}):
                    raise ValueError(f"entry {i} is a mesh ({q.get('file')}) whose surface was not read (its arrays {COLLIDER_MESH_KEYS[0].format(i)})")
                bodies.append(TriangleMesh(*meshes[i], thickness=thickness))
        own = 2 * thickness if contact.get("self_contact") else None  # two parts of the surface, each reaching out its thickness
        if own is not None and primitives is None:
            raise ValueError("self_contact: the scene's model has no surface of edges or triangles to hold off itself")
        return ContactBarrier(n_vertices, shapes, contact["d_hat"], contact["kappa"], attached=attached, rest_dirichlet=rest_D,
                              friction=mu, slip=slip, primitives=primitives, meshes=bodies, self_contact=own)  # fmt: skip
    except ValueError as e:
        raise ValueError(f"contact.colliders: {e}") from None


def posed_collider_entries(entries, rest_dirichlet, targets) -> list[dict]:
    """A scene's ``contact.colliders`` entries where they stand when the prescribed vertices (rest positions
    ``rest_dirichlet`` (m, 3)) are at ``targets`` (m, 3): every attached one carried by their rigid motion
    (:func:`~latentsim.physics.colliders.posed_colliders`), the static ones as they are."""
    attached = [bool(q.get("attached")) for q in entries]
    if not any(attached):
        return list(entries)
    moved = iter(posed_colliders([collider(q) for q in entries if q["type"] != "mesh"], [a for q, a in zip(entries, attached) if q["type"] != "mesh"],
                                 rest_dirichlet, targets))  # fmt: skip
    out = []
    for q, a in zip(entries, attached):
        m = next(moved) if q["type"] != "mesh" else None
        out.append({**q, **{k: list(getattr(m, k)) for k in m.points + m.directions}} if a else q)
    return out


def contact_settings(contact: dict, rest_positions, masses, gravity, own: float = 0.0) -> dict:
    """A scene's ``contact`` block with its defaults resolved: ``d_hat`` (null: 1e-3 of the rest
    bounding-box diagonal, IPC's default) and ``kappa`` (null: 100 m_max |g| / d_hat, so that the
    barrier holds a vertex pressed with 119 times the heaviest vertex's weight at d_hat / 2); with
    ``friction``, its ``friction_velocity`` (unset: :data:`FRICTION_VELOCITY`); ``thickness`` (null: ``own``,
    the scene's :func:`own_thickness`), recorded where it or ``own`` is not 0 (a solid's block resolves as it
    did before thickness existed)."""
    rest = np.asarray(rest_positions, dtype=float)
    d_hat = contact.get("d_hat") or 1e-3 * float(np.linalg.norm(rest.max(0) - rest.min(0)))
    kappa = contact.get("kappa") or 100.0 * float(np.max(masses)) * max(float(np.linalg.norm(gravity)), 1.0) / d_hat
    out = {"colliders": list(contact["colliders"]), "d_hat": float(d_hat), "kappa": float(kappa)}
    thickness = own if contact.get("thickness") is None else float(contact["thickness"])
    if thickness or own:
        out["thickness"] = float(thickness)
    if contact.get("self_contact"):  # (likewise without self-contact)
        out["self_contact"] = True
    if contact.get("friction"):  # (a frictionless block resolves as it did before friction existed)
        out.update(friction=float(contact["friction"]), friction_velocity=float(contact.get("friction_velocity") or FRICTION_VELOCITY))
    return out


MATERIAL_KEYS = ("youngs_modulus", "poisson_ratio", "density", "thickness", "radius", "bending_stiffness")
# the material model is a string, stored as the attribute ``material_model`` (``model`` is the scene's)
MATERIAL_MODEL_ATTR = "material_model"
ELEMENT_KEYS = ("edges", "triples", "triangles", "tets", "root_of")
# the resolved contact block (contact_settings), as JSON
CONTACT_ATTR = "contact"


def contact_from_artefact(f) -> ContactBarrier | None:
    """The contact barrier a trajectories.h5 (open h5py.File) records (its resolved ``contact``
    block), or None for a scene without colliders."""
    if CONTACT_ATTR not in f.attrs:
        return None
    c = json.loads(str(f.attrs[CONTACT_ATTR]))
    arrays = {k: f[k][()] for k in ELEMENT_KEYS + ("surface",) if k in f}
    return contact_barrier(c, len(f["rest_positions"]), f["rest_positions"][()], f["dirichlet"][()] if "dirichlet" in f else (), float(f.attrs["dt"]),
                           surface_primitives(str(f.attrs["model"]), arrays), collider_meshes(f))  # fmt: skip


def potential_from_artefact(f, w_bc: float = 1e5, free_only: bool = False) -> IncrementalPotential:
    """Rebuild the IncrementalPotential from a trajectories.h5 (open h5py.File).

    ``free_only``: drop the stencils whose vertices are all prescribed, as the
    full-space solver does (see :func:`build_potential`).
    """
    arrays = {k: f[k][()] for k in ("rest_positions", "dirichlet") + ELEMENT_KEYS if k in f}
    arrays.update({k: f[k][()] for k in f.keys() if k.startswith("collider")})
    material = {k: float(f.attrs[k]) for k in MATERIAL_KEYS if k in f.attrs}
    if MATERIAL_MODEL_ATTR in f.attrs:
        material["model"] = str(f.attrs[MATERIAL_MODEL_ATTR])
    contact = json.loads(str(f.attrs[CONTACT_ATTR])) if CONTACT_ATTR in f.attrs else None
    return build_potential(str(f.attrs["model"]), arrays, material, float(f.attrs["dt"]), f.attrs["gravity"], w_bc, free_only=free_only, contact=contact)
