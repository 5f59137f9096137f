"""Mesh preparation stage: from a scene's ``mesh`` and ``dirichlet`` config to mesh.h5.

Procedural rods, cloth grids and tet beams are generated; files are fetched
(local folder or pinned URL with sha256), read, optionally tetrahedralised to a
target vertex count, scaled and rotated; the Dirichlet set is selected by a rule;
quality checks stop the stage with a message naming what and where.
"""

from __future__ import annotations

import logging

import meshio
import numpy as np

from latentsim import mesh as meshlib
from latentsim.io import atomic_h5, atomic_path, write_dataset

log = logging.getLogger(__name__)


def rod_stencils(n_rods: int, per_rod: int):
    """Edges (E,2), bending triples (B,3) and root_of (n,) for contiguous rods."""
    base = (np.arange(n_rods) * per_rod)[:, None]
    e = np.arange(per_rod - 1)
    edges = np.stack([base + e, base + e + 1], axis=-1).reshape(-1, 2)
    b = np.arange(per_rod - 2)
    triples = np.stack([base + b, base + b + 1, base + b + 2], axis=-1).reshape(-1, 3)
    root_of = np.repeat(base[:, 0], per_rod)
    return edges.astype(np.int64), triples.astype(np.int64), root_of.astype(np.int64)


def _rotation(axis, degrees):
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    t = np.deg2rad(degrees)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def build_mesh(model: str, cfg: dict, sources: dict) -> dict:
    """Arrays of a scene's mesh (before the Dirichlet selection).

    Parameters
    ----------
    model : 'rods' | 'shell' | 'tets'
    cfg : the scene's ``mesh`` config
    sources : the top-level ``meshes`` config (local_dir, cache_dir)
    """
    gen = cfg["generator"]
    out = {}
    if gen == "rod_bundle":
        if model != "rods":
            raise meshlib.MeshError(f"mesh.generator 'rod_bundle' needs model 'rods', not '{model}'")
        V, _, _ = meshlib.rod_bundle(cfg["n_rods"], cfg["vertices_per_rod"], cfg["length"], cfg["spacing"], cfg["direction"])
        out["edges"], out["triples"], out["root_of"] = rod_stencils(cfg["n_rods"], cfg["vertices_per_rod"])
    elif gen == "cloth_grid":
        V, out["triangles"] = meshlib.cloth_grid(cfg["nx"], cfg["ny"], cfg["width"], cfg["height"], plane=cfg["plane"])
    elif gen == "beam_tets":
        V, out["tets"] = meshlib.beam_tets(cfg["nx"], cfg["ny"], cfg["nz"], cfg["length"], cfg["width"], cfg["height"])
    elif gen == "file":
        path = meshlib.fetch_mesh(cfg["file"], local_dir=sources.get("local_dir"), cache_dir=sources["cache_dir"])
        m = meshlib.read_mesh(path)
        V = m.vertices
        if model == "tets":
            if m.tets is not None and cfg.get("target_vertices") in (None, 0):
                out["tets"] = m.tets
            else:
                surf = m.triangles if m.triangles is not None else meshlib.surface_of(m.tets)
                V, surf, _ = meshlib.remove_unreferenced(V, surf)
                V, out["tets"] = tetrahedralize_to(V, surf, int(cfg["target_vertices"]), str(path))
        elif model == "shell":
            if m.triangles is None:
                raise meshlib.MeshError(f"{path}: model 'shell' needs a triangle mesh")
            out["triangles"] = m.triangles
        else:
            raise meshlib.MeshError(f"{path}: model '{model}' cannot be read from a file; use generator rod_bundle")
    else:
        raise meshlib.MeshError(f"mesh.generator '{gen}' unknown")
    V = np.asarray(V, dtype=np.float64)
    if cfg.get("scale", 1.0) != 1.0:
        V = V * float(cfg["scale"])
    if cfg.get("rotate_degrees", 0.0):
        V = V @ _rotation(cfg["rotate_axis"], cfg["rotate_degrees"]).T
    if cfg.get("translate"):
        V = V + np.asarray(cfg["translate"], dtype=float)
    out["rest_positions"] = V
    return out


# the keys each selection rule reads (the config schema fills all of them with defaults)
RULE_KEYS = {"extreme": ("axis", "side", "fraction"), "sphere": ("center", "radius"), "box": ("min", "max"), "indices": ("indices",)}


