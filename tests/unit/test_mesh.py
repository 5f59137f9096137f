"""Tests for latentsim.mesh: reading, fetching, generators, TetGen, selections, checks."""

from __future__ import annotations

import logging
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from latentsim import mesh as M
from latentsim.mesh import MeshError

REPO = Path(__file__).resolve().parents[2]
MESH_DIR = Path(os.environ.get("LATENTSIM_MESH_DIR", REPO / ".." / "shared" / "meshes")).resolve()
# Outside CI the shared meshes may be absent (a clone elsewhere); in CI they must be there.
_MESHES_MISSING = not (MESH_DIR / "SOURCES.md").is_file()
if _MESHES_MISSING and os.environ.get("CI"):
    raise RuntimeError(f"CI: the shared meshes are not at {MESH_DIR} (set LATENTSIM_MESH_DIR)")
needs_meshes = pytest.mark.skipif(_MESHES_MISSING, reason=f"shared meshes not found at {MESH_DIR}")

EDGE_RE = re.compile(r"edge \(\d+, \d+\)")


# ---------------------------------------------------------------------------
# OBJ reader
# ---------------------------------------------------------------------------

OBJ_TEXT = """\
# a unit square, a quad and a triangle given with every corner form
mtllib nothing.mtl
o square
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0   # trailing comment
v 0.5 0.5 1.0 1.0
vt 0 0
vt 1 0
vt 1 1
vn 0 0 1
g faces
usemtl none
s off
f 1/1/1 2/2/1 3/3/1 4/1/1
f -5//1 -4//1 -1//1
f 2/1 3/2 5/3
f 3 4 \\
  5
l 1 2
"""


def test_read_obj_forms_quads_negative_indices(tmp_path):
    path = tmp_path / "small.obj"
    path.write_text(OBJ_TEXT)
    v, t = M.read_obj(path)
    assert v.dtype == np.float64 and v.shape == (5, 3)
    assert t.dtype == np.int64
    np.testing.assert_array_equal(v[4], [0.5, 0.5, 1.0])
    np.testing.assert_array_equal(t, [[0, 1, 2], [0, 2, 3],  # fan of the quad
                                      [0, 1, 4],              # -5, -4, -1 with 5 vertices
                                      [1, 2, 4],
                                      [2, 3, 4]])             # continued line
    m = M.read_mesh(path)
    assert m.tets is None and m.name == "small.obj"
    np.testing.assert_array_equal(m.triangles, t)


def test_read_obj_negative_index_is_relative_to_vertices_so_far(tmp_path):
    path = tmp_path / "rel.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n"
                    "v 0 0 1\nv 1 0 1\nv 0 1 1\nf -3 -2 -1\n")
    _, t = M.read_obj(path)
    np.testing.assert_array_equal(t, [[0, 1, 2], [3, 4, 5]])


@pytest.mark.parametrize("text, pattern", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 x\nf 1 2 3\n", r"bad\.obj:3: cannot parse vertex"),
    ("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", r"bad\.obj:2: non-finite"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 4\n", r"bad\.obj:5: face index 4 out of range"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"bad\.obj:4: face index 0"),
    ("v 0 0 0\nv 1 0 0\nf -3 -2 -1\n", r"bad\.obj:3: negative face index -3"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"bad\.obj:4: face needs at least 3"),
    ("v 0 0 0\nv 1 0\n", r"bad\.obj:2: vertex needs 3"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"bad\.obj: no faces"),
    ("v 0 0 0\nf a/1 2 3\n", r"bad\.obj:2: cannot parse face corner"),
])
def test_read_obj_errors_name_file_and_line(tmp_path, text, pattern):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(MeshError, match=pattern):
        M.read_mesh(path)


def test_read_mesh_missing_and_unparsable(tmp_path):
    with pytest.raises(MeshError, match=r"nope\.vtu: mesh file not found"):
        M.read_mesh(tmp_path / "nope.vtu")
    garbage = tmp_path / "garbage.vtu"
    garbage.write_bytes(b"\x00\x01 this is not xml")
    with pytest.raises(MeshError, match=r"garbage\.vtu: cannot read mesh"):
        M.read_mesh(garbage)
    binary_obj = tmp_path / "binary.obj"
    binary_obj.write_bytes(b"v \xff\xfe\x00 1 2\n")
    with pytest.raises(MeshError, match=r"binary\.obj"):
        M.read_mesh(binary_obj)


def test_read_mesh_meshio_nan_range_and_orientation(tmp_path):
    import meshio

    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    tets = np.array([[0, 1, 3, 2], [1, 2, 4, 3]])  # both negative: the opposite convention
    assert (M.tet_volumes(p, tets) < 0).all()
    path = tmp_path / "two.vtu"
    meshio.write(path, meshio.Mesh(p, [("tetra", tets)]))
    m = M.read_mesh(path)
    assert m.flipped == 2 and (M.tet_volumes(m.vertices, m.tets) > 0).all()
    assert M.read_mesh(path, orient=False).flipped == 0

    bad = p.copy()
    bad[2, 1] = np.nan
    meshio.write(tmp_path / "nan.vtu", meshio.Mesh(bad, [("tetra", tets)]))
    with pytest.raises(MeshError, match=r"nan\.vtu: 1 vertices with NaN/inf.*vertex 2"):
        M.read_mesh(tmp_path / "nan.vtu")
    meshio.write(tmp_path / "range.vtu", meshio.Mesh(p, [("tetra", np.array([[0, 1, 2, 9]]))]))
    with pytest.raises(MeshError, match=r"range\.vtu: tet 0 has vertex index out of range"):
        M.read_mesh(tmp_path / "range.vtu")


def _write_beam(path, tets=None, vertices=None):
    """A 3x2x2-cell tet beam (72 positive tets) as a VTU, its tets or vertices replaced when given."""
    import meshio

    v, t = M.beam_tets(3, 2, 2, 0.3, 0.1, 0.1)
    meshio.write(path, meshio.Mesh(v if vertices is None else vertices, [("tetra", t if tets is None else tets)]))
    return v, t


