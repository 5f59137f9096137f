"""A scene's rest mesh from its config: generate or fetch and read, tetrahedralise, place, select.

The config is the scene's ``mesh`` mapping (``generator``: ``rod_bundle``,
``cloth_grid``, ``beam_tets`` or ``file``, the generator's sizes, and
``scale``/``rotate_axis``/``rotate_degrees``/``translate``), its ``dirichlet``
rule and the top-level ``meshes`` sources (``local_dir``, ``cache_dir``).
The result is the dict of arrays the mesh stage writes to ``mesh.h5``.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from latentsim.mesh.generators import beam_tets, cloth_grid, rod_bundle, rod_stencils
from latentsim.mesh.geometry import remove_unreferenced
from latentsim.mesh.quality import check_mesh
from latentsim.mesh.readers import read_mesh
from latentsim.mesh.selection import select_dirichlet
from latentsim.mesh.sources import mesh_file
from latentsim.mesh.surface import surface_of
from latentsim.mesh.tetgen import tetrahedralize_to
from latentsim.mesh.transform import place
from latentsim.mesh.validation import MeshError

logger = logging.getLogger(__name__)


def _tetgen_quality(q: dict) -> tuple[float, float] | None:
    """TetGen's (radius-edge ratio, min dihedral) bounds of ``mesh.quality``, None when off."""
    if not q.get("tetgen", True):
        return None
    return float(q.get("radius_edge", 2.0)), float(q.get("min_dihedral_deg", 10.0))


#: the default gate on the smallest dihedral angle [degrees] of a mesh the pipeline makes
GATE_MIN_DIHEDRAL_DEG = 5.0
#: the default gate for a file's own tets, kept as they are (the Neural Modes meshes have
#: 0.23 and 0.50 degrees)
GATE_MIN_DIHEDRAL_DEG_FILE_TETS = 0.01


#: a ``mesh.target_vertices`` above this is warned of in the mesh stage's log (the schema's maximum is 50000)
LARGE_TARGET_VERTICES = 10_000


def quality_gate(cfg: dict) -> float:
    """The smallest dihedral angle [degrees] a scene's tets may have (0: no gate).

    ``mesh.quality.gate_min_dihedral_deg`` when set; otherwise
    :data:`GATE_MIN_DIHEDRAL_DEG_FILE_TETS` for a file's own tets
    (``generator: file``, ``target_vertices`` 0) and :data:`GATE_MIN_DIHEDRAL_DEG`
    for tets the pipeline makes (TetGen, ``beam_tets``).
    """
    gate = (cfg.get("quality") or {}).get("gate_min_dihedral_deg")
    if gate is not None:
        return float(gate)
    if cfg.get("generator") == "file" and not cfg.get("target_vertices"):
        return GATE_MIN_DIHEDRAL_DEG_FILE_TETS
    return GATE_MIN_DIHEDRAL_DEG


def _from_file(model: str, cfg: dict, sources: dict) -> dict[str, np.ndarray]:
    """``rest_positions`` and the model's cells of the scene's mesh file.

    A tet model keeps the file's tets unless ``target_vertices`` is set (> 0);
    then the file's surface is tetrahedralised to about that many vertices.
    """
    if not cfg.get("file"):
        raise MeshError("mesh.generator 'file' needs mesh.file (a pinned mesh name or a path)")
    path = mesh_file(cfg["file"], sources, sha256=cfg.get("sha256"))
    m = read_mesh(path)
    out = {"rest_positions": m.vertices}
    if model == "tets":
        if m.tets is not None and cfg.get("target_vertices") in (None, 0):
            out["tets"] = m.tets
        else:
            if not cfg.get("target_vertices"):
                raise MeshError(
                    f"{path}: a surface (triangles, no tets); model 'tets' fills it with tets by "
                    f"TetGen: set mesh.target_vertices (> 0) to the vertex count wanted")
            surf = m.triangles if m.triangles is not None else surface_of(m.tets)
            V, surf, _ = remove_unreferenced(m.vertices, surf)
            try:
                out["rest_positions"], out["tets"] = tetrahedralize_to(
                    V, surf, int(cfg["target_vertices"]), str(path),
                    quality=_tetgen_quality(cfg.get("quality") or {}),
                    remesh=bool((cfg.get("quality") or {}).get("remesh", True)))
            except MeshError as exc:  # name the file where the message does not
                if str(path) in str(exc):
                    raise
                raise MeshError(f"{path}: cannot fill with tets: {exc}") from exc
    elif model == "shell":
        if m.triangles is None:
            raise MeshError(f"{path}: model 'shell' needs a triangle mesh")
        out["triangles"] = m.triangles
    else:
        raise MeshError(
            f"{path}: model '{model}' cannot be read from a file; use generator rod_bundle")
    return out


def _generated(model: str, cfg: dict) -> dict[str, np.ndarray]:
    """``rest_positions`` and the cells of a procedural mesh (rods also: triples, root_of)."""
    gen = cfg["generator"]
    out = {}
    if gen == "rod_bundle":
        if model != "rods":
            raise MeshError(f"mesh.generator 'rod_bundle' needs model 'rods', not '{model}'")
        out["rest_positions"], _, _ = rod_bundle(cfg["n_rods"], cfg["vertices_per_rod"],
                                                 cfg["length"], cfg["spacing"], cfg["direction"],
                                                 ring_radius=cfg.get("ring_radius"))
        out["edges"], out["triples"], out["root_of"] = rod_stencils(cfg["n_rods"],
                                                                    cfg["vertices_per_rod"])
    elif gen == "cloth_grid":
        out["rest_positions"], out["triangles"] = cloth_grid(
            cfg["nx"], cfg["ny"], cfg["width"], cfg["height"], plane=cfg["plane"])
    elif gen == "beam_tets":
        out["rest_positions"], out["tets"] = beam_tets(
            cfg["nx"], cfg["ny"], cfg["nz"], cfg["length"], cfg["width"], cfg["height"])
    else:
        raise MeshError(f"mesh.generator '{gen}' unknown")
    return out


