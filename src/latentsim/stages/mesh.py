"""Mesh preparation stage: from a scene's ``mesh`` and ``dirichlet`` config to mesh.h5 (and a VTU).

The mesh itself is made by :func:`latentsim.mesh.scene_mesh` (generate or
fetch and read, tetrahedralise, place, check, select the Dirichlet set); this
stage writes it, with the quality statistics as ``quality_*`` attributes.
"""

from __future__ import annotations

import meshio
import numpy as np

from latentsim.io import atomic_h5, atomic_path, write_dataset
from latentsim.mesh import scene_mesh


def prepare_mesh(scene: str, model: str, mesh_cfg: dict, dirichlet_rule: dict, sources: dict,
                 out_h5, out_vtu=None) -> dict:
    """Build, check and write ``mesh.h5`` (and a VTU for ParaView); returns the arrays written."""
    arrays, quality = scene_mesh(scene, model, mesh_cfg, dirichlet_rule, sources)
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
