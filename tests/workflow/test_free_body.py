"""A free body (``dirichlet: {type: free}``) through every stage: a small block thrown up with a spin, landing on
the ground.  Nothing is prescribed, so the stages that compare or re-apply prescribed positions must hold with
an empty set; the full space must keep the block out of the ground with the thrown start recorded."""

from __future__ import annotations

import importlib.util

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml
from workflow_support import ROOT, snakemake

SCENE = {
    "model": "tets",
    "mesh": {"generator": "beam_tets", "nx": 2, "ny": 2, "nz": 2, "length": 0.1, "width": 0.1, "height": 0.1,
             "rotate_axis": [1, 0, 1], "rotate_degrees": 35},
    "dirichlet": {"type": "free"},
    "material": {"youngs_modulus": 1.0e5, "poisson_ratio": 0.3, "density": 1000.0},
    "contact": {"colliders": [{"type": "half_space", "point": [0.0, -0.15, 0.0], "normal": [0.0, 1.0, 0.0]}]},
    "sequences": [
        {"name": "toss", "split": "train", "frames": 30, "initial_velocity": [0, 0.5, 0], "initial_angular_velocity": [0, 0, 3]},
        {"name": "throw", "split": "test", "frames": 30, "initial_velocity": [0, 0.3, 0], "initial_angular_velocity": [-1, 0, 1]},
    ],
    "autoencoder": {"latent_dim": 6, "widths": [32], "epochs": 150, "lr": 1.0e-3, "batch_size": 32},
    "integrator": {"widths": [32, 32], "epochs": 150, "lr": 1.0e-3, "batch_size": 32},
    "baselines": ["newton_1it"],
}


@pytest.fixture(scope="module")
def free_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("free_body")
    config = work / "free.yaml"
    config.write_text(yaml.safe_dump({"seeds": [0], "device": "cpu", "scenes": {"tiny_drop": SCENE}}))
    snakemake("all", "--cores", "2", "--configfile", str(config), "--directory", str(work))
    return work


def test_the_full_space_keeps_a_thrown_free_body_out_of_the_ground_from_its_recorded_start(free_run):
    spec = importlib.util.spec_from_file_location("check_frames", ROOT / "benchmarks" / "check_frames.py")
    check_frames = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check_frames)
    path = free_run / "results" / "sim" / "tiny_drop" / "trajectories.h5"
    with h5py.File(path) as f:
        assert f["dirichlet"].shape == (0,)
        assert f["sequences/throw"].attrs["initial_velocity"].tolist() == [0, 0.3, 0, -1, 0, 1]
        x = f["sequences/throw/positions"][()]
        near = f["sequences/throw/min_contact_distance"][()]
    assert near.min() > 0 and x[-1, :, 1].min() < x[0, :, 1].min() - 0.05  # it fell onto the ground, never into it
    report = check_frames.check(path)
    assert report["frames"] == 29 + 29 and report["worst"] <= 1.0 and report["nearest"] > 0
    for name in ("toss", "throw"):
        assert (free_run / "results" / "sim" / "tiny_drop" / "paraview" / f"{name}.xdmf").is_file()


def test_every_method_is_measured_with_no_prescribed_set_to_compare(free_run):
    """Every method has its row, its error and its penetration; the Dirichlet error, with nothing prescribed, is
    empty rather than a number; the stress conditions a free body has ran; the report's pages were written."""
    ev = free_run / "results" / "evaluation"
    metrics = pd.read_csv(ev / "tiny_drop" / "metrics.csv")
    assert sorted(metrics["method"]) == ["newton_1it", "self_supervised"]
    assert metrics["dirichlet_error"].isna().all()
    assert np.isfinite(metrics["mean_error"]).all() and (metrics["max_penetration"] >= 0).all()
    stress = pd.read_csv(ev / "tiny_drop" / "stress.csv")
    # nothing prescribed, no program to speed up, stop or reverse: the long rollout and the perturbed start alone
    assert sorted(stress["condition"]) == ["long_x10", "perturbed_start"] and stress["bc_error"].isna().all()
    assert (ev / "summary.html").is_file() and (ev / "tiny_drop" / "clip.gif").is_file()