def test_wholly_flipped_file_is_reoriented_and_counted(tmp_path, caplog):
    v, t = M.beam_tets(3, 2, 2, 0.3, 0.1, 0.1)
    path = tmp_path / "flipped.vtu"
    _write_beam(path, tets=t[:, [0, 1, 3, 2]])
    with caplog.at_level(logging.WARNING, logger="latentsim.mesh.readers"):
        m = M.read_mesh(path)
    assert m.flipped == len(t) == 72
    np.testing.assert_allclose(M.tet_volumes(m.vertices, m.tets), M.tet_volumes(v, t), rtol=1e-12)
    assert "flipped.vtu: all 72 tets with a volume are negatively oriented; reoriented them" in caplog.text
    assert m.check()["n_inverted"] == 0


def test_a_minority_of_negative_tets_is_a_tangled_mesh(tmp_path):
    """Three of 72 tets against the rest (vertex order swapped, as a tangle reads in the file): an
    error naming the file and the counts, not a silent reorientation recorded as 0 inverted."""
    v, t = M.beam_tets(3, 2, 2, 0.3, 0.1, 0.1)
    bad = t.copy()
    bad[[5, 17, 40]] = bad[[5, 17, 40]][:, [0, 1, 3, 2]]
    path = tmp_path / "tangled.vtu"
    _write_beam(path, tets=bad)
    with pytest.raises(MeshError, match=r"tangled\.vtu: 3 of 72 tets are negatively oriented and 69 positively "
                       r"\(first of the 3 against the rest: tet 5 .*volume -.*tangled"):
        M.read_mesh(path)
    # the same the other way round: a wholly flipped file with three tets the right way
    _write_beam(path, tets=bad[:, [0, 1, 3, 2]])
    with pytest.raises(MeshError, match=r"tangled\.vtu: 69 of 72 tets are negatively oriented and 3 positively "
                       r"\(first of the 3 against the rest: tet 5 "):
        M.read_mesh(path)


def test_a_vertex_pushed_through_its_tets_is_a_tangled_mesh(tmp_path):
    """A geometric tangle: one interior vertex moved past the opposite faces of some of its tets."""
    v, t = M.beam_tets(3, 2, 2, 0.3, 0.1, 0.1)
    inner = int(np.argmin(np.linalg.norm(v - [0.1, 0.0, 0.0], axis=1)))  # an interior vertex
    moved = v.copy()
    moved[inner, 1] += 0.08  # past its neighbours a cell (0.05) above: tets around it turn inside out
    n_neg = int((M.tet_volumes(moved, t) < 0).sum())
    assert 0 < n_neg < len(t) / 2
    path = tmp_path / "pushed.vtu"
    _write_beam(path, vertices=moved)
    with pytest.raises(MeshError, match=rf"pushed\.vtu: {n_neg} of 72 tets are negatively oriented"):
        M.read_mesh(path)


# ---------------------------------------------------------------------------
# Real meshes and sources
# ---------------------------------------------------------------------------

@needs_meshes
@pytest.mark.parametrize("name", sorted(M.MESH_SOURCES))
def test_real_meshes_load_with_documented_counts(name):
    entry = M.MESH_SOURCES[name]
    assert M.sha256_of(MESH_DIR / name) == entry["sha256"]
    m = M.read_mesh(MESH_DIR / name)
    assert m.vertices.dtype == np.float64 and m.vertices.shape == (entry["vertices"], 3)
    if "tets" in entry:
        assert m.triangles is None
        assert m.tets.dtype == np.int64 and m.tets.shape == (entry["tets"], 4)
        assert m.flipped == 0  # the files themselves are positively oriented
        assert (M.tet_volumes(m.vertices, m.tets) > 0).all()
        surf = M.surface_of(m.tets)
        assert M.enclosed_volume(m.vertices, surf) == pytest.approx(
            M.tet_volumes(m.vertices, m.tets).sum(), rel=1e-9)
    else:
        assert m.tets is None
        assert m.triangles.shape == (entry["triangles"], 3)
    stats = m.check()
    assert stats["problems"] == [] and stats["n_unreferenced"] == 0


def test_sources_table_is_pinned():
    for name, entry in M.MESH_SOURCES.items():
        assert re.fullmatch(r"[0-9a-f]{64}", entry["sha256"]), name
        assert entry["url"].startswith("https://raw.githubusercontent.com/"), name
        assert re.search(r"/[0-9a-f]{40}/", entry["url"]), name  # pinned commit


# ---------------------------------------------------------------------------
# fetch_mesh
# ---------------------------------------------------------------------------

@needs_meshes
def test_fetch_local_dir_returns_file_in_place(tmp_path):
    path = M.fetch_mesh("square.obj", local_dir=MESH_DIR, cache_dir=tmp_path / "cache")
    assert path == MESH_DIR / "square.obj"
    assert not (tmp_path / "cache").exists()  # nothing copied


@needs_meshes
def test_fetch_local_dir_wrong_hash(tmp_path):
    local = tmp_path / "local"
    local.mkdir()
    shutil.copyfile(MESH_DIR / "square.obj", local / "square.obj")
    with open(local / "square.obj", "ab") as fh:
        fh.write(b"# tampered\n")
    actual = M.sha256_of(local / "square.obj")
    with pytest.raises(MeshError) as err:
        M.fetch_mesh("square.obj", local_dir=local, cache_dir=tmp_path / "cache")
    msg = str(err.value)
    assert "square.obj" in msg and M.MESH_SOURCES["square.obj"]["sha256"] in msg and actual in msg


@needs_meshes
def test_fetch_download_file_url(tmp_path):
    src = tmp_path / "upstream" / "ref.obj"
    src.parent.mkdir()
    shutil.copyfile(MESH_DIR / "square.obj", src)
    cache = tmp_path / "cache"
    # local dir without the file falls through to the download
    path = M.fetch_mesh("square.obj", local_dir=tmp_path / "empty", cache_dir=cache,
                        url=src.as_uri())
    assert path == cache / "square.obj"
    assert M.sha256_of(path) == M.MESH_SOURCES["square.obj"]["sha256"]
    assert sorted(p.name for p in cache.iterdir()) == ["square.obj"]  # no temp file left
    # second call: served from the cache even though the url is now dead
    src.unlink()
    assert M.fetch_mesh("square.obj", cache_dir=cache, url=src.as_uri()) == path
    assert M.read_mesh(path).triangles.shape == (200, 3)


