"""Mesh preparation stage: from a scene's ``mesh`` and ``dirichlet`` config to mesh.h5 (and a VTU).

The mesh itself is made by :func:`latentsim.mesh.scene_mesh` (generate or
fetch and read, tetrahedralise, place, check, select the Dirichlet set); this
stage writes it, with the quality statistics as ``quality_*`` attributes
(and the gate applied, ``quality_gate_min_dihedral_deg``);
:func:`write_quality_table` gathers those of every scene into one table.
"""

from __future__ import annotations

import meshio
import numpy as np
import pandas as pd

from latentsim.io import atomic_h5, atomic_path, open_artefact, write_csv, write_dataset
from latentsim.mesh import scene_mesh
from latentsim.mesh.build import quality_gate
from latentsim.report.paraview import cells_for

#: the mesh quality table's columns after ``scene`` and ``model``: :func:`latentsim.mesh.check_mesh`'s
#: statistics (empty where a mesh has no such element) and the gate the mesh passed
QUALITY_COLUMNS = ("n_vertices", "n_tets", "n_triangles", "dihedral_min_deg", "dihedral_median_deg",
                   "dihedral_max_deg", "gate_min_dihedral_deg", "n_below_min_dihedral", "radius_edge_max",
                   "edge_ratio_max", "volume_ratio", "volume_total", "angle_min_deg", "area_total")


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
        if model == "tets":
            f.attrs["quality_gate_min_dihedral_deg"] = quality_gate(mesh_cfg)
    if out_vtu is not None:
        write_vtu(out_vtu, model, arrays, arrays["rest_positions"])
    return arrays


def write_quality_table(meshes: dict, out_csv) -> pd.DataFrame:
    """One row per scene of the quality statistics its ``mesh.h5`` records, as a CSV (atomic).

    Parameters
    ----------
    meshes : {scene: path of its mesh.h5}
    out_csv : the ``.csv`` to write: columns ``scene``, ``model``, then :data:`QUALITY_COLUMNS`
        (dihedral angles in degrees; ``radius_edge_max`` is circumradius / shortest edge, 0.612 for a
        regular tet; ``volume_ratio`` largest / smallest tet volume).
    """
    rows = []
    for scene, path in meshes.items():
        with open_artefact(path) as f:
            row = {"scene": scene, "model": str(f.attrs["model"])}
            for k in QUALITY_COLUMNS:
                v = f.attrs.get(f"quality_{k}")
                row[k] = v.item() if isinstance(v, np.generic) else v
        rows.append(row)
    df = pd.DataFrame(rows, columns=["scene", "model", *QUALITY_COLUMNS])
    write_csv(df, out_csv, index=False)
    return df


def write_vtu(path, model, arrays, positions, point_data=None):
    """One VTU file (atomic), e.g. the rest mesh with a Dirichlet marker."""
    mark = np.zeros(len(positions))
    mark[np.asarray(arrays["dirichlet"])] = 1.0
    pd = {"dirichlet": mark}
    pd.update(point_data or {})
    with atomic_path(path) as tmp:
        meshio.write(str(tmp), meshio.Mesh(np.asarray(positions), cells_for(model, arrays), point_data=pd), file_format="vtu")
