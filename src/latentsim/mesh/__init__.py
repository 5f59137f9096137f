"""Mesh preparation: fetching, reading, generating, tetrahedralizing and checking meshes.

This is the library behind the pipeline's first stage.  Everything is NumPy in
and NumPy out: vertices are float64 arrays of shape (n, 3) and cells are int64
arrays -- edges (e, 2), triangles (t, 3), tetrahedra (e, 4) -- indexing rows of
the vertex array (0-based).

Conventions
-----------
* A tetrahedron ``(a, b, c, d)`` is *positively oriented* when
  ``det[b - a, c - a, d - a] > 0``, i.e. its signed volume
  ``dot(cross(b - a, c - a), d - a) / 6`` is positive.  Every generator and
  :func:`tetrahedralize` return positively oriented tets; :func:`read_mesh`
  reorients negative ones (and counts them in ``Mesh.flipped``).
* A closed surface triangle ``(a, b, c)`` is oriented with its normal
  ``cross(b - a, c - a)`` pointing out of the enclosed volume;
  :func:`surface_of` returns boundary faces oriented that way.
* Every problem with a mesh raises :class:`MeshError` (a ``ValueError``) whose
  message names the file or mesh and the offending item.

Mesh files are never part of the repository: :func:`fetch_mesh` takes them
from a local folder named in the config (e.g. ``../shared/meshes``) or
downloads the pinned URL of :data:`MESH_SOURCES`, and checks the sha256 either
way.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import re
import tempfile
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from itertools import permutations
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

logger = logging.getLogger(__name__)

__all__ = [
    "MESH_SOURCES",
    "DEFAULT_CACHE_DIR",
    "MeshError",
    "Mesh",
    "sha256_of",
    "fetch_mesh",
    "read_mesh",
    "read_obj",
    "rod_bundle",
    "cloth_grid",
    "beam_tets",
    "check_closed_surface",
    "tetrahedralize",
    "surface_of",
    "tet_volumes",
    "triangle_areas",
    "enclosed_volume",
    "remove_unreferenced",
    "rotation_matrix",
    "normalise",
    "select_vertices",
    "check_mesh",
]

# ---------------------------------------------------------------------------
# Sources
# ---------------------------------------------------------------------------

_NEURAL_MODES = (
    "https://raw.githubusercontent.com/jiahong-w/neural-modes/"
    "233aa77b12ac0ecf7503f49560f12510cfbb4eb6/datasets"
)

#: Pinned public meshes: file name -> url, sha256 (plus licence and the counts
#: the file holds, for reference).  Facts copied from ``shared/meshes/SOURCES.md``.
MESH_SOURCES: dict[str, dict[str, Any]] = {
    "armadillo.vtu": {
        "url": f"{_NEURAL_MODES}/armadillo/ref.vtu",
        "sha256": "cc260f19b94cb43f308e91689dc9bd7826d9e849bc68743380c972631fe38a43",
        "licence": "Apache-2.0 (c) 2024 Jiahong Wang",
        "vertices": 7179,
        "tets": 26211,
    },
    "giraffe.vtu": {
        "url": f"{_NEURAL_MODES}/giraffe/ref.vtu",
        "sha256": "abb7a510bad351b93893460572141811af9520d39c81b9fb793fee81e9491e01",
        "licence": "Apache-2.0 (c) 2024 Jiahong Wang",
        "vertices": 1698,
        "tets": 5424,
    },
    "square.obj": {
        "url": f"{_NEURAL_MODES}/square/ref.obj",
        "sha256": "61990f9667badee8a5ac9d51152b83b6d0c684bd663241847cf3d43934013849",
        "licence": "Apache-2.0 (c) 2024 Jiahong Wang",
        "vertices": 121,
        "triangles": 200,
    },
    "bunny.obj": {
        "url": "https://raw.githubusercontent.com/evouga/libshell/"
        "6072d9e4b3c9f99c8cfe538b8b5560954d87dfdf/example/bunny.obj",
        "sha256": "b8cedb0c8027f0d73f56c192751a6d307b5b8b863642a850a7f2b03af41cebf8",
        "licence": "MPL-2.0 (libshell)",
        "vertices": 2823,
        "triangles": 5642,
    },
    "coarse_bunny.mesh": {
        "url": "https://raw.githubusercontent.com/lawsonfulton/AutoDef/"
        "ce530cc91806d9c3acbe8b2b7cdea1d6dc37157c/meshes/coarsebunny.mesh",
        "sha256": "59aefe2888359522742404117d840af42288dddb2771188f96932b7f58392989",
        "licence": "MIT (c) 2019 Lawson Fulton",
        "vertices": 739,
        "tets": 2352,
    },
}

#: Where :func:`fetch_mesh` downloads to when no ``cache_dir`` is given
#: (``$LATENTSIM_CACHE/meshes``, default ``~/.cache/latentsim/meshes``).
DEFAULT_CACHE_DIR = (
    Path(os.environ.get("LATENTSIM_CACHE", Path.home() / ".cache" / "latentsim")) / "meshes"
)


class MeshError(ValueError):
    """Any problem with a mesh: missing or corrupt file, bad hash, bad topology or quality."""


# ---------------------------------------------------------------------------
# Fetching
# ---------------------------------------------------------------------------


def sha256_of(path: str | os.PathLike) -> str:
    """Hex sha256 digest of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _check_hash(path: Path, expected: str, what: str) -> None:
    actual = sha256_of(path)
    if actual != expected.lower():
        raise MeshError(
            f"{what} {path.name!r} ({path}): sha256 mismatch, expected {expected.lower()}, "
            f"got {actual}"
        )