@needs_meshes
def test_fetch_wrong_hash_leaves_nothing_in_cache(tmp_path):
    src = tmp_path / "ref.obj"
    shutil.copyfile(MESH_DIR / "square.obj", src)
    cache = tmp_path / "cache"
    wrong = "0" * 64
    with pytest.raises(MeshError) as err:
        M.fetch_mesh("square.obj", cache_dir=cache, url=src.as_uri(), sha256=wrong)
    msg = str(err.value)
    assert "square.obj" in msg and wrong in msg and M.MESH_SOURCES["square.obj"]["sha256"] in msg
    assert list(cache.iterdir()) == []


def test_fetch_errors(tmp_path):
    with pytest.raises(MeshError, match="no sha256 pinned"):
        M.fetch_mesh("unknown.obj", cache_dir=tmp_path)
    with pytest.raises(MeshError, match="plain file name"):
        M.fetch_mesh("../etc/passwd", cache_dir=tmp_path, sha256="0" * 64)
    with pytest.raises(MeshError, match="download from .* failed"):
        M.fetch_mesh("x.obj", cache_dir=tmp_path / "c", sha256="0" * 64,
                     url=(tmp_path / "missing.obj").as_uri())
    assert list((tmp_path / "c").iterdir()) == []


# ---------------------------------------------------------------------------
# Closed-surface check and TetGen
# ---------------------------------------------------------------------------

def _tet_surface(offset=0):
    """Outward-oriented surface of the unit tet on vertices offset..offset+3."""
    return M.surface_of(np.array([[0, 1, 2, 3]])) + offset


@pytest.fixture(scope="module")
def bunny():
    if not (MESH_DIR / "bunny.obj").is_file():
        pytest.skip("shared meshes not available")
    return M.read_mesh(MESH_DIR / "bunny.obj")


def test_bunny_surface_is_closed(bunny):
    M.check_closed_surface(bunny.triangles)
    assert M.enclosed_volume(bunny.vertices, bunny.triangles) > 0


def test_tetrahedralize_bunny(bunny):
    v, t, info = M.tetrahedralize(bunny.vertices, bunny.triangles, target_vertices=3500,
                                  return_info=True)
    assert v.dtype == np.float64 and t.dtype == np.int64
    assert 3000 <= len(v) <= 4000 and len(info["runs"]) == 1
    vol = M.tet_volumes(v, t)
    assert (vol > 0).all()
    enclosed = M.enclosed_volume(bunny.vertices, bunny.triangles)
    assert vol.sum() == pytest.approx(enclosed, rel=1e-2)
    # 'Y': the surface is kept exactly, vertices first and in order
    np.testing.assert_array_equal(v[:len(bunny.vertices)], bunny.vertices)
    surf = M.surface_of(t)
    as_set = lambda tri: {tuple(np.roll(f, -int(np.argmin(f)))) for f in tri.tolist()}
    assert as_set(surf) == as_set(bunny.triangles)  # same faces, same orientation
    stats = M.check_mesh(v, tets=t, name="bunny-tets")
    assert stats["problems"] == [] and stats["dihedral_min_deg"] > 1.0


def test_tetrahedralize_reaches_larger_target(bunny):
    v, t, info = M.tetrahedralize(bunny.vertices, bunny.triangles, target_vertices=4500,
                                  tolerance=0.08, return_info=True)
    assert abs(len(v) - 4500) <= 0.08 * 4500, info["runs"]
    assert (M.tet_volumes(v, t) > 0).all()


def test_open_surface_rejected(bunny):
    open_tris = np.delete(bunny.triangles, 100, axis=0)
    with pytest.raises(MeshError, match="open") as err:
        M.tetrahedralize(bunny.vertices, open_tris)
    assert EDGE_RE.search(str(err.value))
    a, b = map(int, EDGE_RE.search(str(err.value)).group(0)[6:-1].split(", "))
    assert {a, b} <= set(bunny.triangles[100].tolist())


def test_non_manifold_and_misoriented_surfaces_rejected():
    # two tets' surfaces glued along one edge: closed, but that edge has 4 triangles
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
                  [0, 0, 0], [1, 0, 0], [0, -1, 0], [0, 0, -1.0]])
    tris = np.concatenate([_tet_surface(0), _tet_surface(4)])
    tris[tris == 4] = 0
    tris[tris == 5] = 1
    with pytest.raises(MeshError, match=r"edge \(0, 1\) is non-manifold"):
        M.tetrahedralize(p, tris)
    flipped = _tet_surface(0)
    flipped[2] = flipped[2, ::-1]
    with pytest.raises(MeshError, match="inconsistent orientation") as err:
        M.check_closed_surface(flipped)
    assert EDGE_RE.search(str(err.value))


def test_surface_of_tet_and_beam():
    surf = _tet_surface()
    assert len(surf) == 4
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    assert M.enclosed_volume(p, surf) == pytest.approx(1 / 6)
    v, t = M.beam_tets(4, 2, 3, 2.0, 0.5, 0.75)
    s = M.surface_of(t)
    M.check_closed_surface(s)
    assert M.triangle_areas(v, s).sum() == pytest.approx(2 * (2 * .5 + 2 * .75 + .5 * .75))
    assert M.enclosed_volume(v, s) == pytest.approx(2.0 * 0.5 * 0.75)
    with pytest.raises(MeshError, match="shared by 3 tets"):
        M.surface_of(np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 2, 1, 5]]))


