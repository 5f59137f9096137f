"""The example of a scene of one's own (config/examples/ring.yaml): a user's STL end to end, a mistyped path.

Each run copies config/examples/ into a temporary working directory at the same place as in a checkout,
so the config's relative mesh path resolves as it does for a user running from the repository root.
"""

from __future__ import annotations

import importlib.util
import math
import shutil
import time

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml
from workflow_support import ROOT, snakemake

EXAMPLES = ROOT / "config" / "examples"
CONFIG = yaml.safe_load((EXAMPLES / "ring.yaml").read_text())
SCENE = CONFIG["scenes"]["ring"]


def load_make_mesh():
    spec = importlib.util.spec_from_file_location("make_mesh", EXAMPLES / "make_mesh.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MAKE_MESH = load_make_mesh()


def checkout_like(work, mesh_file=None):
    """config/examples/ copied into ``work``; with ``mesh_file``, a config ``typo.yaml`` pointing there."""
    shutil.copytree(EXAMPLES, work / "config" / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    if mesh_file is None:
        return work / "config" / "examples" / "ring.yaml"
    cfg = yaml.safe_load((EXAMPLES / "ring.yaml").read_text())
    cfg["scenes"]["ring"]["mesh"]["file"] = mesh_file
    path = work / "config" / "examples" / "typo.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.fixture(scope="module")
def ring_run(tmp_path_factory):
    """One complete `snakemake all` of the example config in a fresh working directory."""
    work = tmp_path_factory.mktemp("ring")
    config = checkout_like(work)
    t0 = time.perf_counter()
    snakemake("all", "--cores", "2", "--configfile", str(config), "--directory", str(work))
    print(f"example scene: snakemake all took {time.perf_counter() - t0:.0f} s")
    return work


def test_make_mesh_writes_the_committed_file(tmp_path):
    """The script regenerates config/examples/ring.stl byte for byte."""
    MAKE_MESH.main(["make_mesh.py", str(tmp_path / "ring.stl")])
    assert (tmp_path / "ring.stl").read_bytes() == (EXAMPLES / "ring.stl").read_bytes()


def test_example_mesh_is_the_files_ring_filled_with_tets(ring_run):
    """The tets fill exactly the file's polyhedron (in metres), keep its every surface vertex, and hold the
    lowest 10% of the ring."""
    scale = SCENE["mesh"]["scale"]
    V_file, _ = MAKE_MESH.ring_surface()
    V_file = V_file * scale
    with h5py.File(ring_run / "results/mesh/ring/mesh.h5") as f:
        V, T, D = f["rest_positions"][()], f["tets"][()], f["dirichlet"][()]
        quality = {k[len("quality_"):]: v for k, v in f.attrs.items() if k.startswith("quality_")}
    target = SCENE["mesh"]["target_vertices"]
    assert len(V_file) < len(V) <= 1.2 * target  # the surface's vertices and TetGen's interior ones
    a, b, c = (V[T[:, i]] - V[T[:, 0]] for i in (1, 2, 3))
    vol = np.einsum("ij,ij->i", np.cross(a, b), c) / 6
    assert (vol > 0).all()
    # the polyhedron's exact volume (float32 corners in the STL), 7.5% below the smooth torus's 2 pi^2 R r^2
    assert vol.sum() == pytest.approx(MAKE_MESH.polyhedron_volume() * scale**3, rel=1e-6)
    smooth = 2 * math.pi**2 * MAKE_MESH.MAJOR_RADIUS * MAKE_MESH.TUBE_RADIUS**2 * scale**3
    assert 0.90 * smooth < vol.sum() < smooth
    rounding = 1e-6 * np.abs(V_file).max()  # float32 corners in the STL
    nearest = np.sqrt(((V_file[:, None, :] - V[None, :, :]) ** 2).sum(-1)).min(axis=1)
    assert nearest.max() < rounding  # every vertex of the file
    assert np.allclose(V.min(0), V_file.min(0), atol=rounding) and np.allclose(V.max(0), V_file.max(0), atol=rounding)
    assert quality["n_inverted"] == 0 and quality["n_degenerate_tets"] == 0 and quality["dihedral_min_deg"] > 1.0
    rule = SCENE["dirichlet"]
    y = V[:, 1]
    cut = y.min() + rule["fraction"] * (y.max() - y.min())
    assert len(D) > 3 and sorted(D) == sorted(np.flatnonzero(y <= cut + 1e-12))


def test_example_simulation_converged_and_moved(ring_run):
    """Every stored full-space frame met the Newton tolerance, and the ring deforms (not only carried)."""
    with h5py.File(ring_run / "results/sim/ring/trajectories.h5") as f:
        tol = f.attrs["newton_tolerance"] * f.attrs["force_scale"]
        rest, D = f["rest_positions"][()], f["dirichlet"][()]
        diag = np.linalg.norm(rest.max(0) - rest.min(0))
        assert sorted(f["sequences"]) == ["sway", "sway_train"]
        for name, seq in f["sequences"].items():
            x, g = seq["positions"][()], seq["gradient_norm"][()]
            assert np.isfinite(x).all() and (g[1:] <= tol).all(), name
            carried = x[:, D[:1]] - rest[D[:1]]  # the held set moves rigidly without rotation here
            assert np.abs(x[:, D] - rest[D] - carried).max() < 1e-9
            assert np.linalg.norm(x - carried - rest, axis=2).max() > 0.02 * diag, name


def test_example_rollout_is_evaluated(ring_run):
    """The learned rollout stays close to the full simulation (a loose bound: tiny networks), and the
    evaluation tables hold its row."""
    summary = pd.read_csv(ring_run / "results/evaluation/summary.csv")
    row = summary[(summary["scene"] == "ring") & (summary["method"] == "self_supervised")]
    assert len(row) == 1
    row = row.iloc[0]
    assert row["sequence"] == "sway" and row["frames"] == SCENE["sequences"][0]["frames"]
    assert row["diverged_frame"] == -1
    assert np.isfinite(row["mean_error"]) and 0 < row["mean_error"] < 0.05  # of the bounding-box diagonal
    assert row["max_error"] < 0.25
    metrics = pd.read_csv(ring_run / "results/evaluation/ring/metrics.csv")
    assert "self_supervised" in set(metrics["method"])
    assert "ring" in (ring_run / "results/evaluation/summary.md").read_text()
    assert (ring_run / "results/evaluation/ring/frames.png").stat().st_size > 1000


@pytest.mark.parametrize("mesh_file, hint", [
    ("config/examples/rign.stl", "did you mean 'config/examples/ring.stl'?"),
    ("config/exampels/ring.stl", "folder 'config/exampels' does not exist"),
])  # fmt: skip
def test_mistyped_mesh_path_stops_before_any_job(tmp_path, mesh_file, hint):
    config = checkout_like(tmp_path, mesh_file)
    proc = snakemake("-n", "all", "--cores", "1", "--configfile", str(config), "--directory", str(tmp_path), check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert f"config key 'scenes.ring.mesh.file': mesh file '{mesh_file}' not found" in out, out[-3000:]
    assert hint in out and "relative to the working directory" in out
    assert not (tmp_path / "results").exists()


def test_mistyped_mesh_path_is_not_skipped_beside_old_results(ring_run, tmp_path):
    """With the mesh already built, Snakemake alone would skip the missing input ("Nothing to be done")."""
    config = checkout_like(tmp_path, "config/examples/rign.stl")
    proc = snakemake("-n", "all", "--cores", "1", "--configfile", str(config), "--directory", str(ring_run), check=False)
    assert proc.returncode != 0
    assert "config key 'scenes.ring.mesh.file': mesh file 'config/examples/rign.stl' not found" in proc.stdout + proc.stderr