def fetch_mesh(
    name: str,
    local_dir: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    url: str | None = None,
    sha256: str | None = None,
    timeout: float = 60.0,
) -> Path:
    """Return a verified local path to the mesh file ``name``.

    Order of preference:

    1. ``local_dir/name`` if ``local_dir`` is given and holds the file: its
       sha256 is checked (a mismatch raises, it does not fall back to a
       download) and that path is returned as is (nothing is copied).
    2. ``cache_dir/name`` if it exists with the right sha256.
    3. Download ``url`` into ``cache_dir`` through a temporary file in the same
       folder, check the sha256, then rename it into place.  On any failure the
       temporary file is removed, so the cache never holds an unverified file.

    Parameters
    ----------
    name : str
        Plain file name (no folders), e.g. ``"armadillo.vtu"``.
    local_dir : path, optional
        Folder of pre-fetched meshes (config ``mesh_dir``, e.g. ``../shared/meshes``).
    cache_dir : path, optional
        Download folder; default :data:`DEFAULT_CACHE_DIR`.
    url, sha256 : str, optional
        Override the pinned entry of :data:`MESH_SOURCES`; required for files
        not listed there.  A sha256 is always required.
    timeout : float
        Seconds for the download connection.

    Returns
    -------
    Path
        Path of the verified file.

    Raises
    ------
    MeshError
        Unknown name without url/sha256, hash mismatch (naming the file, the
        expected and the actual hash), or a failed download.
    """
    if not name or Path(name).name != name or name in (".", ".."):
        raise MeshError(f"mesh name must be a plain file name, got {name!r}")
    entry = MESH_SOURCES.get(name, {})
    url = url if url is not None else entry.get("url")
    sha256 = sha256 if sha256 is not None else entry.get("sha256")
    if not sha256:
        raise MeshError(
            f"no sha256 pinned for mesh {name!r}: pass sha256= (known meshes: "
            f"{', '.join(sorted(MESH_SOURCES))})"
        )
    sha256 = sha256.lower()
    if not re.fullmatch(r"[0-9a-f]{64}", sha256):
        raise MeshError(f"mesh {name!r}: sha256 must be 64 hex digits, got {sha256!r}")

    if local_dir is not None:
        local = Path(local_dir) / name
        if local.is_file():
            _check_hash(local, sha256, "local mesh")
            logger.info("mesh %s: using local file %s (sha256 ok)", name, local)
            return local
        logger.info("mesh %s: not in local folder %s, trying cache/download", name, local_dir)

    cache = Path(cache_dir) if cache_dir is not None else DEFAULT_CACHE_DIR
    target = cache / name
    if target.is_file():
        if sha256_of(target) == sha256:
            logger.info("mesh %s: using cached %s (sha256 ok)", name, target)
            return target
        logger.warning("mesh %s: cached %s has a wrong sha256, downloading again", name, target)

    if not url:
        raise MeshError(f"mesh {name!r} is not available locally and has no url to download")
    cache.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{name}.", suffix=".part", dir=cache)
    tmp = Path(tmp_name)
    try:
        h = hashlib.sha256()
        with os.fdopen(fd, "wb") as out:
            try:
                with urllib.request.urlopen(url, timeout=timeout) as response:
                    for chunk in iter(lambda: response.read(1 << 20), b""):
                        h.update(chunk)
                        out.write(chunk)
            except (urllib.error.URLError, OSError, ValueError) as exc:
                raise MeshError(f"mesh {name!r}: download from {url} failed: {exc}") from exc
        actual = h.hexdigest()
        if actual != sha256:
            raise MeshError(
                f"downloaded mesh {name!r} from {url}: sha256 mismatch, expected {sha256}, "
                f"got {actual}"
            )
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
    logger.info("mesh %s: downloaded %s -> %s (sha256 ok)", name, url, target)
    return target


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------


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
        they had negative volume in the file.
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
            line, lineno_used = pending + line, pending_line
            pending = ""
        else:
            lineno_used = lineno
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        where = f"{path}:{lineno_used}"
        if key == "v":
            if len(parts) < 4:
                raise MeshError(f"{where}: vertex needs 3 coordinates: {raw.strip()!r}")
            try:
                xyz = [float(s) for s in parts[1:4]]
            except ValueError as exc:
                raise MeshError(f"{where}: cannot parse vertex {raw.strip()!r}") from exc
            if not all(math.isfinite(c) for c in xyz):
                raise MeshError(f"{where}: non-finite vertex coordinate {raw.strip()!r}")
            verts.append(xyz)
        elif key == "f":
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
                    i = len(verts) + i
                    if i < 0:
                        raise MeshError(
                            f"{where}: negative face index {head} refers before the first "
                            f"vertex ({len(verts)} vertices defined so far)"
                        )
                else:
                    i -= 1
                idx.append(i)
            for k in range(1, len(idx) - 1):
                tris.append((idx[0], idx[k], idx[k + 1]))
                tri_lines.append(lineno_used)
        # vt, vn, vp, g, o, s, l, p, usemtl, mtllib, ...: ignored
    if pending:
        raise MeshError(f"{path}:{pending_line}: file ends inside a continued line")
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
        Reorient negatively oriented tets by swapping their last two vertices
        (counted in ``Mesh.flipped`` and logged).  All five pinned meshes are
        already positively oriented (``flipped == 0``).

    Returns
    -------
    Mesh

    Raises
    ------
    MeshError
        Missing file, unreadable content, no usable cells, non-finite
        coordinates or out-of-range indices; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    triangles = tets = None
    if path.suffix.lower() == ".obj":
        vertices, triangles = read_obj(path)
    else:
        import meshio

        try:
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
            tets = np.concatenate(tet_blocks)
        elif tri_blocks:
            triangles = np.concatenate(tri_blocks)
        else:
            raise MeshError(
                f"{path}: no tetra, triangle or quad cells (found: "
                f"{', '.join(b.type for b in m.cells) or 'none'})"
            )
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:
        raise MeshError(
            f"{path}: {bad.size} vertices with NaN/inf coordinates, first is vertex {int(bad[0])}"
        )
    for label, cells in (("tet", tets), ("triangle", triangles)):
        if cells is None:
            continue
        out = np.flatnonzero(((cells < 0) | (cells >= len(vertices))).any(axis=1))
        if out.size:
            raise MeshError(
                f"{path}: {label} {int(out[0])} has vertex index out of range "
                f"{cells[out[0]].tolist()} (mesh has {len(vertices)} vertices)"
            )
    flipped = 0
    if tets is not None and orient:
        vol = tet_volumes(vertices, tets)
        neg = vol < 0
        flipped = int(neg.sum())
        if flipped:
            tets = tets.copy()
            tets[neg] = tets[neg][:, [0, 1, 3, 2]]
            logger.warning("%s: reoriented %d of %d negatively oriented tets",
                           path, flipped, len(tets))
    return Mesh(vertices=vertices, triangles=triangles, tets=tets, name=path.name,
                flipped=flipped)


# ---------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------