# ---------------------------------------------------------------------------
# Generators
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("per_cell", [5, 6])
@pytest.mark.parametrize("n", [(1, 1, 1), (3, 2, 4)])
def test_beam_tets(per_cell, n):
    L, W, H = 2.0, 0.3, 0.7
    v, t = M.beam_tets(*n, L, W, H, tets_per_cell=per_cell)
    nx, ny, nz = n
    assert v.shape == ((nx + 1) * (ny + 1) * (nz + 1), 3) and v.dtype == np.float64
    assert t.shape == (per_cell * nx * ny * nz, 4) and t.dtype == np.int64
    vol = M.tet_volumes(v, t)
    assert (vol > 0).all()
    assert vol.sum() == pytest.approx(L * W * H, rel=1e-12)
    np.testing.assert_allclose(v.min(0), [0, -W / 2, -H / 2])
    np.testing.assert_allclose(v.max(0), [L, W / 2, H / 2])
    # conforming: interior faces are shared by exactly two tets (surface_of checks > 2)
    # and the boundary is exactly the box surface
    s = M.surface_of(t)
    assert M.triangle_areas(v, s).sum() == pytest.approx(2 * (L * W + L * H + W * H))
    stats = M.check_mesh(v, tets=t)
    assert stats["problems"] == [] and stats["n_unreferenced"] == 0


def test_cloth_grid():
    v, t = M.cloth_grid(10, 10, 0.2, 0.2)  # the Neural Modes square: 121 v / 200 tri
    assert v.shape == (121, 3) and t.shape == (200, 3) and t.dtype == np.int64
    assert np.all(v[:, 1] == 0)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    assert (n[:, 1] > 0).all()  # xz cloth: normals +y
    assert M.triangle_areas(v, t).sum() == pytest.approx(0.04)
    v, t = M.cloth_grid(4, 3, 2.0, 1.5, plane="xy")
    assert v.shape == (20, 3) and t.shape == (24, 3) and np.all(v[:, 2] == 0)
    np.testing.assert_allclose(v.max(0), [1.0, 0.75, 0])
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    assert (n[:, 2] > 0).all()
    assert M.check_mesh(v, triangles=t)["problems"] == []
    with pytest.raises(MeshError, match="plane"):
        M.cloth_grid(2, 2, 1, 1, plane="yz")


def test_rod_bundle():
    n_rods, m = 5, 7
    v, e, roots = M.rod_bundle(n_rods, m, length=0.6, spacing=0.1)
    assert v.shape == (n_rods * m, 3) and e.shape == (n_rods * (m - 1), 2)
    assert e.dtype == np.int64 and roots.dtype == np.int64
    np.testing.assert_array_equal(roots, np.arange(n_rods) * m)
    assert np.all(v[roots, 1] == 0)  # roots in the xz plane
    assert len({tuple(r) for r in v[roots].round(12).tolist()}) == n_rods
    for r in range(n_rods):
        rod = v[r * m:(r + 1) * m]
        np.testing.assert_allclose(rod[:, [0, 2]], np.repeat(rod[:1, [0, 2]], m, 0))
        np.testing.assert_allclose(rod[:, 1], -np.linspace(0, 0.6, m))  # hangs down
    np.testing.assert_array_equal(e[:m - 1], np.column_stack([np.arange(m - 1), np.arange(1, m)]))
    # spacing between grid neighbours
    assert np.linalg.norm(v[roots[1]] - v[roots[0]]) == pytest.approx(0.1)
    v2, _, _ = M.rod_bundle(1, 3, 1.0, 0.1, direction=(2.0, 0, 0))
    np.testing.assert_allclose(v2, [[0, 0, 0], [0.5, 0, 0], [1, 0, 0]])
    with pytest.raises(MeshError):
        M.rod_bundle(2, 1, 1.0, 0.1)


def test_rod_bundle_ring():
    """Roots evenly on a circle about the origin, rods hanging straight down from each."""
    n_rods, m = 8, 5
    v, _, roots = M.rod_bundle(n_rods, m, 0.2, 0.01, origin=(0.1, 0.3, -0.2), ring_radius=0.05)
    root_xyz = v[roots]
    np.testing.assert_allclose(root_xyz[:, 1], 0.3)
    np.testing.assert_allclose(np.hypot(root_xyz[:, 0] - 0.1, root_xyz[:, 2] + 0.2), 0.05)
    np.testing.assert_allclose(root_xyz.mean(0), [0.1, 0.3, -0.2], atol=1e-15)
    # neighbours one chord apart, the same all round
    chord = np.linalg.norm(np.roll(root_xyz, -1, 0) - root_xyz, axis=1)
    np.testing.assert_allclose(chord, 2 * 0.05 * np.sin(np.pi / n_rods))
    for r in range(n_rods):
        np.testing.assert_allclose(v[r * m:(r + 1) * m, 1], 0.3 - np.linspace(0, 0.2, m))
    with pytest.raises(MeshError, match="ring_radius"):
        M.rod_bundle(2, 3, 1.0, 0.1, ring_radius=-1.0)


# ---------------------------------------------------------------------------
# normalise
# ---------------------------------------------------------------------------

def test_normalise_and_rotation():
    R = M.rotation_matrix("x", 180)
    np.testing.assert_array_equal(R, np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(M.rotation_matrix([0, 0, 2], 90) @ [1, 0, 0], [0, 1, 0],
                               atol=1e-15)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3)) * [1, 3, 2] + 5
    out = M.normalise(v, height=1.5)
    assert np.ptp(out[:, 1]) == pytest.approx(1.5)
    np.testing.assert_allclose(out.min(0) + out.max(0), 0, atol=1e-12)
    top = np.argmax(v[:, 1])
    flipped = M.normalise(v, rotation={"axis": "x", "degrees": 180}, center=None, ground=True)
    assert np.argmin(flipped[:, 1]) == top and flipped[:, 1].min() == pytest.approx(0)
    assert M.normalise(v, scale=2.0, center="centroid").mean(0) == pytest.approx(np.zeros(3))
    with pytest.raises(MeshError):
        M.normalise(v, height=1.0, scale=2.0)


# ---------------------------------------------------------------------------
# Selections
# ---------------------------------------------------------------------------

