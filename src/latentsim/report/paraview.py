"""ParaView series of any trajectory file: XDMF + HDF5 time series with displacement and error fields.

:func:`write_xdmf_series` writes one sequence of a trajectory-layout file
(:mod:`latentsim.report.motion`) on its rest mesh (rod edges as lines, shell
triangles, tetrahedra), one time step per frame, with the point fields
``displacement`` (positions minus rest; ParaView: *Warp By Vector*),
``dirichlet`` (1 on prescribed vertices) and, against a reference file, the
per-vertex ``error``.  :func:`single_block_xdmf` makes any of meshio's XDMF time series hold the
animation alone (meshio adds a static copy of the mesh, which ParaView draws over the animation).
"""

from __future__ import annotations

import os
import shutil
import copy
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np

from latentsim.io import ArtefactError, atomic_path, open_artefact, require
from latentsim.report.motion import load_motion, model_of
from latentsim.utils import working_directory

__all__ = ["cells_for", "single_block_xdmf", "write_xdmf_series"]


def cells_for(model: str, arrays: dict):
    """meshio cell blocks of a model's elements (a mesh artefact's ``edges``, ``triangles`` or ``tets``)."""
    if model == "rods":
        return [("line", np.asarray(arrays["edges"]))]
    if model == "shell":
        return [("triangle", np.asarray(arrays["triangles"]))]
    return [("tetra", np.asarray(arrays["tets"]))]


def single_block_xdmf(path) -> int:
    """Rewrite a meshio XDMF time series in place so that ParaView reads one block: the animation.

    meshio's ``TimeSeriesWriter`` stores the mesh once, as a static grid named ``mesh`` beside the temporal
    collection, and each time step includes that grid's geometry and topology by XPointer.  ParaView reads
    the static grid as a block of its own, drawn over the animation at rest.  Here every time step holds
    the geometry and topology itself (the same HDF5 datasets: a few lines of XML a step, no data copied) and
    the static grid is removed.  meshio's ``TimeSeriesReader`` reads the result (it takes the mesh from the
    first step).  Returns the number of time steps.

    Raises ``ValueError`` naming the file when it is not such a series (no temporal collection, or no mesh
    grid to take the geometry and topology from); a file already rewritten is left as it is.
    """
    path = Path(path)
    tree = ET.parse(path)
    domain = tree.getroot().find("Domain")
    grids = [] if domain is None else domain.findall("Grid")
    series = [g for g in grids if g.get("GridType") == "Collection" and g.get("CollectionType") == "Temporal"]
    static = [g for g in grids if g.get("GridType", "Uniform") == "Uniform"]
    if len(series) != 1:
        raise ValueError(f"{path}: expected one temporal collection in the XDMF domain, found {len(series)}")
    steps = series[0].findall("Grid")
    if not static:
        if steps and all(s.find("Geometry") is not None for s in steps):
            return len(steps)  # already one block
        raise ValueError(f"{path}: no static mesh grid to take the geometry and topology from")
    if len(static) != 1:
        raise ValueError(f"{path}: expected one static mesh grid, found {len(static)}")
    shared = [copy.deepcopy(e) for e in static[0] if e.tag in ("Topology", "Geometry")]
    for k, step in enumerate(steps):
        for inc in [e for e in step if e.tag.endswith("}include")]:
            step.remove(inc)
        step.set("Name", f"step_{k}")
        step.set("GridType", "Uniform")
        for i, e in enumerate(shared):
            step.insert(i, copy.deepcopy(e))
    domain.remove(static[0])
    ET.indent(tree)
    with atomic_path(path) as tmp:
        tree.write(tmp, encoding="utf-8", xml_declaration=True)
    return len(steps)


def _cells(h5, model: str, h5_path):
    """meshio cell blocks of the model's connectivity: rod edges as lines, shell triangles, tetrahedra."""
    key = {"rods": ("line", "edges"), "shell": ("triangle", "triangles"), "tets": ("tetra", "tets")}[model]
    return [(key[0], np.asarray(require(h5, key[1], path=h5_path)[()]))]