def tet_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (e,) of tets (e, 4): ``det[b-a, c-a, d-a] / 6``."""
    p = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets)
    a, b, c, d = (p[t[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Areas (t,) of triangles (t, 3)."""
    p = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    a, b, c = (p[t[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def enclosed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Volume enclosed by a closed, outward-oriented surface (divergence theorem).

    Sum over triangles of ``dot(a, cross(b, c)) / 6``; positive for outward
    normals.  Centred on the vertex mean to limit round-off.
    """
    p = np.asarray(vertices, dtype=np.float64)
    p = p - p.mean(axis=0)
    t = np.asarray(triangles)
    a, b, c = (p[t[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def remove_unreferenced(vertices: np.ndarray, *cells: np.ndarray):
    """Drop vertices no cell references and renumber the cells.

    Parameters
    ----------
    vertices : (n, 3)
    *cells : (e, k) int arrays

    Returns
    -------
    vertices : (m, 3), then each cell array renumbered, then ``kept`` (m,) int64:
    the old index of every kept vertex.
    """
    vertices = np.asarray(vertices)
    used = np.zeros(len(vertices), dtype=bool)
    for c in cells:
        used[np.asarray(c).ravel()] = True
    kept = np.flatnonzero(used).astype(np.int64)
    new_index = np.full(len(vertices), -1, dtype=np.int64)
    new_index[kept] = np.arange(len(kept))
    return (vertices[kept], *(new_index[np.asarray(c)] for c in cells), kept)


# ---------------------------------------------------------------------------
# Procedural generators
# ---------------------------------------------------------------------------


def _positive_int(value, what: str, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < minimum:
        raise MeshError(f"{what} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _positive_float(value, what: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise MeshError(f"{what} must be a positive finite number, got {value!r}")
    return v


def rod_bundle(
    n_rods: int,
    vertices_per_rod: int,
    length: float,
    spacing: float,
    direction: Sequence[float] = (0.0, -1.0, 0.0),
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight rods hanging from a grid of roots in the xz plane.

    Roots sit on a ``ceil(sqrt(n_rods))``-column grid with the given spacing,
    filled row by row (x fastest, then z), the full grid centred on ``origin``
    in the plane ``y = origin[1]``.  Each rod runs ``length`` from its root
    along ``direction`` with uniformly spaced vertices.

    Parameters
    ----------
    n_rods : int >= 1
    vertices_per_rod : int >= 2
        ``m``; rod ``r`` owns vertices ``r*m .. r*m + m - 1`` and vertex
        ``r*m`` is its root.
    length, spacing : float > 0
    direction : (3,) array-like, normalised internally.
    origin : (3,) array-like, centre of the root grid.

    Returns
    -------
    vertices : (n_rods * m, 3) float64
    edges : (n_rods * (m - 1), 2) int64, consecutive vertices of each rod,
        root first, rod by rod.
    roots : (n_rods,) int64, ``arange(n_rods) * m``.
    """
    n = _positive_int(n_rods, "n_rods")
    m = _positive_int(vertices_per_rod, "vertices_per_rod", 2)
    length = _positive_float(length, "length")
    spacing = _positive_float(spacing, "spacing")
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(d)
    if not (np.isfinite(norm) and norm > 0):
        raise MeshError(f"rod direction must be a non-zero vector, got {direction!r}")
    d = d / norm
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    r = np.arange(n)
    roots_xyz = np.zeros((n, 3))
    roots_xyz[:, 0] = (r % cols - (cols - 1) / 2.0) * spacing
    roots_xyz[:, 2] = (r // cols - (rows - 1) / 2.0) * spacing
    roots_xyz += np.asarray(origin, dtype=np.float64).reshape(3)
    s = np.linspace(0.0, length, m)
    vertices = (roots_xyz[:, None, :] + s[None, :, None] * d[None, None, :]).reshape(-1, 3)
    first = (r[:, None] * m + np.arange(m - 1)[None, :]).ravel()
    edges = np.column_stack([first, first + 1]).astype(np.int64)
    roots = (r * m).astype(np.int64)
    return vertices, edges, roots


def cloth_grid(
    nx: int, ny: int, width: float, height: float, plane: str = "xz"
) -> tuple[np.ndarray, np.ndarray]:
    """Regular triangulated rectangle (a cloth sheet), centred on the origin.

    ``nx`` x ``ny`` square cells, each split along the same diagonal into two
    triangles: ``(nx+1)(ny+1)`` vertices and ``2 nx ny`` triangles (10 x 10
    gives the 121 / 200 of the Neural Modes square).

    Parameters
    ----------
    nx, ny : int >= 1
        Cells along the first and second axis of ``plane``.
    width, height : float > 0
        Extent along the first and second axis of ``plane``.
    plane : {"xz", "xy"}
        ``"xz"``: horizontal sheet at y = 0, width along x, height along z,
        triangle normals +y.  ``"xy"``: vertical sheet at z = 0, width along
        x, height along y, normals +z.

    Returns
    -------
    vertices : ((nx+1)(ny+1), 3) float64; vertex ``j*(nx+1) + i`` is at
        column ``i`` (first axis), row ``j`` (second axis).
    triangles : (2 nx ny, 3) int64, all with the positive normal above.
    """
    nx = _positive_int(nx, "nx")
    ny = _positive_int(ny, "ny")
    width = _positive_float(width, "width")
    height = _positive_float(height, "height")
    if plane not in ("xz", "xy"):
        raise MeshError(f"cloth plane must be 'xz' or 'xy', got {plane!r}")
    u = np.linspace(-width / 2, width / 2, nx + 1)
    w = np.linspace(-height / 2, height / 2, ny + 1)
    uu, ww = np.meshgrid(u, w)  # (ny+1, nx+1), row j, column i
    vertices = np.zeros(((nx + 1) * (ny + 1), 3))
    ax_u = 0
    ax_w = 1 if plane == "xy" else 2
    vertices[:, ax_u] = uu.ravel()
    vertices[:, ax_w] = ww.ravel()
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    v00 = (j * (nx + 1) + i).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    # normal of (v00, v10, v11) is e_u x e_w: +z for xy, -y for xz
    if plane == "xy":
        tris = np.concatenate([np.column_stack([v00, v10, v11]), np.column_stack([v00, v11, v01])])
    else:
        tris = np.concatenate([np.column_stack([v00, v11, v10]), np.column_stack([v00, v01, v11])])
    return vertices, tris.astype(np.int64)


def _cube_corners() -> np.ndarray:
    # local corner c = bx + 2 by + 4 bz
    return np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)


def beam_tets(
    nx: int,
    ny: int,
    nz: int,
    length: float,
    width: float,
    height: float,
    tets_per_cell: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """Box ``[0, length] x [-width/2, width/2] x [-height/2, height/2]`` of tets.

    The box is cut into ``nx x ny x nz`` hexahedral cells (along x, y, z).
    With ``tets_per_cell=6`` each cell gets the Kuhn/Freudenthal split along
    its (0,0,0)-(1,1,1) diagonal; with ``5`` each cell gets a central tet on
    the corners of even global parity ``(i+j+k) % 2 == 0`` plus four corner
    tets, the pattern alternating between neighbouring cells.  Both are
    conforming (every interior face is shared by exactly two tets) and every
    tet is positively oriented (orientation fixed on exact integer lattice
    coordinates).

    Parameters
    ----------
    nx, ny, nz : int >= 1
    length, width, height : float > 0
    tets_per_cell : {5, 6}

    Returns
    -------
    vertices : ((nx+1)(ny+1)(nz+1), 3) float64; vertex
        ``i + (nx+1) * (j + (ny+1) * k)`` is grid node ``(i, j, k)``.
    tets : (tets_per_cell * nx * ny * nz, 4) int64, positively oriented.
    """
    nx, ny, nz = (_positive_int(v, name) for v, name in ((nx, "nx"), (ny, "ny"), (nz, "nz")))
    length = _positive_float(length, "length")
    width = _positive_float(width, "width")
    height = _positive_float(height, "height")
    if tets_per_cell not in (5, 6):
        raise MeshError(f"tets_per_cell must be 5 or 6, got {tets_per_cell!r}")
    gi, gj, gk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1),
                             indexing="ij")
    lattice = np.column_stack([gi.ravel("F"), gj.ravel("F"), gk.ravel("F")])  # i fastest
    vertices = np.column_stack([
        lattice[:, 0] * (length / nx),
        lattice[:, 1] * (width / ny) - width / 2,
        lattice[:, 2] * (height / nz) - height / 2,
    ]).astype(np.float64)
    # exact end points (no accumulated round-off)
    vertices[lattice[:, 0] == nx, 0] = length
    vertices[lattice[:, 1] == ny, 1] = width / 2
    vertices[lattice[:, 2] == nz, 2] = height / 2

    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    ci, cj, ck = ci.ravel("F"), cj.ravel("F"), ck.ravel("F")
    corners = _cube_corners()
    # global vertex index of each cell corner: (cells, 8)
    cv = ((ci[:, None] + corners[None, :, 0])
          + (nx + 1) * ((cj[:, None] + corners[None, :, 1])
                        + (ny + 1) * (ck[:, None] + corners[None, :, 2])))

    def local(bits):
        return sum(int(b) << a for a, b in enumerate(bits))

    if tets_per_cell == 6:
        patterns = []
        for perm in permutations(range(3)):
            path, cur = [0], np.zeros(3, dtype=int)
            for axis in perm:
                cur[axis] = 1
                path.append(local(cur))
            patterns.append(path)
        tets = np.concatenate([cv[:, p] for p in patterns])
    else:
        even_cell = (ci + cj + ck) % 2 == 0
        tets_list = []
        for cell_even in (True, False):
            sel = even_cell if cell_even else ~even_cell
            if not sel.any():
                continue
            # corners whose *global* parity is even form the central tet
            central = [c for c in range(8) if (corners[c].sum() % 2 == 0) == cell_even]
            others = [c for c in range(8) if c not in central]
            pats = [central]
            for c in others:
                nbrs = [c ^ 1, c ^ 2, c ^ 4]
                pats.append([c, *nbrs])
            tets_list.extend(cv[sel][:, p] for p in pats)
        tets = np.concatenate(tets_list)
    tets = tets.astype(np.int64)
    # orientation on the integer lattice: exact
    sign = np.sign(tet_volumes(lattice.astype(np.float64), tets))
    if (sign == 0).any():  # pragma: no cover - construction guarantees non-degenerate tets
        raise MeshError("beam_tets produced a degenerate tet")
    neg = sign < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    return vertices, tets


# ---------------------------------------------------------------------------
# Surfaces and tetrahedralization
# ---------------------------------------------------------------------------


def _as_cells(cells, k: int, what: str, n_vertices: int | None = None) -> np.ndarray:
    arr = np.asarray(cells)
    if arr.ndim != 2 or arr.shape[1] != k:
        raise MeshError(f"{what} must have shape (n, {k}), got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise MeshError(f"{what} must be an integer array, got dtype {arr.dtype}")
    arr = arr.astype(np.int64, copy=False)
    if n_vertices is not None and arr.size:
        bad = np.flatnonzero(((arr < 0) | (arr >= n_vertices)).any(axis=1))
        if bad.size:
            raise MeshError(
                f"{what} {int(bad[0])} has vertex index out of range {arr[bad[0]].tolist()} "
                f"({n_vertices} vertices)"
            )
    return arr


def _as_vertices(vertices, what: str = "vertices") -> np.ndarray:
    arr = np.asarray(vertices, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MeshError(f"{what} must have shape (n, 3), got {arr.shape}")
    return arr


_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def surface_of(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tetrahedral mesh.

    A face is on the boundary when exactly one tet has it.  For positively
    oriented tets the returned triangles have outward normals.

    Parameters
    ----------
    tets : (e, 4) int

    Returns
    -------
    triangles : (t, 3) int64, in order of the owning tet (faces opposite
        vertex 0, 1, 2, 3 of each tet).

    Raises
    ------
    MeshError
        If a face is shared by more than two tets (non-conforming mesh).
    """
    tets = _as_cells(tets, 4, "tet")
    faces = tets[:, _TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    c = counts[inverse]
    if (c > 2).any():
        f = int(np.flatnonzero(c > 2)[0])
        raise MeshError(
            f"face {key[f].tolist()} is shared by {int(c[f])} tets (tet {f // 4} among them): "
            "mesh is not conforming"
        )
    return faces[c == 1]


def check_closed_surface(triangles: np.ndarray, name: str = "surface") -> None:
    """Check that triangles form a closed, manifold, consistently oriented surface.

    Every undirected edge must be used by exactly two triangles, once in each
    direction.  Several closed components are allowed.  (Self-intersections
    and vertices where two sheets touch are not detected here; TetGen reports
    intersections itself.)

    Parameters
    ----------
    triangles : (t, 3) int

    Raises
    ------
    MeshError
        Naming a bad edge ``(a, b)`` and its triangles: a degenerate triangle,
        an edge in more than two triangles (non-manifold), an edge in only one
        triangle (open surface), or an edge used twice in the same direction
        (inconsistent orientation).  Non-manifold edges are reported before
        open ones, open before orientation problems.
    """
    tri = _as_cells(triangles, 3, f"{name}: triangle")
    if len(tri) == 0:
        raise MeshError(f"{name}: no triangles")
    degenerate = np.flatnonzero((tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2])
                                | (tri[:, 0] == tri[:, 2]))
    if degenerate.size:
        t = int(degenerate[0])
        raise MeshError(f"{name}: triangle {t} {tri[t].tolist()} repeats a vertex")
    directed = tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    owner = np.repeat(np.arange(len(tri)), 3)
    key = np.sort(directed, axis=1)
    forward = np.where(directed[:, 0] < directed[:, 1], 1, -1)
    uniq, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()

    def owners(edge_id: int) -> list[int]:
        return owner[inverse == edge_id].tolist()

    def describe(edge_ids: np.ndarray, problem: str) -> str:
        e = int(edge_ids[0])
        a, b = uniq[e].tolist()
        more = f" ({edge_ids.size - 1} more such edges)" if edge_ids.size > 1 else ""
        return f"{name}: edge ({a}, {b}) {problem} triangles {owners(e)}{more}"

    nonmanifold = np.flatnonzero(counts > 2)
    if nonmanifold.size:
        raise MeshError(describe(nonmanifold, "is non-manifold, shared by"))
    boundary = np.flatnonzero(counts == 1)
    if boundary.size:
        raise MeshError(describe(boundary, "is open (boundary), used only by"))
    direction_sum = np.bincount(inverse, weights=forward, minlength=len(uniq))
    flipped = np.flatnonzero(direction_sum != 0)
    if flipped.size:
        raise MeshError(describe(flipped, "has inconsistent orientation, same direction in"))


def _run_tetgen(vertices: np.ndarray, triangles: np.ndarray, switches: str):
    import tetgen

    import tempfile

    from latentsim.utils import working_directory

    tg = tetgen.TetGen(vertices, triangles.astype(np.int32))
    try:
        # TetGen writes tetgen-tmpfile_* debris into the cwd when it fails
        with tempfile.TemporaryDirectory() as scratch, working_directory(scratch):
            out = tg.tetrahedralize(switches=switches)
    except RuntimeError as exc:
        raise MeshError(f"TetGen failed with switches {switches!r}: {exc}") from exc
    nodes = np.asarray(out[0], dtype=np.float64)
    elems = np.asarray(out[1], dtype=np.int64)
    if elems.ndim != 2 or elems.shape[1] != 4 or len(elems) == 0:
        raise MeshError(f"TetGen (switches {switches!r}) returned no tets")
    return nodes, elems


def tetrahedralize(
    vertices: np.ndarray,
    triangles: np.ndarray,
    target_vertices: int | None = None,
    quality: tuple[float, float] | None = (2.0, 10.0),
    *,
    tolerance: float = 0.05,
    max_runs: int = 8,
    preserve_surface: bool = True,
    return_info: bool = False,
):
    """Fill a closed triangle surface with tetrahedra using TetGen.

    The surface is first checked with :func:`check_closed_surface`.  TetGen
    runs with ``p`` (piecewise linear complex), ``q<ratio>/<dihedral>``
    (quality bound) when ``quality`` is given, ``Y`` when
    ``preserve_surface`` (no Steiner points on the surface: the boundary of
    the result is exactly the input triangles) and ``a<volume>`` (maximum tet
    volume) while searching for ``target_vertices``.

    Vertex count.  TetGen only adds vertices, so the first run (quality bound,
    no volume bound) gives the fewest vertices reachable: if that is already
    within ``tolerance`` of the target, or above it, it is returned (a count
    far above the target is logged: decimate the surface first).  Otherwise a
    maximum volume is searched: the interior vertex count is modelled as
    ``C * a**-p`` (p fitted from the runs, 1 at first, initial guess
    ``a = 0.2 V / (target - n0)``), bracketed, for at most ``max_runs``
    TetGen runs in all; the run closest to the target is returned.  On the
    Stanford bunny (2,823 surface vertices) the quality run alone gives 3,543
    vertices / 12,049 tets in ~0.1 s.

    Parameters
    ----------
    vertices : (n, 3) float
    triangles : (t, 3) int, closed, outward oriented (orientation consistency
        is checked; a surface oriented inward still works since TetGen does
        not care, and the output tets are oriented positively regardless).
    target_vertices : int, optional
    quality : (max radius-edge ratio, min dihedral angle in degrees) or None
        for no quality refinement.
    tolerance : float
        Relative distance to ``target_vertices`` that stops the search.
    max_runs : int
        Maximum number of TetGen runs.
    preserve_surface : bool
        Pass ``Y`` so the surface is not refined.
    return_info : bool
        Also return a dict: ``runs`` (list of (max volume or None, vertices,
        tets, seconds)), ``switches`` of the chosen run, ``seconds`` in all.

    Returns
    -------
    vertices : (m, 3) float64; the input surface vertices that are used come
        first, in their input order (unreferenced input vertices are dropped).
    tets : (e, 4) int64, positively oriented.
    info : dict, only if ``return_info``.

    Raises
    ------
    MeshError
        Open / non-manifold / inconsistently oriented surface (naming an
        edge), or a TetGen failure (e.g. self-intersecting surface).
    """
    v = _as_vertices(vertices)
    tri = _as_cells(triangles, 3, "triangle", len(v))
    if not np.isfinite(v).all():
        raise MeshError("tetrahedralize: vertices contain NaN/inf")
    check_closed_surface(tri)
    v, tri, _ = remove_unreferenced(v, tri)
    if quality is not None:
        ratio, dihedral = (float(q) for q in quality)
        if ratio < 1.0 or not (0.0 <= dihedral < 70.0):
            raise MeshError(f"quality (radius-edge ratio >= 1, 0 <= dihedral < 70) got {quality}")
        base = f"pq{ratio:g}/{dihedral:g}"
    else:
        base = "p"
    if preserve_surface:
        base += "Y"
    if target_vertices is not None:
        target_vertices = _positive_int(target_vertices, "target_vertices")
    max_runs = _positive_int(max_runs, "max_runs")

    runs: list[tuple[float | None, int, int, float]] = []
    best: dict[str, Any] = {}

    def run(max_volume: float | None) -> int:
        switches = base + (f"a{max_volume:.8e}" if max_volume is not None else "") + "Q"
        t0 = time.perf_counter()
        nodes, elems = _run_tetgen(v, tri, switches)
        dt = time.perf_counter() - t0
        n = len(nodes)
        runs.append((max_volume, n, len(elems), dt))
        logger.info("tetgen %s: %d vertices, %d tets, %.2fs", switches, n, len(elems), dt)
        score = abs(n - target_vertices) if target_vertices else 0
        if not best or score < best["score"]:
            best.update(score=score, nodes=nodes, elems=elems, switches=switches)
        return n

    t_start = time.perf_counter()
    n0 = run(None)
    if target_vertices is not None and n0 > target_vertices * (1 + tolerance):
        logger.warning(
            "tetrahedralize: the quality run already gives %d vertices (target %d); TetGen "
            "cannot coarsen, decimate the surface to get fewer", n0, target_vertices)
    if target_vertices is not None and n0 < target_vertices * (1 - tolerance):
        total = abs(enclosed_volume(v, tri))
        a = 0.2 * total / (target_vertices - n0)
        lo = hi = None  # (log a, log(n - n0)) with n below / above target
        p = 1.0
        want = math.log(target_vertices - n0)
        for _ in range(max_runs - 1):
            n = run(a)
            if abs(n - target_vertices) <= tolerance * target_vertices:
                break
            la, ln = math.log(a), math.log(max(n - n0, 1))
            if n < target_vertices:
                lo = (la, ln)
            else:
                hi = (la, ln)
            if lo is not None and hi is not None and lo[1] != hi[1]:
                # interpolate log a linearly in log(n - n0) between the bracket
                s = (want - lo[1]) / (hi[1] - lo[1])
                la_new = lo[0] + s * (hi[0] - lo[0])
                margin = 0.1 * abs(lo[0] - hi[0])
                la_new = min(max(la_new, min(lo[0], hi[0]) + margin), max(lo[0], hi[0]) - margin)
            else:
                if len(runs) >= 3 and runs[-2][0] is not None and runs[-2][1] > n0 \
                        and runs[-2][1] != n:
                    la2, ln2 = math.log(runs[-2][0]), math.log(runs[-2][1] - n0)
                    if la2 != la:
                        p = min(max(-(ln - ln2) / (la - la2), 0.3), 3.0)
                step = (ln - want) / p
                la_new = la + min(max(step, -math.log(10.0)), math.log(10.0))
            a = math.exp(la_new)
    nodes, elems = best["nodes"], best["elems"]

    vol = tet_volumes(nodes, elems)
    neg = vol < 0
    if neg.any():
        elems = elems.copy()
        elems[neg] = elems[neg][:, [0, 1, 3, 2]]
        logger.info("tetrahedralize: reoriented %d tets", int(neg.sum()))
    if (vol == 0).any():
        raise MeshError(f"TetGen produced a zero-volume tet (index {int(np.argmax(vol == 0))})")
    nodes, elems, kept = remove_unreferenced(nodes, elems)
    if len(kept) != len(best["nodes"]):
        logger.info("tetrahedralize: dropped %d unreferenced TetGen nodes",
                    len(best["nodes"]) - len(kept))
    seconds = time.perf_counter() - t_start
    logger.info("tetrahedralize: %d vertices, %d tets (target %s) in %d runs, %.2fs",
                len(nodes), len(elems), target_vertices, len(runs), seconds)
    if return_info:
        return nodes, elems, {"runs": runs, "switches": best["switches"], "seconds": seconds}
    return nodes, elems


# ---------------------------------------------------------------------------
# Normalisation
# ---------------------------------------------------------------------------

_AXES = {"x": 0, "y": 1, "z": 2}


def _axis_index(axis, what: str = "axis") -> int:
    if isinstance(axis, str) and axis.lower().lstrip("+") in _AXES:
        return _AXES[axis.lower().lstrip("+")]
    if not isinstance(axis, bool) and isinstance(axis, (int, np.integer)) and 0 <= axis < 3:
        return int(axis)
    raise MeshError(f"{what} must be 'x', 'y', 'z' or 0..2, got {axis!r}")


def rotation_matrix(axis: str | Sequence[float], degrees: float) -> np.ndarray:
    """Right-handed rotation by ``degrees`` about ``axis`` (Rodrigues).

    Parameters
    ----------
    axis : "x" | "y" | "z" or (3,) vector (normalised internally)
    degrees : float

    Returns
    -------
    R : (3, 3) float64, rotating column vectors: ``x_new = R @ x``.
        Multiples of 90 degrees are exact (entries 0, +-1).
    """
    if isinstance(axis, str):
        k = np.zeros(3)
        k[_axis_index(axis)] = 1.0
    else:
        k = np.asarray(axis, dtype=np.float64).reshape(3)
        nrm = np.linalg.norm(k)
        if not (np.isfinite(nrm) and nrm > 0):
            raise MeshError(f"rotation axis must be a non-zero vector, got {axis!r}")
        k = k / nrm
    deg = float(degrees)
    quarter = deg / 90.0
    if quarter == round(quarter):
        c, s = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][int(round(quarter)) % 4]
    else:
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return c * np.eye(3) + s * K + (1.0 - c) * np.outer(k, k)


def normalise(
    vertices: np.ndarray,
    *,
    rotation: Any = None,
    height: float | None = None,
    scale: float | None = None,
    axis: str = "y",
    center: str | None = "bbox",
    ground: bool = False,
) -> np.ndarray:
    """Rotate, scale and centre a vertex array (returns a new array).

    Steps, in order: rotate about the bounding-box centre; scale uniformly
    (``height``: make the extent along ``axis`` equal to it, or a plain
    ``scale`` factor); translate so the bounding-box centre (``"bbox"``) or the
    vertex mean (``"centroid"``) is at the origin (``None``: keep); finally,
    with ``ground=True``, shift along ``axis`` so the minimum is 0 (object
    standing on the ground plane).

    Parameters
    ----------
    vertices : (n, 3)
    rotation : None, (3, 3) matrix, ``{"axis": "x", "degrees": 180}`` or
        ``("x", 180)``.  E.g. upside down: ``{"axis": "x", "degrees": 180}``.
    height : float > 0, optional
    scale : float > 0, optional (not together with ``height``)
    axis : "x" | "y" | "z", the height / ground axis.
    center : "bbox" | "centroid" | None
    ground : bool

    Returns
    -------
    (n, 3) float64
    """
    v = _as_vertices(vertices).copy()
    if len(v) == 0:
        raise MeshError("normalise: no vertices")
    if not np.isfinite(v).all():
        raise MeshError("normalise: vertices contain NaN/inf")
    ax = _axis_index(axis)
    if rotation is not None:
        if isinstance(rotation, Mapping):
            unknown = set(rotation) - {"axis", "degrees"}
            if unknown or not {"axis", "degrees"} <= set(rotation):
                raise MeshError(f"rotation must be {{'axis': .., 'degrees': ..}}, got {rotation!r}")
            R = rotation_matrix(rotation["axis"], rotation["degrees"])
        elif isinstance(rotation, (tuple, list)) and len(rotation) == 2:
            R = rotation_matrix(rotation[0], rotation[1])
        else:
            R = np.asarray(rotation, dtype=np.float64)
            if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9) \
                    or np.linalg.det(R) <= 0:
                raise MeshError("rotation matrix must be a proper 3x3 rotation")
        c = 0.5 * (v.min(axis=0) + v.max(axis=0))
        v = (v - c) @ R.T + c
    if height is not None and scale is not None:
        raise MeshError("normalise: give height or scale, not both")
    if height is not None:
        h = _positive_float(height, "height")
        extent = v[:, ax].max() - v[:, ax].min()
        if extent <= 0:
            raise MeshError("normalise: zero extent along the height axis")
        v *= h / extent
    elif scale is not None:
        v *= _positive_float(scale, "scale")
    if center == "bbox":
        v -= 0.5 * (v.min(axis=0) + v.max(axis=0))
    elif center == "centroid":
        v -= v.mean(axis=0)
    elif center is not None:
        raise MeshError(f"center must be 'bbox', 'centroid' or None, got {center!r}")
    if ground:
        v[:, ax] -= v[:, ax].min()
    return v


# ---------------------------------------------------------------------------
# Vertex selection (Dirichlet / rigid regions)
# ---------------------------------------------------------------------------

_RULE_KEYS = {
    "extreme": ({"type", "axis", "side", "fraction"}, set()),
    "sphere": ({"type", "center", "radius"}, set()),
    "box": ({"type", "min", "max"}, set()),
    "indices": ({"type", "indices"}, set()),
}


def _vec3(value, rule, key) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"selection rule {rule!r}: {key!r} must be 3 numbers") from exc
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise MeshError(f"selection rule {rule!r}: {key!r} must be 3 finite numbers")
    return arr


def _number(rule: dict, key: str) -> float:
    try:
        value = float(rule[key])
    except (TypeError, ValueError) as exc:
        raise MeshError(f"selection rule {rule!r}: {key!r} must be a number") from exc
    if not math.isfinite(value):
        raise MeshError(f"selection rule {rule!r}: {key!r} must be finite")
    return value


def select_vertices(vertices: np.ndarray, rule: Mapping[str, Any]) -> np.ndarray:
    """Indices of the vertices matched by a selection rule given as config data.

    Rules (all keys required, no others allowed, so config typos fail):

    * ``{"type": "extreme", "axis": "y", "side": "max", "fraction": 0.05}``:
      vertices whose coordinate along ``axis`` is within ``fraction * extent``
      of the maximum (``side: "min"``: of the minimum), boundary included,
      with ``0 <= fraction <= 1`` (0 picks the extreme vertices only).
    * ``{"type": "sphere", "center": [x, y, z], "radius": r}``: ``|x - c| <= r``.
    * ``{"type": "box", "min": [..], "max": [..]}``: inside the closed box.
    * ``{"type": "indices", "indices": [...]}``: explicit indices.

    (``{"type": "roots"}`` belongs to rod scenes, which use ``rod_bundle``'s
    ``roots``, and is rejected here.)

    Parameters
    ----------
    vertices : (n, 3)
    rule : mapping

    Returns
    -------
    indices : (k,) int64, sorted, unique, k >= 1.

    Raises
    ------
    MeshError
        Unknown type, missing/unknown keys, bad values, or an empty selection;
        the message quotes the rule.
    """
    v = _as_vertices(vertices)
    if not isinstance(rule, Mapping) or "type" not in rule:
        raise MeshError(f"selection rule must be a mapping with a 'type', got {rule!r}")
    kind = rule["type"]
    if kind == "roots":
        raise MeshError(
            f"selection rule {dict(rule)!r}: 'roots' is resolved by the rod scene from "
            "rod_bundle's roots, not by select_vertices")
    if kind not in _RULE_KEYS:
        raise MeshError(f"selection rule {dict(rule)!r}: unknown type {kind!r} "
                        f"(known: {', '.join(sorted(_RULE_KEYS))})")
    required, optional = _RULE_KEYS[kind]
    missing = required - set(rule)
    extra = set(rule) - required - optional
    if missing or extra:
        raise MeshError(f"selection rule {dict(rule)!r}: "
                        + (f"missing keys {sorted(missing)} " if missing else "")
                        + (f"unknown keys {sorted(extra)}" if extra else ""))
    rule_d = dict(rule)
    if kind == "extreme":
        ax = _axis_index(rule["axis"], f"selection rule {rule_d!r}: axis")
        side = rule["side"]
        if side not in ("max", "min"):
            raise MeshError(f"selection rule {rule_d!r}: side must be 'max' or 'min'")
        frac = _number(rule_d, "fraction")
        if not (0.0 <= frac <= 1.0):
            raise MeshError(f"selection rule {rule_d!r}: fraction must be in [0, 1]")
        coord = v[:, ax]
        lo, hi = coord.min(), coord.max()
        if side == "max":
            mask = coord >= hi - frac * (hi - lo)
        else:
            mask = coord <= lo + frac * (hi - lo)
    elif kind == "sphere":
        c = _vec3(rule["center"], rule_d, "center")
        r = _number(rule_d, "radius")
        if r < 0:
            raise MeshError(f"selection rule {rule_d!r}: radius must be >= 0")
        mask = np.einsum("ij,ij->i", v - c, v - c) <= r * r
    elif kind == "box":
        lo, hi = _vec3(rule["min"], rule_d, "min"), _vec3(rule["max"], rule_d, "max")
        if (lo > hi).any():
            raise MeshError(f"selection rule {rule_d!r}: min > max")
        mask = ((v >= lo) & (v <= hi)).all(axis=1)
    else:  # indices
        raw = np.asarray(rule["indices"])
        if raw.ndim != 1 or (raw.size and not np.issubdtype(raw.dtype, np.integer)):
            raise MeshError(f"selection rule {rule_d!r}: indices must be a list of integers")
        idx = raw.astype(np.int64)
        bad = idx[(idx < 0) | (idx >= len(v))]
        if bad.size:
            raise MeshError(f"selection rule {rule_d!r}: index {int(bad[0])} out of range "
                            f"({len(v)} vertices)")
        mask = np.zeros(len(v), dtype=bool)
        mask[idx] = True
    out = np.flatnonzero(mask).astype(np.int64)
    if out.size == 0:
        lo_b, hi_b = (v.min(axis=0).round(6).tolist(), v.max(axis=0).round(6).tolist()) \
            if len(v) else (None, None)
        raise MeshError(f"selection rule {rule_d!r} selects no vertex "
                        f"(mesh bounding box {lo_b} .. {hi_b})")
    return out


# ---------------------------------------------------------------------------
# Quality checks
# ---------------------------------------------------------------------------

# the edge shared by faces opposite vertices k and l of a tet; pairs (k, l)
_FACE_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def _tet_quality(p: np.ndarray, tets: np.ndarray) -> dict[str, np.ndarray]:
    x = p[tets]  # (e, 4, 3)
    faces = x[:, _TET_FACES]  # (e, 4, 3, 3)
    normals = np.cross(faces[:, :, 1] - faces[:, :, 0], faces[:, :, 2] - faces[:, :, 0])
    nn = np.linalg.norm(normals, axis=2, keepdims=True)
    unit = normals / np.where(nn > 0, nn, 1.0)
    cos = np.einsum("eij,eij->ei", unit[:, _FACE_PAIRS[:, 0]], unit[:, _FACE_PAIRS[:, 1]])
    dihedral = 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    edges = x[:, [0, 0, 0, 1, 1, 2]] - x[:, [1, 2, 3, 2, 3, 3]]
    elen = np.linalg.norm(edges, axis=2)
    return {"dihedral": dihedral, "edge_min": elen.min(axis=1), "edge_max": elen.max(axis=1),
            "edge_rms": np.sqrt((elen ** 2).mean(axis=1))}


def check_mesh(
    vertices: np.ndarray,
    tets: np.ndarray | None = None,
    triangles: np.ndarray | None = None,
    name: str = "mesh",
    *,
    unreferenced: str = "warn",
    degenerate_tol: float = 1e-10,
    strict: bool = True,
) -> dict[str, Any]:
    """Check a mesh and return quality statistics for logging.

    Checks, in order: array shapes, NaN/inf coordinates, indices in range,
    unreferenced vertices (``unreferenced="warn"``: logged as a warning;
    ``"error"``: a problem; ``"ignore"``), inverted tets (negative volume),
    zero-volume tets (``volume <= degenerate_tol * rms_edge**3``, i.e. a shape
    measure ~1e-9 of a regular tet's), degenerate triangles (repeated vertex
    or ``area <= degenerate_tol * rms_edge**2``).  Every message names the mesh
    and the first bad vertex/element index (and its volume or area) and how
    many there are.

    Parameters
    ----------
    vertices : (n, 3)
    tets : (e, 4) int, optional
    triangles : (t, 3) int, optional
    name : str, used in messages
    unreferenced : "warn" | "error" | "ignore"
    degenerate_tol : float
    strict : bool
        Raise :class:`MeshError` on the first problem (default).  If False,
        problems are collected in ``stats["problems"]`` and statistics are
        computed for what can be computed.

    Returns
    -------
    dict with plain Python numbers: ``n_vertices``, ``n_tets``,
    ``n_triangles``, ``n_unreferenced``, ``bbox_min``, ``bbox_max``; for tets
    ``volume_total``, ``volume_min``, ``volume_max``, ``n_inverted``,
    ``n_degenerate_tets``, ``dihedral_min_deg``, ``dihedral_max_deg``,
    ``edge_ratio_max`` (longest / shortest edge of a tet); for triangles
    ``area_total``, ``area_min``, ``area_max``, ``n_degenerate_triangles``,
    ``angle_min_deg``; and ``problems`` (list of str, empty when all is well).
    """
    problems: list[str] = []

    def problem(msg: str) -> None:
        if strict:
            raise MeshError(msg)
        logger.warning(msg)
        problems.append(msg)

    if unreferenced not in ("warn", "error", "ignore"):
        raise MeshError(f"unreferenced must be 'warn', 'error' or 'ignore', got {unreferenced!r}")
    p = _as_vertices(vertices, f"{name}: vertices")
    n = len(p)
    stats: dict[str, Any] = {"name": name, "n_vertices": n,
                             "n_tets": 0 if tets is None else int(len(tets)),
                             "n_triangles": 0 if triangles is None else int(len(triangles))}
    finite = np.isfinite(p).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        problem(f"{name}: {bad.size} vertices with NaN/inf coordinates, first is vertex "
                f"{int(bad[0])} {p[bad[0]].tolist()}")
    if finite.any():
        stats["bbox_min"] = p[finite].min(axis=0).tolist()
        stats["bbox_max"] = p[finite].max(axis=0).tolist()

    cells = {}
    for label, arr, k in (("tet", tets, 4), ("triangle", triangles, 3)):
        if arr is None:
            continue
        a = _as_cells(arr, k, f"{name}: {label}")
        bad = np.flatnonzero(((a < 0) | (a >= n)).any(axis=1))
        if bad.size:
            problem(f"{name}: {label} {int(bad[0])} has vertex index out of range "
                    f"{a[bad[0]].tolist()} ({n} vertices)")
            a = a[np.setdiff1d(np.arange(len(a)), bad)]
        cells[label] = a

    if cells:
        used = np.zeros(n, dtype=bool)
        for a in cells.values():
            used[a.ravel()] = True
        unref = np.flatnonzero(~used)
        stats["n_unreferenced"] = int(unref.size)
        if unref.size and unreferenced != "ignore":
            msg = (f"{name}: {unref.size} unreferenced vertices (first: "
                   f"{unref[:5].tolist()})")
            if unreferenced == "error":
                problem(msg)
            else:
                logger.warning(msg)
    else:
        stats["n_unreferenced"] = 0

    ok_vertex = finite
    if "tet" in cells and len(cells["tet"]):
        t = cells["tet"]
        good = ok_vertex[t].all(axis=1)
        vol = np.full(len(t), np.nan)
        vol[good] = tet_volumes(p, t[good])
        q = _tet_quality(p, t[good]) if good.any() else None
        inverted = np.flatnonzero(vol < 0)
        scale = np.full(len(t), np.nan)
        if q is not None:
            scale[good] = q["edge_rms"] ** 3
        degenerate = np.flatnonzero(np.abs(vol) <= degenerate_tol * scale)
        degenerate = np.setdiff1d(degenerate, inverted)
        stats.update(n_inverted=int(inverted.size), n_degenerate_tets=int(degenerate.size))
        if inverted.size:
            i = int(inverted[0])
            problem(f"{name}: tet {i} {t[i].tolist()} is inverted, volume {vol[i]:.6g} "
                    f"({inverted.size} inverted tets)")
        if degenerate.size:
            i = int(degenerate[0])
            problem(f"{name}: tet {i} {t[i].tolist()} has (near) zero volume {vol[i]:.6g} "
                    f"({degenerate.size} such tets)")
        if good.any():
            vg = vol[good]
            stats.update(volume_total=float(vg.sum()), volume_min=float(vg.min()),
                         volume_max=float(vg.max()),
                         dihedral_min_deg=float(np.nanmin(q["dihedral"])),
                         dihedral_max_deg=float(np.nanmax(q["dihedral"])))
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = q["edge_max"] / q["edge_min"]
            stats["edge_ratio_max"] = float(np.nanmax(ratio)) if np.isfinite(ratio).any() \
                else float("inf")

    if "triangle" in cells and len(cells["triangle"]):
        f = cells["triangle"]
        good = ok_vertex[f].all(axis=1)
        area = np.full(len(f), np.nan)
        area[good] = triangle_areas(p, f[good])
        x = p[f[good]]
        e = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 1], x[:, 0] - x[:, 2]], axis=1)
        elen = np.linalg.norm(e, axis=2)
        scale = np.full(len(f), np.nan)
        scale[good] = (elen ** 2).mean(axis=1)
        repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        degenerate = np.flatnonzero(repeated | (area <= degenerate_tol * scale))
        stats["n_degenerate_triangles"] = int(degenerate.size)
        if degenerate.size:
            i = int(degenerate[0])
            problem(f"{name}: triangle {i} {f[i].tolist()} is degenerate, area {area[i]:.6g} "
                    f"({degenerate.size} degenerate triangles)")
        if good.any():
            ag = area[good]
            stats.update(area_total=float(ag.sum()), area_min=float(ag.min()),
                         area_max=float(ag.max()))
            # interior angle at each corner: between the two edges leaving it
            with np.errstate(divide="ignore", invalid="ignore"):
                cosang = np.stack([
                    np.einsum("ij,ij->i", -e[:, 2], e[:, 0]),
                    np.einsum("ij,ij->i", -e[:, 0], e[:, 1]),
                    np.einsum("ij,ij->i", -e[:, 1], e[:, 2]),
                ], axis=1) / (elen[:, [2, 0, 1]] * elen)
            ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            stats["angle_min_deg"] = float(np.nanmin(ang)) if np.isfinite(ang).any() else 0.0
    stats["problems"] = problems
    return stats