def test_select_extreme_fraction_exact():
    rng = np.random.default_rng(1)
    v = rng.uniform(-1, 2, size=(2000, 3))
    y = v[:, 1]
    idx = M.select_vertices(v, {"type": "extreme", "axis": "y", "side": "max", "fraction": 0.05})
    expected = np.flatnonzero(y >= y.max() - 0.05 * (y.max() - y.min()))
    np.testing.assert_array_equal(idx, expected)
    assert idx.dtype == np.int64 and 60 < len(idx) < 140
    idx = M.select_vertices(v, {"type": "extreme", "axis": "x", "side": "min", "fraction": 0.1})
    x = v[:, 0]
    np.testing.assert_array_equal(idx, np.flatnonzero(x <= x.min() + 0.1 * np.ptp(x)))
    # boundary included: grid vertices exactly at the threshold
    g, _ = M.cloth_grid(10, 10, 1.0, 1.0)
    idx = M.select_vertices(g, {"type": "extreme", "axis": "z", "side": "max", "fraction": 0.0})
    assert len(idx) == 11


def test_select_sphere_box_indices():
    v, _ = M.cloth_grid(4, 4, 4.0, 4.0)  # integer grid -2..2 in x and z
    idx = M.select_vertices(v, {"type": "sphere", "center": [0, 0, 0], "radius": 1.0})
    assert sorted(map(tuple, v[idx].tolist())) == sorted(
        [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 0, 1), (0, 0, -1)])
    idx = M.select_vertices(v, {"type": "box", "min": [-2, -1, -2], "max": [-1, 1, 2]})
    assert len(idx) == 10 and (v[idx, 0] <= -1).all()
    np.testing.assert_array_equal(
        M.select_vertices(v, {"type": "indices", "indices": [3, 1, 3]}), [1, 3])


@pytest.mark.parametrize("rule, pattern", [
    ({"type": "sphere", "center": [10, 10, 10], "radius": 0.5}, "selects no vertex"),
    ({"type": "box", "min": [5, 5, 5], "max": [6, 6, 6]}, "selects no vertex"),
    ({"type": "indices", "indices": []}, "selects no vertex"),
    ({"type": "indices", "indices": [99]}, "out of range"),
    ({"type": "blob"}, "unknown type 'blob'"),
    ({"type": "extreme", "axis": "y", "side": "max"}, r"missing keys \['fraction'\]"),
    ({"type": "extreme", "axis": "y", "side": "top", "fraction": 0.1}, "side"),
    ({"type": "extreme", "axis": "y", "side": "max", "fraction": 0.1, "fracton": 1},
     "unknown keys"),
    ({"type": "roots"}, "roots"),
])
def test_select_errors_name_rule(rule, pattern):
    v, _ = M.cloth_grid(2, 2, 1.0, 1.0)
    with pytest.raises(MeshError, match=pattern) as err:
        M.select_vertices(v, rule)
    assert f"'type': '{rule['type']}'" in str(err.value)


# ---------------------------------------------------------------------------
# check_mesh
# ---------------------------------------------------------------------------

def test_check_mesh_flags_inverted_tet_by_index():
    v, t = M.beam_tets(2, 1, 1, 1.0, 1.0, 1.0)
    stats = M.check_mesh(v, tets=t)
    assert stats["n_tets"] == 12 and stats["volume_total"] == pytest.approx(1.0)
    assert 0 < stats["dihedral_min_deg"] < stats["dihedral_max_deg"] < 180
    bad = t.copy()
    bad[7] = bad[7, [1, 0, 2, 3]]
    vol7 = M.tet_volumes(v, bad[7:8])[0]
    with pytest.raises(MeshError, match=rf"tet 7 .* inverted, volume {vol7:.6g}"):
        M.check_mesh(v, tets=bad, name="beam")
    stats = M.check_mesh(v, tets=bad, strict=False)
    assert stats["n_inverted"] == 1 and len(stats["problems"]) == 1


def test_check_mesh_flags_nan_and_degenerate():
    v, t = M.beam_tets(1, 1, 1, 1.0, 1.0, 1.0)
    v[3, 2] = np.nan
    with pytest.raises(MeshError, match=r"my beam: 1 vertices with NaN/inf .* vertex 3"):
        M.check_mesh(v, tets=t, name="my beam")
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1.0]])
    with pytest.raises(MeshError, match=r"tet 1 .* zero volume"):
        M.check_mesh(p, tets=np.array([[0, 1, 2, 4], [0, 1, 2, 3]]))
    with pytest.raises(MeshError, match=r"triangle 1 .* degenerate"):
        M.check_mesh(p, triangles=np.array([[0, 1, 2], [0, 1, 1], [1, 3, 2], [0, 1, 4],
                                             [0, 4, 2]]))
    with pytest.raises(MeshError, match="out of range"):
        M.check_mesh(p, tets=np.array([[0, 1, 2, 7]]))


def test_check_mesh_unreferenced(caplog):
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0], [5, 5, 5]])
    t = np.array([[0, 1, 2, 3]])
    with caplog.at_level(logging.WARNING, logger="latentsim.mesh"):
        stats = M.check_mesh(p, tets=t, name="lonely")
    assert stats["n_unreferenced"] == 1 and "lonely: 1 unreferenced vertices" in caplog.text
    with pytest.raises(MeshError, match=r"unreferenced vertices \(first: \[4\]\)"):
        M.check_mesh(p, tets=t, unreferenced="error")
    q, t2, kept = M.remove_unreferenced(p, t)
    assert len(q) == 4 and kept.tolist() == [0, 1, 2, 3] and (t2 == t).all()


# ---------------------------------------------------------------------------
# Scene meshes: rod stencils, placement, welding, decimation, Dirichlet rules
# ---------------------------------------------------------------------------

def test_rod_stencils_match_rod_bundle():
    edges, triples, root_of = M.rod_stencils(3, 5)
    _, e, roots = M.rod_bundle(3, 5, 1.0, 0.1)
    np.testing.assert_array_equal(edges, e)
    np.testing.assert_array_equal(np.unique(root_of), roots)
    np.testing.assert_array_equal(root_of[:5], [0] * 5)
    assert triples.shape == (9, 3)
    # each triple is two consecutive edges of one rod
    np.testing.assert_array_equal(triples[:, 1] - triples[:, 0], 1)
    np.testing.assert_array_equal(triples[:, 2] - triples[:, 1], 1)
    np.testing.assert_array_equal(root_of[triples[:, 0]], root_of[triples[:, 2]])