def build_mesh(model: str, cfg: dict, sources: dict) -> dict[str, np.ndarray]:
    """Arrays of a scene's mesh (before the Dirichlet selection).

    Parameters
    ----------
    model : 'rods' | 'shell' | 'tets'
    cfg : the scene's ``mesh`` config
    sources : the top-level ``meshes`` config (local_dir, cache_dir)

    Returns
    -------
    dict: the model's cells (``edges``, ``triples``, ``root_of`` for rods;
    ``triangles`` for shells; ``tets`` for tets), then ``rest_positions``
    (n, 3) float64 after ``scale``, ``rotate_degrees`` about ``rotate_axis``
    and ``translate``.
    """
    out = _from_file(model, cfg, sources) if cfg["generator"] == "file" else _generated(model, cfg)
    V = out.pop("rest_positions")
    out["rest_positions"] = place(V, cfg.get("scale", 1.0), cfg.get("rotate_axis"),
                                  cfg.get("rotate_degrees", 0.0), cfg.get("translate"))
    return out


def generated_diagonal(model: str, cfg: dict) -> float | None:
    """The rest bounding-box diagonal [m] of a generated mesh, placed (``scale``, rotation, ``translate``), from
    its config alone; None for a file's (known once it is read) or a config :func:`build_mesh` refuses.

    The coarsest mesh of the same shape has the same box: a grid's vertices lie in the convex hull of its
    corners and a rod's on the segment between its ends, which every resolution keeps, so one cell per axis and
    two vertices per rod suffice, whatever the placement.
    """
    if cfg.get("generator") == "file":
        return None
    try:
        V = build_mesh(model, {**cfg, "nx": 1, "ny": 1, "nz": 1, "vertices_per_rod": 2}, {})["rest_positions"]
    except MeshError:
        return None
    return float(np.linalg.norm(V.max(0) - V.min(0)))


def scene_mesh(scene: str, model: str, mesh_cfg: dict, dirichlet_rule: dict,
               sources: dict) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A scene's checked mesh with its Dirichlet set (and, for tets, its surface).

    Returns
    -------
    arrays : :func:`build_mesh`'s arrays plus ``dirichlet`` (k,) int64 and,
        for tets, ``surface`` (t, 3) int64.
    quality : :func:`check_mesh`'s statistics.

    Raises
    ------
    MeshError
        A quality problem (a tet's dihedral angle below :func:`quality_gate`
        included) or an empty Dirichlet
        set, naming the scene.
    """
    if model == "tets" and mesh_cfg.get("generator") == "file" and int(mesh_cfg.get("target_vertices") or 0) > LARGE_TARGET_VERTICES:
        logger.warning("scene %s: mesh.target_vertices %d is above %d: remeshing and TetGen may take many minutes (2e5 took 14.5), "
                       "and every later stage grows with the vertex count", scene, int(mesh_cfg["target_vertices"]), LARGE_TARGET_VERTICES)
    arrays = build_mesh(model, mesh_cfg, sources)
    gate = quality_gate(mesh_cfg)
    quality = check_mesh(arrays["rest_positions"], tets=arrays.get("tets"),
                         triangles=arrays.get("triangles"), name=scene,
                         min_dihedral_deg=gate if gate > 0 else None)
    arrays["dirichlet"] = select_dirichlet(arrays["rest_positions"], dirichlet_rule,
                                           arrays.get("root_of"))
    if len(arrays["dirichlet"]) == 0 and dirichlet_rule["type"] != "free":
        raise MeshError(f"scene '{scene}': the Dirichlet rule {dirichlet_rule} selects no vertex")
    if model == "tets":
        arrays["surface"] = surface_of(arrays["tets"])
    logger.info("scene %s: %d vertices, %d Dirichlet; quality %s", scene,
                len(arrays["rest_positions"]), len(arrays["dirichlet"]), quality)
    return arrays, quality


def collider_mesh(entry: dict, sources: dict, where: str = "contact.colliders") -> tuple[np.ndarray, np.ndarray]:
    """A mesh collider's surface where it stands, vertices (m, 3) [m] and triangles (f, 3): its ``file`` (a pinned mesh's
    name or the user's own, found as ``mesh.file`` is) read, a tet mesh's boundary taken, and placed by its ``scale``,
    ``rotate_axis`` / ``rotate_degrees`` and ``translate`` (:func:`~latentsim.mesh.transform.place`)."""
    path = mesh_file(entry["file"], sources, sha256=entry.get("sha256"), where=f"{where}.file")
    m = read_mesh(path)
    triangles = m.triangles if m.triangles is not None else (surface_of(m.tets) if m.tets is not None else None)
    if triangles is None or not len(triangles):
        raise MeshError(f"{path} ({where}): a mesh collider needs triangles (or tets), the file has neither")
    V, triangles, _ = remove_unreferenced(m.vertices, triangles)
    V = place(V, float(entry.get("scale", 1.0)), entry.get("rotate_axis"), float(entry.get("rotate_degrees", 0.0)), entry.get("translate"))
    return V, np.asarray(triangles, dtype=np.int64)
