"""The :class:`Mesh` read from a file, and the readers: Wavefront OBJ, and everything meshio reads.

``.obj`` is parsed here (:func:`read_obj`: 1-based and negative indices,
polygons fan-triangulated); ``.vtu``, ``.mesh`` (MEDIT), ``.msh``, ``.vtk`` ...
go through meshio.  Every reader checks coordinates (finite) and indices (in
range) and names the file (and line) of a problem; :func:`read_mesh` turns a
file whose tets are all negatively oriented positive (``det[b - a, c - a, d - a] > 0``)
and rejects one whose tets are of both orientations (tangled).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from latentsim.mesh.geometry import reorient, tet_volumes
from latentsim.mesh.quality import check_mesh
from latentsim.mesh.validation import MeshError, as_cells, require_finite

logger = logging.getLogger(__name__)


@dataclass
class Mesh:
    """A mesh as read from a file.

    Attributes
    ----------
    vertices : (n, 3) float64
    triangles : (t, 3) int64 or None
        Surface triangles; None for tetrahedral meshes (use
        ``surface_of(mesh.tets)`` for their boundary) and for rod meshes.
    tets : (e, 4) int64 or None
        Positively oriented tetrahedra.
    name : str
        Usually the file name.
    flipped : int
        How many tets the reader reoriented (swapped two vertices) because
        they had negative volume in the file: 0, or all of them.
    """

    vertices: np.ndarray
    triangles: np.ndarray | None = None
    tets: np.ndarray | None = None
    name: str = "mesh"
    flipped: int = 0

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def check(self, **kwargs) -> dict:
        """Run :func:`check_mesh` on this mesh and return its statistics."""
        return check_mesh(self.vertices, tets=self.tets, triangles=self.triangles,
                          name=self.name, **kwargs)


# ---------------------------------------------------------------------------
# OBJ
# ---------------------------------------------------------------------------


def _obj_lines(text: str, path: Path) -> Iterator[tuple[int, str, str]]:
    """(line number, content, raw last line) of each logical OBJ line.

    Comments (``#`` to the end of the line) are stripped and lines ending in
    ``\\`` are joined with the next; the number is that of the first line.
    """
    pending = ""
    pending_line = 0
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip()
        if line.endswith("\\"):  # line continuation
            if not pending:
                pending_line = lineno
            pending += line[:-1] + " "
            continue
        if pending:
            yield pending_line, pending + line, raw
            pending = ""
        else:
            yield lineno, line, raw
    if pending:
        raise MeshError(f"{path}:{pending_line}: file ends inside a continued line")


def _obj_vertex(parts: list[str], where: str, raw: str) -> list[float]:
    """The coordinates of a ``v x y z [w | r g b]`` line (extra numbers ignored)."""
    if len(parts) < 4:
        raise MeshError(f"{where}: vertex needs 3 coordinates: {raw.strip()!r}")
    try:
        xyz = [float(s) for s in parts[1:4]]
    except ValueError as exc:
        raise MeshError(f"{where}: cannot parse vertex {raw.strip()!r}") from exc
    if not all(math.isfinite(c) for c in xyz):
        raise MeshError(f"{where}: non-finite vertex coordinate {raw.strip()!r}")
    return xyz


def _obj_face(parts: list[str], where: str, raw: str, n_defined: int) -> list[int]:
    """0-based vertex indices of an ``f`` line; corners ``i``, ``i/t``, ``i//n``, ``i/t/n``.

    A negative index counts back from the ``n_defined`` vertices defined so
    far; indices past the end are checked once the whole file is read.
    """
    if len(parts) < 4:
        raise MeshError(f"{where}: face needs at least 3 corners: {raw.strip()!r}")
    idx = []
    for token in parts[1:]:
        head = token.split("/", 1)[0]
        try:
            i = int(head)
        except ValueError as exc:
            raise MeshError(f"{where}: cannot parse face corner {token!r}") from exc
        if i == 0:
            raise MeshError(f"{where}: face index 0 (OBJ indices start at 1)")
        if i < 0:
            i = n_defined + i
            if i < 0:
                raise MeshError(
                    f"{where}: negative face index {head} refers before the first "
                    f"vertex ({n_defined} vertices defined so far)"
                )
        else:
            i -= 1
        idx.append(i)
    return idx


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read vertices and faces of a Wavefront OBJ file.

    Understands ``v x y z [w | r g b]`` and ``f`` lines whose corners are
    ``i``, ``i/t``, ``i//n`` or ``i/t/n``; indices are 1-based, or negative
    (relative to the vertices defined so far).  Polygons are fan-triangulated
    (``0,k,k+1``).  Texture coordinates, normals, groups, materials, lines and
    comments are ignored, so the numbers of ``vn``/``vt`` and ``v`` may differ.

    Returns
    -------
    vertices : (n, 3) float64
    triangles : (t, 3) int64

    Raises
    ------
    MeshError
        Missing file, a line that does not parse, a non-finite coordinate, an
        index of 0 or out of range (each with file and line number), or a file
        without vertices or faces.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise MeshError(f"{path}: not a text OBJ file ({exc})") from exc

    verts: list[list[float]] = []
    tris: list[tuple[int, int, int]] = []
    tri_lines: list[int] = []
    for lineno, line, raw in _obj_lines(text, path):
        parts = line.split()
        if not parts:
            continue
        where = f"{path}:{lineno}"
        if parts[0] == "v":
            verts.append(_obj_vertex(parts, where, raw))
        elif parts[0] == "f":
            idx = _obj_face(parts, where, raw, len(verts))
            for k in range(1, len(idx) - 1):
                tris.append((idx[0], idx[k], idx[k + 1]))
                tri_lines.append(lineno)
        # vt, vn, vp, g, o, s, l, p, usemtl, mtllib, ...: ignored
    if not verts:
        raise MeshError(f"{path}: no vertices ('v' lines) found")
    if not tris:
        raise MeshError(f"{path}: no faces ('f' lines) found")
    vertices = np.asarray(verts, dtype=np.float64)
    triangles = np.asarray(tris, dtype=np.int64)
    bad = np.flatnonzero((triangles >= len(vertices)).any(axis=1))
    if bad.size:
        t = int(bad[0])
        raise MeshError(
            f"{path}:{tri_lines[t]}: face index {int(triangles[t].max()) + 1} out of range "
            f"(file has {len(vertices)} vertices)"
        )
    return vertices, triangles


# ---------------------------------------------------------------------------
# meshio formats
# ---------------------------------------------------------------------------


def _read_meshio(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Vertices (n, 3), tets (e, 4) or None, triangles (t, 3) or None of a file meshio reads.

    Tets come from ``tetra`` cells; triangles from ``triangle`` and split
    ``quad`` cells, only when there are no tets.  Other cell types are ignored.
    """
    # meshio (with its many format plugins) is only needed for non-OBJ files
    import meshio

    try:
        # meshio's STL reader tells ASCII from binary by a size check that overflows harmlessly
        with np.errstate(over="ignore"):
            m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types, even sys.exit
        raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    vertices = np.asarray(m.points, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] not in (2, 3):
        raise MeshError(f"{path}: points have shape {vertices.shape}, expected (n, 3)")
    if vertices.shape[1] == 2:
        vertices = np.column_stack([vertices, np.zeros(len(vertices))])
    tet_blocks, tri_blocks = [], []
    for block in m.cells:
        data = np.asarray(block.data, dtype=np.int64)
        if block.type == "tetra":
            tet_blocks.append(data)
        elif block.type == "triangle":
            tri_blocks.append(data)
        elif block.type == "quad":
            tri_blocks.append(np.concatenate([data[:, [0, 1, 2]], data[:, [0, 2, 3]]]))
        else:
            logger.debug("%s: ignoring %d %s cells", path, len(data), block.type)
    if tet_blocks:
        return vertices, np.concatenate(tet_blocks), None
    if tri_blocks:
        return vertices, None, np.concatenate(tri_blocks)
    raise MeshError(
        f"{path}: no tetra, triangle or quad cells (found: "
        f"{', '.join(b.type for b in m.cells) or 'none'})"
    )


def read_mesh(path: str | os.PathLike, orient: bool = True) -> Mesh:
    """Read a mesh file into a :class:`Mesh`.

    ``.obj`` goes through :func:`read_obj`; everything else (``.vtu``,
    ``.mesh``, ``.msh``, ``.vtk``, ...) through meshio.  From meshio files the
    ``tetra`` cells become ``tets``; ``triangle`` (and split ``quad``) cells
    become ``triangles`` only when the file has no tets (the triangles stored
    in tet files, e.g. MEDIT face markers, may include interior faces, so they
    are dropped: use :func:`surface_of` for the boundary).  Other cell types
    are ignored.  float32 coordinates are promoted to float64.

    Parameters
    ----------
    path : path
    orient : bool
        Check the tets' orientation: a file whose tets are all negatively
        oriented (the opposite convention) is reoriented by swapping their last
        two vertices (counted in ``Mesh.flipped`` and logged); a file with tets
        of both orientations is tangled and raises.  All five pinned meshes are
        already positively oriented (``flipped == 0``).

    Returns
    -------
    Mesh

    Raises
    ------
    MeshError
        Missing file, unreadable content, no usable cells, non-finite
        coordinates, out-of-range indices or (``orient``) tets of both
        orientations; the message names the file (and the counts).
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    if path.suffix.lower() == ".obj":
        vertices, triangles = read_obj(path)
        tets = None
    else:
        vertices, tets, triangles = _read_meshio(path)
    require_finite(vertices, str(path))
    for label, cells, k in (("tet", tets, 4), ("triangle", triangles, 3)):
        if cells is not None:
            as_cells(cells, k, f"{path}: {label}", len(vertices))
    flipped = 0
    if tets is not None and orient:
        vol = tet_volumes(vertices, tets)
        neg, n_pos = vol < 0, int((vol > 0).sum())
        flipped = int(neg.sum())
        if flipped and not n_pos:  # the opposite convention (zero volumes are check_mesh's)
            tets = reorient(tets, neg)
            logger.warning("%s: all %d tets with a volume are negatively oriented; reoriented them",
                           path, flipped)
        elif flipped:
            # one orientation for the file with tets against it: those are inverted (tangled)
            # elements, which a vertex swap would hide, not fix
            i = int(np.flatnonzero(neg if flipped <= n_pos else vol > 0)[0])
            raise MeshError(
                f"{path}: {flipped} of {len(tets)} tets are negatively oriented and {n_pos} "
                f"positively (first of the {min(flipped, n_pos)} against the rest: tet {i} {tets[i].tolist()}, volume "
                f"{vol[i]:.6g}): the mesh is tangled (inverted elements); repair it in the mesher "
                f"that wrote it")
    return Mesh(vertices=vertices, triangles=triangles, tets=tets, name=path.name,
                flipped=flipped)