def test_place_scales_then_rotates_then_translates():
    v = np.array([[1.0, 0, 0], [0, 2.0, 0]])
    out = M.place(v, scale=2.0, rotate_axis=[0, 0, 1], rotate_degrees=90, translate=[0, 0, 1])
    np.testing.assert_array_equal(out, [[0, 2, 1], [-4, 0, 1]])  # quarter turns are exact
    np.testing.assert_array_equal(M.place(v), v)
    r = M.place(v, rotate_axis=[1, 1, 1], rotate_degrees=120)  # x -> y -> z -> x
    np.testing.assert_allclose(r, [[0, 1, 0], [0, 0, 2]], atol=1e-15)


def test_weld_merges_close_vertices_and_drops_collapsed_triangles():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1e-9]])
    tris = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [1, 4, 3], [4, 2, 0]])
    v, f = M.weld(p, tris, 1e-6)
    # vertex 4 joins 1: triangle 3 collapses, 2 becomes (0, 3, 1), 4 doubles 0 and both go
    np.testing.assert_array_equal(v, p[:4])
    np.testing.assert_array_equal(f, [[0, 2, 3], [0, 3, 1]])


@pytest.mark.parametrize("remesh", [True, False])
def test_tetrahedralize_to_coarsens_a_dense_surface(bunny, remesh):
    """Remeshed (the default) or decimated, the bunny reaches its target; remeshed, with no
    dihedral angle under 5 degrees and its volume kept."""
    v, t = M.tetrahedralize_to(bunny.vertices, bunny.triangles, 2120, "bunny", remesh=remesh)
    assert len(v) < len(bunny.vertices)  # TetGen alone cannot go below the surface's count
    assert abs(len(v) - 2120) <= 0.05 * 2120
    assert (M.tet_volumes(v, t) > 0).all()
    M.check_closed_surface(M.surface_of(t))
    assert M.check_mesh(v, tets=t, name="bunny")["problems"] == []
    if remesh:
        assert M.check_mesh(v, tets=t, min_dihedral_deg=5.0)["n_below_min_dihedral"] == 0
        volume = M.enclosed_volume(bunny.vertices, bunny.triangles)
        assert M.tet_volumes(v, t).sum() == pytest.approx(volume, rel=0.01)


def test_select_dirichlet_roots_and_config_filled_rules():
    _, _, root_of = M.rod_stencils(2, 4)
    v, _, _ = M.rod_bundle(2, 4, 1.0, 0.1)
    np.testing.assert_array_equal(M.select_dirichlet(v, {"type": "roots"}, root_of), [0, 1, 4, 5])
    np.testing.assert_array_equal(
        M.select_dirichlet(v, {"type": "roots", "clamp": False}, root_of), [0, 4])
    with pytest.raises(MeshError, match="needs a rod scene"):
        M.select_dirichlet(v, {"type": "roots"})
    # the schema fills every rule key; only the rule's own keys reach select_vertices
    filled = {"type": "extreme", "axis": "y", "side": "min", "fraction": 0.0, "clamp": True,
              "center": [0, 0, 0], "radius": 0.1, "indices": []}
    np.testing.assert_array_equal(M.select_dirichlet(v, filled), [3, 7])


def test_scene_mesh_beam():
    cfg = {"generator": "beam_tets", "nx": 2, "ny": 1, "nz": 1, "length": 1.0, "width": 0.5,
           "height": 0.5, "scale": 2.0, "rotate_degrees": 0.0, "translate": [0, 0, 1.0]}
    rule = {"type": "extreme", "axis": "x", "side": "min", "fraction": 0.0}
    arrays, quality = M.scene_mesh("beam", "tets", cfg, rule, sources={})
    v0, t0 = M.beam_tets(2, 1, 1, 1.0, 0.5, 0.5)
    np.testing.assert_array_equal(arrays["tets"], t0)
    np.testing.assert_array_equal(arrays["rest_positions"], v0 * 2.0 + [0, 0, 1.0])
    np.testing.assert_array_equal(arrays["surface"], M.surface_of(t0))
    np.testing.assert_array_equal(arrays["dirichlet"], np.flatnonzero(v0[:, 0] == 0))
    assert quality["volume_total"] == pytest.approx(8 * 0.25) and quality["problems"] == []
    with pytest.raises(MeshError, match="needs model 'rods'"):
        M.build_mesh("tets", {"generator": "rod_bundle"}, sources={})


def test_a_free_body_has_no_dirichlet_vertex_and_only_the_free_rule_selects_none():
    cfg = {"generator": "beam_tets", "nx": 2, "ny": 1, "nz": 1, "length": 1.0, "width": 0.5, "height": 0.5}
    arrays, _ = M.scene_mesh("block", "tets", cfg, {"type": "free"}, sources={})
    assert arrays["dirichlet"].shape == (0,) and arrays["dirichlet"].dtype == np.int64
    with pytest.raises(MeshError, match="selects no vertex"):  # an empty selection is a mistake, not a free body
        M.scene_mesh("block", "tets", cfg, {"type": "indices", "indices": []}, sources={})


# ---------------------------------------------------------------------------
# a user's own mesh file (mesh.file a path, optional mesh.sha256)
# ---------------------------------------------------------------------------

def _cube_surface():
    """The unit cube's closed surface: 8 vertices, 12 outward triangles."""
    V = np.array([[x, y, z] for z in (0.0, 1.0) for y in (0.0, 1.0) for x in (0.0, 1.0)])
    F = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return V, F


def _write_user_mesh(path: Path) -> None:
    import meshio

    V, F = _cube_surface()
    if path.suffix == ".obj":  # OBJ with per-corner normals (f v//vn), as exporters write it
        lines = [f"v {x} {y} {z}" for x, y, z in V] + ["vn 0 0 1"]
        lines += [f"f {a + 1}//1 {b + 1}//1 {c + 1}//1" for a, b, c in F]
        path.write_text("\n".join(lines) + "\n")
    elif path.suffix == ".vtu":  # a volume mesh: the cube as 5 tets
        T = np.array([[0, 1, 2, 4], [1, 3, 2, 7], [1, 4, 5, 7], [2, 7, 6, 4], [1, 2, 4, 7]])
        meshio.write(path, meshio.Mesh(V, [("tetra", T)]))
    else:
        fmt = {".msh": "gmsh22"}.get(path.suffix)
        meshio.write(path, meshio.Mesh(V, [("triangle", F)]), file_format=fmt)


