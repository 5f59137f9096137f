"""Mesh preparation: fetching, reading, generating, tetrahedralising and checking meshes.

This is the library behind the pipeline's first stage.  Everything is NumPy in
and NumPy out: vertices are float64 arrays of shape (n, 3) and cells are int64
arrays -- edges (e, 2), triangles (t, 3), tetrahedra (e, 4) -- indexing rows of
the vertex array (0-based).

Modules, one job each:

* :mod:`~latentsim.mesh.validation`: :class:`MeshError` and the argument checks;
* :mod:`~latentsim.mesh.sources`: pinned meshes (:data:`MESH_SOURCES`), :func:`fetch_mesh`,
  a scene's file (pinned or the user's own) by :func:`mesh_file`, a missing own file by
  :func:`check_user_mesh`;
* :mod:`~latentsim.mesh.readers`: :class:`Mesh`, :func:`read_obj`, :func:`read_mesh`;
* :mod:`~latentsim.mesh.geometry`: volumes, areas, orientation, unreferenced vertices;
* :mod:`~latentsim.mesh.generators`: :func:`rod_bundle`, :func:`cloth_grid`, :func:`beam_tets`;
* :mod:`~latentsim.mesh.surface`: :func:`surface_of`, :func:`check_closed_surface`, :func:`weld`;
* :mod:`~latentsim.mesh.remesh`: :func:`remesh_isotropic` (a surface to near-equilateral triangles);
* :mod:`~latentsim.mesh.tetgen`: :func:`tetrahedralize`, :func:`tetrahedralize_to`,
  :func:`improve_slivers`;
* :mod:`~latentsim.mesh.transform`: :func:`rotation_matrix`, :func:`normalise`, :func:`place`;
* :mod:`~latentsim.mesh.selection`: :func:`select_vertices`, :func:`select_dirichlet`;
* :mod:`~latentsim.mesh.quality`: :func:`check_mesh`;
* :mod:`~latentsim.mesh.build`: a scene's mesh from its config (:func:`build_mesh`, :func:`scene_mesh`), a mesh collider's (:func:`collider_mesh`).

Conventions
-----------
* A tetrahedron ``(a, b, c, d)`` is *positively oriented* when
  ``det[b - a, c - a, d - a] > 0``, i.e. its signed volume
  ``dot(cross(b - a, c - a), d - a) / 6`` is positive.  Every generator and
  :func:`tetrahedralize` return positively oriented tets; :func:`read_mesh`
  reorients a file whose tets are all negative (and counts them in
  ``Mesh.flipped``) and rejects one with tets of both orientations (tangled).
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

from latentsim.mesh.build import build_mesh, collider_mesh, scene_mesh
from latentsim.mesh.generators import beam_tets, cloth_grid, rod_bundle, rod_stencils
from latentsim.mesh.geometry import (
    enclosed_volume,
    remove_unreferenced,
    reorient,
    tet_volumes,
    triangle_areas,
)
from latentsim.mesh.quality import check_mesh
from latentsim.mesh.readers import Mesh, read_mesh, read_obj
from latentsim.mesh.selection import select_dirichlet, select_vertices
from latentsim.mesh.sources import (
    DEFAULT_CACHE_DIR,
    MESH_SOURCES,
    check_user_mesh,
    fetch_mesh,
    mesh_file,
    sha256_of,
    user_mesh_path,
)
from latentsim.mesh.surface import check_closed_surface, surface_of, weld
from latentsim.mesh.remesh import remesh_isotropic
from latentsim.mesh.tetgen import improve_slivers, tetrahedralize, tetrahedralize_to
from latentsim.mesh.transform import normalise, place, rotation_matrix
from latentsim.mesh.validation import MeshError

__all__ = [
    "MESH_SOURCES",
    "DEFAULT_CACHE_DIR",
    "MeshError",
    "Mesh",
    "sha256_of",
    "user_mesh_path",
    "check_user_mesh",
    "fetch_mesh",
    "mesh_file",
    "read_mesh",
    "read_obj",
    "rod_bundle",
    "rod_stencils",
    "cloth_grid",
    "beam_tets",
    "check_closed_surface",
    "remesh_isotropic",
    "improve_slivers",
    "tetrahedralize",
    "tetrahedralize_to",
    "surface_of",
    "weld",
    "tet_volumes",
    "triangle_areas",
    "enclosed_volume",
    "remove_unreferenced",
    "reorient",
    "rotation_matrix",
    "normalise",
    "place",
    "select_vertices",
    "select_dirichlet",
    "check_mesh",
    "build_mesh",
    "collider_mesh",
    "scene_mesh",
]