def write_xdmf_series(h5_path, sequence: str, out, reference=None, *, stop_at_divergence=True) -> dict:
    """XDMF + HDF5 time series of one sequence of any trajectory-layout file, for ParaView.

    The mesh is the rest shape (``rest_positions``) with the model's cells
    (rod edges as lines, shell triangles, tetrahedra), held by every time step
    (one block in ParaView: :func:`single_block_xdmf`); each time step carries
    the point fields

    - ``displacement`` (n,3) [m]: positions minus rest (ParaView: *Warp By Vector*);
    - ``dirichlet`` (n,) : 1 on prescribed vertices, 0 elsewhere;
    - ``error`` (n,) [m], only with ``reference``: distance of each vertex to
      the reference file's same sequence at the same frame (NaN past the
      reference's last frame).

    Parameters
    ----------
    h5_path : trajectory-layout file (``rollout.h5``, ``trajectories.h5``).
    sequence : str, group under ``/sequences``.
    out : path of the ``.xdmf`` to write; its heavy data go to the sibling
        ``<stem>.h5``.  Both are written under temporary names and renamed
        (the ``.h5`` first), so a complete ``.xdmf`` always has its data.
    reference : path of the ground-truth file, or None.
    stop_at_divergence : bool
        Write only the frames before ``diverged_frame`` (the rest are NaN).

    Returns
    -------
    dict with ``frames`` (number of time steps written), ``fields`` (names)
    and ``h5`` (path of the data file).
    """
    out = Path(out)
    if out.suffix.lower() != ".xdmf":
        raise ValueError(f"write_xdmf_series: out must end in .xdmf, got {out}")
    data_file = out.with_suffix(".h5")
    for src in [h5_path] + ([reference] if reference is not None else []):
        if data_file.resolve() == Path(src).resolve():
            raise ValueError(f"write_xdmf_series: the series data file {data_file} would overwrite the input {src}")
    h5_path = str(h5_path)
    with open_artefact(h5_path) as f:
        model = model_of(f, h5_path)
        cells = _cells(f, model, h5_path)
        rest = require(f, "rest_positions", path=h5_path)[()]
        D = f["dirichlet"][()] if "dirichlet" in f else np.zeros(0, dtype=np.int64)
        dt = float(f.attrs.get("dt", 1.0))
        seqs = require(f, "sequences", path=h5_path)
        if sequence not in seqs:
            raise ArtefactError(f"{h5_path}: no sequence '{sequence}'; has {sorted(seqs)}")
        g = seqs[sequence]
        pos = require(g, "positions", path=h5_path)[()]
        div = int(g.attrs.get("diverged_frame", -1))
    if pos.shape[1:] != rest.shape:
        raise ArtefactError(f"{h5_path}: sequence '{sequence}' positions {pos.shape} do not match rest_positions {rest.shape}")
    if stop_at_divergence and div >= 0:
        pos = pos[:div]
    ref = None
    if reference is not None:
        ref = load_motion(reference, sequence).positions
        if ref.shape[1:] != rest.shape:
            raise ValueError(
                f"write_xdmf_series: reference {reference} sequence '{sequence}' has {ref.shape[1]} vertices, {h5_path} has {rest.shape[0]}"
            )
    marker = np.zeros(len(rest))
    marker[D] = 1.0
    fields = ["displacement", "dirichlet"] + (["error"] if ref is not None else [])
    out.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.stem}.tmp-"))
    try:
        # meshio's TimeSeriesWriter writes <stem>.h5 into the current directory and
        # names it inside the .xdmf, so both are written under their final names in a
        # temporary folder and then moved beside each other
        with working_directory(tmpdir), meshio.xdmf.TimeSeriesWriter(out.name) as w:
            w.write_points_cells(rest, cells)
            for t in range(len(pos)):
                pd = {"displacement": pos[t] - rest, "dirichlet": marker}
                if ref is not None:
                    pd["error"] = (
                        np.linalg.norm(pos[t] - ref[t], axis=1) if t < len(ref) else np.full(len(rest), np.nan)
                    )
                w.write_data(t * dt, point_data=pd)
        single_block_xdmf(tmpdir / out.name)
        os.replace(tmpdir / data_file.name, data_file)
        os.replace(tmpdir / out.name, out)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return {"frames": len(pos), "fields": fields, "h5": data_file}