@pytest.mark.parametrize("name", ["part.obj", "part.stl", "part.ply", "part.vtu", "part.msh",
                                  "part.mesh"])
def test_user_mesh_file_any_format_to_tets(tmp_path, name):
    path = tmp_path / name
    _write_user_mesh(path)
    target = 0 if name.endswith(".vtu") else 40
    cfg = {"generator": "file", "file": str(path), "target_vertices": target}
    out = M.build_mesh("tets", cfg, {"local_dir": None, "cache_dir": str(tmp_path / "cache")})
    vol = M.tet_volumes(out["rest_positions"], out["tets"])
    assert (vol > 0).all()
    assert vol.sum() == pytest.approx(1.0, rel=1e-9)  # the cube, whatever the tetrahedralisation
    assert not (tmp_path / "cache").exists()  # a user's file is read in place


def test_user_mesh_file_shell_and_local_dir(tmp_path):
    _write_user_mesh(tmp_path / "part.obj")
    sources = {"local_dir": str(tmp_path), "cache_dir": str(tmp_path / "cache")}
    assert M.user_mesh_path("part.obj", sources) == tmp_path / "part.obj"
    assert M.user_mesh_path("square.obj", sources) is None  # pinned names stay pinned
    out = M.build_mesh("shell", {"generator": "file", "file": "part.obj"}, sources)
    assert out["triangles"].shape == (12, 3) and out["rest_positions"].shape == (8, 3)


def test_user_mesh_file_sha256_and_errors(tmp_path):
    path = tmp_path / "part.stl"
    _write_user_mesh(path)
    sources = {"local_dir": None, "cache_dir": str(tmp_path / "cache")}
    good = M.sha256_of(path)
    assert M.mesh_file(str(path), sources, sha256=good.upper()) == path
    wrong = "f" * 64
    with pytest.raises(MeshError) as err:
        M.mesh_file(str(path), sources, sha256=wrong)
    assert str(path) in str(err.value) and wrong in str(err.value) and good in str(err.value)
    with pytest.raises(MeshError, match="sha256 must be 64 hex"):
        M.mesh_file(str(path), sources, sha256="abc")
    with pytest.raises(MeshError, match=r"mesh.file: mesh file '.*missing.obj' not found"):
        M.mesh_file(str(tmp_path / "missing.obj"), sources)
    with pytest.raises(MeshError, match="needs mesh.file"):
        M.build_mesh("tets", {"generator": "file", "file": None}, sources)


def test_user_surface_mesh_errors_name_the_file(tmp_path):
    """A surface for model tets needs target_vertices; an open one cannot be filled: both name the file."""
    import meshio

    sources = {"local_dir": None, "cache_dir": str(tmp_path / "cache")}
    path = tmp_path / "part.stl"
    _write_user_mesh(path)
    with pytest.raises(MeshError, match=r"part\.stl: a surface .* set mesh\.target_vertices"):
        M.build_mesh("tets", {"generator": "file", "file": str(path), "target_vertices": 0}, sources)
    V, F = _cube_surface()
    meshio.write(tmp_path / "open.stl", meshio.Mesh(V, [("triangle", F[:-1])]))
    with pytest.raises(MeshError, match=r"open\.stl: cannot fill with tets: .*open"):
        M.build_mesh("tets", {"generator": "file", "file": str(tmp_path / "open.stl"), "target_vertices": 20}, sources)


def test_missing_user_mesh_message_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "parts").mkdir()
    _write_user_mesh(tmp_path / "parts" / "bracket.stl")
    none = {"local_dir": None}
    assert M.check_user_mesh("parts/bracket.stl", none) == Path("parts/bracket.stl")
    assert M.check_user_mesh("bunny.obj", {"local_dir": "nowhere"}) is None  # pinned: fetched later
    with pytest.raises(MeshError) as err:
        M.check_user_mesh("parts/braket.stl", none, where="config key 'scenes.s.mesh.file'")
    msg = str(err.value)
    assert msg.startswith("config key 'scenes.s.mesh.file': mesh file 'parts/braket.stl' not found")
    assert repr(str(tmp_path)) in msg and "did you mean 'parts/bracket.stl'?" in msg
    with pytest.raises(MeshError, match="folder 'prats' does not exist"):
        M.check_user_mesh("prats/bracket.stl", none)
    with pytest.raises(MeshError, match="a bare file name is read from meshes.local_dir, 'parts'.*did you mean"):
        M.check_user_mesh("bracet.stl", {"local_dir": "parts"})


# ---------------------------------------------------------------------------
# tet quality: TetGen's bounds, the dihedral gate, the statistics
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("levels, quality", [(2, (2.0, 10.0)), (1, (1.5, 10.0))])
def test_tetrahedralize_meets_the_dihedral_bound_on_a_small_closed_surface(levels, quality, icosphere):
    # TetGen's refinement plus optimisation meets the bounds on a well-shaped surface; with a
    # volume bound too (target_vertices) they are goals, not guarantees: check_mesh is the check
    V, F = icosphere(levels)
    v, t = M.tetrahedralize(V, F, quality=quality)
    stats = M.check_mesh(v, tets=t, name="icosphere", min_dihedral_deg=quality[1])
    assert stats["problems"] == [] and stats["n_below_min_dihedral"] == 0
    assert stats["dihedral_min_deg"] >= quality[1]
    assert stats["radius_edge_max"] <= quality[0]
    assert stats["volume_ratio"] >= 1.0 and len(v) >= len(V)
    assert stats["volume_total"] == pytest.approx(M.enclosed_volume(V, F), rel=1e-9)