def weld(V, F, tol: float):
    """Merge vertices closer than ``tol`` and drop the triangles that collapse.

    Quadric decimation leaves needle triangles between (almost) coincident
    vertices; TetGen turns those into zero-volume slivers.
    """
    from scipy.spatial import cKDTree

    rep = np.arange(len(V))
    for i, j in sorted(cKDTree(V).query_pairs(tol)):
        ri, rj = rep[i], rep[j]
        while rep[ri] != ri:
            ri = rep[ri]
        while rep[rj] != rj:
            rj = rep[rj]
        rep[max(ri, rj)] = min(ri, rj)
    for i in range(len(rep)):  # path compression
        r = i
        while rep[r] != r:
            r = rep[r]
        rep[i] = r
    F = rep[F]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    # two needles sharing an edge collapse into the same face twice with opposite orientation
    key = np.sort(F, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    F = F[np.sort(first[counts == 1])]
    V, F, _ = meshlib.remove_unreferenced(V, F)
    return V, F


def tetrahedralize_to(V, surf, target: int, name: str, tolerance: float = 0.05, runs: int = 8):
    """TetGen to about ``target`` vertices, decimating the surface if it alone has too many.

    TetGen never removes surface vertices, so a surface denser than the target
    is first simplified by quadric edge collapse (``fast_simplification``); the
    reduction is bisected until TetGen's output lies within ``tolerance`` of the
    target (or the closest run is kept).
    """
    V_t, T_t = meshlib.tetrahedralize(V, surf, target_vertices=target)
    if len(V_t) <= target * (1 + tolerance):
        return V_t, T_t
    import fast_simplification

    best = (V_t, T_t)
    lo, hi = 0.0, 0.95
    for _ in range(runs):
        r = 0.5 * (lo + hi)
        v2, f2 = fast_simplification.simplify(V, surf.astype(np.int32), target_reduction=r)
        v2, f2 = weld(np.asarray(v2, dtype=np.float64), np.asarray(f2, dtype=np.int64), 1e-7 * np.ptp(V, axis=0).max())
        try:
            meshlib.check_closed_surface(f2.astype(np.int64), name=f"{name} (decimated {r:.2f})")
            vv, tt = meshlib.tetrahedralize(v2.astype(np.float64), f2.astype(np.int64), target_vertices=target)
        except meshlib.MeshError as e:
            log.info("decimation %.3f of %s rejected: %s", r, name, e)
            hi = r
            continue
        if abs(len(vv) - target) < abs(len(best[0]) - target):
            best = (vv, tt)
        if len(vv) > target * (1 + tolerance):
            lo = r
        elif len(vv) < target * (1 - tolerance):
            hi = r
        else:
            break
    log.info("%s: %d vertices for a target of %d", name, len(best[0]), target)
    return best


def select_dirichlet(model: str, arrays: dict, rule: dict) -> np.ndarray:
    """Indices of the Dirichlet vertices.

    Rule {'type': 'roots'} selects each rod's root and, with ``clamp`` (the
    default), also the next vertex, so the root edge's direction is held:
    a clamped rod (hair in its follicle) rather than a pinned pendulum.
    """
    if rule["type"] == "roots":
        if "root_of" not in arrays:
            raise meshlib.MeshError("dirichlet rule 'roots' needs a rod scene")
        roots = np.unique(arrays["root_of"]).astype(np.int64)
        if rule.get("clamp", True):
            roots = np.union1d(roots, roots + 1)
        return roots
    keys = RULE_KEYS[rule["type"]]
    idx = meshlib.select_vertices(arrays["rest_positions"], {k: rule[k] for k in ("type",) + keys if k in rule})
    return np.asarray(idx, dtype=np.int64)


def prepare_mesh(scene: str, model: str, mesh_cfg: dict, dirichlet_rule: dict, sources: dict, out_h5, out_vtu=None):
    """Build, check and write ``mesh.h5`` (and a VTU for ParaView)."""
    arrays = build_mesh(model, mesh_cfg, sources)
    quality = meshlib.check_mesh(arrays["rest_positions"], tets=arrays.get("tets"), triangles=arrays.get("triangles"), name=scene)
    arrays["dirichlet"] = select_dirichlet(model, arrays, dirichlet_rule)
    if len(arrays["dirichlet"]) == 0:
        raise meshlib.MeshError(f"scene '{scene}': the Dirichlet rule {dirichlet_rule} selects no vertex")
    if model == "tets":
        arrays["surface"] = meshlib.surface_of(arrays["tets"])
    log.info("scene %s: %d vertices, %d Dirichlet; quality %s", scene, len(arrays["rest_positions"]), len(arrays["dirichlet"]), quality)
    cfg = {"model": model, "mesh": mesh_cfg, "dirichlet": dirichlet_rule}
    with atomic_h5(out_h5, config=cfg) as f:
        f.attrs["model"] = model
        f.attrs["scene"] = scene
        for k, v in arrays.items():
            write_dataset(f, k, v)
        for k, v in quality.items():
            if isinstance(v, (int, float, np.integer, np.floating)):
                f.attrs[f"quality_{k}"] = v
    if out_vtu is not None:
        write_vtu(out_vtu, model, arrays, arrays["rest_positions"])
    return arrays


def cells_for(model: str, arrays: dict):
    """meshio cell blocks of a model's elements."""
    if model == "rods":
        return [("line", np.asarray(arrays["edges"]))]
    if model == "shell":
        return [("triangle", np.asarray(arrays["triangles"]))]
    return [("tetra", np.asarray(arrays["tets"]))]


def write_vtu(path, model, arrays, positions, point_data=None):
    """One VTU file (atomic), e.g. the rest mesh with a Dirichlet marker."""
    mark = np.zeros(len(positions))
    mark[np.asarray(arrays["dirichlet"])] = 1.0
    pd = {"dirichlet": mark}
    pd.update(point_data or {})
    with atomic_path(path) as tmp:
        meshio.write(str(tmp), meshio.Mesh(np.asarray(positions), cells_for(model, arrays), point_data=pd), file_format="vtu")