def test_check_mesh_quality_statistics_of_a_regular_tet():
    p = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1.0]])
    p = p[[0, 1, 3, 2]] if M.tet_volumes(p, np.array([[0, 1, 2, 3]]))[0] < 0 else p
    stats = M.check_mesh(p, tets=np.array([[0, 1, 2, 3]]), min_dihedral_deg=70.0)
    regular = np.degrees(np.arccos(1 / 3))  # 70.53 degrees
    assert stats["dihedral_min_deg"] == pytest.approx(regular, rel=1e-9)
    assert stats["dihedral_median_deg"] == pytest.approx(regular, rel=1e-9)
    assert stats["radius_edge_max"] == pytest.approx(np.sqrt(6) / 4, rel=1e-9)
    assert stats["volume_ratio"] == pytest.approx(1.0)


def test_check_mesh_rejects_a_sliver_by_name_with_its_angle():
    # a good beam plus one near-flat tet: a square's corners lifted by 1e-3 at one of them
    v, t = M.beam_tets(2, 1, 1, 1.0, 1.0, 1.0)
    n = len(v)
    sliver_pts = np.array([[3, 0, 0], [4, 0, 0], [3, 1, 0], [4, 1, 1e-3]], float)
    v2 = np.vstack([v, sliver_pts])
    s = np.array([[n, n + 1, n + 2, n + 3]])
    if M.tet_volumes(v2, s)[0] < 0:
        s = s[:, [1, 0, 2, 3]]
    t2 = np.vstack([t, s])
    from latentsim.mesh.quality import _tet_quality
    angle = _tet_quality(v2, s)["dihedral"].min()
    assert angle < 0.2
    with pytest.raises(MeshError) as err:
        M.check_mesh(v2, tets=t2, name="sliver beam", min_dihedral_deg=5.0)
    msg = str(err.value)
    assert msg.startswith("sliver beam: tet 12 ")
    assert f"dihedral angle of {angle:.4g} degrees, below the bound of 5" in msg
    # the good beam passes the same gate; without a gate the sliver only shows in the statistics
    assert M.check_mesh(v, tets=t, min_dihedral_deg=5.0)["n_below_min_dihedral"] == 0
    assert M.check_mesh(v2, tets=t2)["dihedral_min_deg"] == pytest.approx(angle)


def test_scene_mesh_gate_from_config(tmp_path, icosphere):
    V, F = icosphere(1)
    import meshio
    path = tmp_path / "ball.stl"
    meshio.write(str(path), meshio.Mesh(V, [("triangle", F)]))
    cfg = {"generator": "file", "file": str(path), "target_vertices": 80,
           "quality": {"tetgen": True, "radius_edge": 2.0, "min_dihedral_deg": 10.0,
                       "gate_min_dihedral_deg": 5.0}}
    rule = {"type": "extreme", "axis": "y", "side": "min", "fraction": 0.2}
    arrays, q = M.scene_mesh("ball", "tets", cfg, rule, {"cache_dir": str(tmp_path)})
    assert q["dihedral_min_deg"] >= 5.0 and q["n_below_min_dihedral"] == 0
    cfg["quality"]["gate_min_dihedral_deg"] = 69.0  # no tet mesh of a sphere meets this
    with pytest.raises(MeshError, match=r"ball: tet \d+ .* below the bound of 69"):
        M.scene_mesh("ball", "tets", cfg, rule, {"cache_dir": str(tmp_path)})


def test_quality_table_has_a_row_per_scene_with_the_gate_passed(tmp_path):
    import pandas as pd

    from latentsim.stages.mesh import QUALITY_COLUMNS, prepare_mesh, write_quality_table

    beam = {"generator": "beam_tets", "nx": 4, "ny": 2, "nz": 2, "length": 0.2, "width": 0.05,
            "height": 0.05}
    cloth = {"generator": "cloth_grid", "nx": 4, "ny": 3, "width": 0.4, "height": 0.3,
             "plane": "xy"}
    rule = {"type": "extreme", "axis": "x", "side": "min", "fraction": 0.1}
    prepare_mesh("beam", "tets", beam, rule, {}, tmp_path / "beam.h5")
    prepare_mesh("sheet", "shell", cloth, rule, {}, tmp_path / "sheet.h5")
    out = tmp_path / "quality.csv"
    df = write_quality_table({"beam": tmp_path / "beam.h5", "sheet": tmp_path / "sheet.h5"}, out)
    read = pd.read_csv(out)
    assert list(read.columns) == ["scene", "model", *QUALITY_COLUMNS]
    assert read["scene"].tolist() == ["beam", "sheet"] and len(df) == 2
    b, s = read.iloc[0], read.iloc[1]
    assert b["n_tets"] > 0 and b["gate_min_dihedral_deg"] == 5.0 and b["n_below_min_dihedral"] == 0
    assert b["dihedral_min_deg"] >= 5.0 and b["radius_edge_max"] >= 0.612
    assert s["n_triangles"] == 24 and np.isnan(s["dihedral_min_deg"]) and s["angle_min_deg"] > 0


def _cube(origin, size=1.0):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float) * size + origin
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]])
    return v, f


def test_a_self_intersecting_surface_is_named_and_a_crashing_tetgen_stops_the_call_not_the_process():
    """Two interpenetrating cubes as one surface: TetGen's error says the surface intersects itself.  A library that
    aborts the process (as TetGen does on some damaged surfaces) is run in a child: its caller gets a MeshError."""
    import os as _os

    from latentsim.mesh.tetgen import _run_tetgen, in_child_process

    (v1, f1), (v2, f2) = _cube(np.zeros(3)), _cube(np.array([0.5, 0.3, 0.2]))
    with pytest.raises(MeshError, match="the surface intersects itself"):
        _run_tetgen(np.vstack([v1, v2]), np.vstack([f1, f2 + 8]), "pYa0.01")
    nodes, tets = _run_tetgen(v1, f1, "pYa0.01")  # a sound surface fills, through the same child process
    assert tets.shape[1] == 4 and np.isclose(np.abs(M.tet_volumes(nodes, tets)).sum(), 1.0)
    with pytest.raises(MeshError, match=r"TetGen crashed \(signal 6\)"):
        in_child_process(_os.abort)
    with pytest.raises(ZeroDivisionError):  # an ordinary exception comes back as itself
        in_child_process(divmod, 1, 0)
