"""The Snakemake workflow as users run it: lint, dry runs, the tiny config end to end.

The tiny config runs in temporary working directories (``snakemake -d``), so
the repository's own results/ is never touched.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml

from latentsim.config import scene_methods, validate_config

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "config" / "tiny.yaml"
SCENES_TINY = ["tiny_cloth", "tiny_rods"]
STAGES = ["prepare_mesh", "simulate", "train_autoencoder", "train_integrator", "rollout", "evaluate"]
# values that measure wall time, the only things allowed to differ between two identical runs
TIMING_DATASETS = {"frame_ms", "step_ms"}
TIMING_ATTRS = {"train_seconds", "rollout_seconds", "step_ms", "integrate_ms", "decode_ms", "autoencoder_train_seconds", "integrator_train_seconds",
                "full_ms", "runtime", "jvp_torch_ms", "jvp_forward_ms"} | {f"{r}_{k}_ms" for r in ("numpy", "torchscript", "eager") for k in ("step", "integrate", "decode")}  # fmt: skip


def snakemake(*args, cwd=ROOT, check=True, timeout=600):
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), *args]
    env = dict(os.environ, CI="1")
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc


def planned_jobs(output: str, methods: bool = False) -> list[tuple]:
    """(rule, scene) of every job a dry run lists; (rule, scene, method) with ``methods``."""
    jobs = []
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", output):
        m = re.match(r"(?:local)?rule (\w+):", block.strip())
        if not m:
            continue
        w = re.search(r"wildcards: [^\n]*\bscene=(\w+)", block)
        job = (m.group(1), w.group(1) if w else None)
        if methods:
            v = re.search(r"wildcards: [^\n]*\bmethod=(\w+)", block)
            job += (v.group(1) if v else None,)
        jobs.append(job)
    return jobs


def test_lint_is_clean():
    proc = snakemake("--lint", check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Lints for" not in proc.stdout + proc.stderr


def test_dry_run_of_default_config_lists_every_stage_for_every_scene(tmp_path):
    """In an empty directory (the repository's own results/ may be partly up to date)."""
    scenes = sorted(yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["scenes"])
    cfg = validate_config(yaml.safe_load((ROOT / "config" / "config.yaml").read_text()))
    out = snakemake("-n", "all", "--cores", "2", "--configfile", str(ROOT / "config" / "config.yaml"), "--directory", str(tmp_path)).stdout
    jobs = planned_jobs(out, methods=True)
    for stage in STAGES:
        assert sorted({s for r, s, _ in jobs if r == stage}) == scenes, stage
    for stage in ("train_integrator", "rollout"):  # one job per method of each scene
        for scene in scenes:
            assert sorted(m for r, s, m in jobs if r == stage and s == scene) == sorted(scene_methods(cfg, scene)), (stage, scene)
    assert ("summary", None, None) in jobs


def test_slurm_profile_dry_run(tmp_path):
    out = snakemake("-n", "all", "--workflow-profile", str(ROOT / "profiles" / "slurm"), "--configfile", str(TINY), "--directory", str(tmp_path)).stdout
    jobs = planned_jobs(out)
    assert ("train_integrator", "tiny_rods") in jobs


@pytest.mark.parametrize(
    "edit, key",
    [
        (lambda c: c["scenes"]["tiny_rods"].update(bogus=1), "scenes.tiny_rods"),
        (lambda c: c["scenes"]["tiny_rods"]["material"].update(youngs_modulus=-5.0), "scenes.tiny_rods.material.youngs_modulus"),
        (lambda c: c["scenes"]["tiny_cloth"]["material"].update(density="heavy"), "scenes.tiny_cloth.material.density"),
        (lambda c: c["scenes"]["tiny_cloth"].update(variants=["nonexistent"]), "scenes.tiny_cloth.variants"),
    ],
)
def test_malformed_config_stops_before_any_job(tmp_path, edit, key):
    cfg = yaml.safe_load(TINY.read_text())
    edit(cfg)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(cfg))
    proc = snakemake("all", "--cores", "1", "--configfile", str(bad), "--directory", str(tmp_path), check=False)
    assert proc.returncode != 0
    assert f"config key '{key}'" in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


# --- the tiny config end to end -----------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One complete run of the tiny config in a fresh directory."""
    work = tmp_path_factory.mktemp("tiny_a")
    t0 = time.perf_counter()
    snakemake("all", "--cores", "2", "--configfile", str(TINY), "--directory", str(work))
    return work, time.perf_counter() - t0


def test_tiny_run_writes_tables_and_figures(tiny_run):
    work, _ = tiny_run
    import pandas as pd

    table = pd.read_csv(work / "results/evaluation/summary.csv")
    assert sorted(table["scene"].unique()) == SCENES_TINY
    assert np.isfinite(table[["mean_error", "full_ms", "latent_ms"]].to_numpy()).all()
    for scene in SCENES_TINY:
        assert (work / f"results/evaluation/{scene}/errors.png").stat().st_size > 1000
        assert (work / f"results/evaluation/{scene}/frames.png").stat().st_size > 1000
        assert (work / f"results/evaluation/{scene}/clip.gif").stat().st_size > 1000
        assert list((work / f"results/evaluation/{scene}/paraview").glob("self_supervised_*.xdmf"))
        assert (work / f"results/sim/{scene}/paraview").is_dir()
        assert (work / f"logs/sim/{scene}.log").read_text()
        assert (work / f"results/benchmarks/sim/{scene}.tsv").exists()
    assert (work / "results/evaluation/speed_accuracy.png").stat().st_size > 1000
    choice = pd.read_csv(work / "results/sweep/tiny_cloth/choice.csv")
    assert sorted(choice["latent_dim"]) == [2, 4] and choice["chosen"].sum() <= 1
    assert (work / "results/sweep/tiny_cloth/sweep.png").stat().st_size > 1000


def test_reduced_baselines_step_with_a_cubature(tiny_run):
    """tiny_cloth asks for a 1% cubature: the PCA, linear-modes and Fulton rollouts record one that
    fits and leaves out most elements, and still finish their test sequence."""
    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_cloth/trajectories.h5") as f:
        n_tri = len(f["triangles"])
    for method in ("pca_reduced", "modes_reduced", "fulton_reduced"):
        with h5py.File(work / f"results/rollout/tiny_cloth/{method}/rollout.h5") as g:
            assert g.attrs["cubature_force_error"] <= 0.01
            k = int(g.attrs["cubature_elements"])
            assert 0 < k == len(g["cubature_index"]) < n_tri  # triangles + hinges together: far fewer
            assert (g["cubature_weights"][()] > 0).all()
            assert g["sequences/line"].attrs["diverged_frame"] == -1


def test_tiny_cloth_swings_out_of_its_plane(tiny_run):
    """The cloth hangs in the xy plane; its corners move along z, so it must bend out of that plane.

    Moved within its own plane (as once configured) it stays exactly flat and barely deforms, and every
    learning stage downstream faces a trivially low-dimensional motion.
    """
    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_cloth/trajectories.h5") as f:
        x = f["sequences/line/positions"][()]
        D = f["dirichlet"][()]
        rest = f["rest_positions"][()]
    rel = x - x[:, D].mean(axis=1, keepdims=True)  # the autoencoder's coordinates
    diag = np.linalg.norm(rest.max(0) - rest.min(0))
    assert np.ptp(rest[:, 2]) == 0.0
    assert np.ptp(rel[..., 2], axis=1).max() > 0.05 * diag


def test_paraview_series_reads_back(tiny_run):
    """The XDMF time series holds every frame's displacement, equal to the stored positions."""
    import meshio

    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_rods/trajectories.h5") as f:
        pos = f["sequences/test_mid/positions"][()]
    from latentsim.utils import working_directory

    with working_directory(work / "results/sim/tiny_rods/paraview"):
        with meshio.xdmf.TimeSeriesReader("test_mid.xdmf") as r:
            points, cells = r.read_points_cells()
            assert r.num_steps == len(pos)
            t, point_data, _ = r.read_data(len(pos) - 1)
    assert np.allclose(points, pos[0])
    assert np.allclose(points + point_data["displacement"], pos[-1])


def test_report_holds_tables_and_figures(tiny_run, tmp_path):
    work, _ = tiny_run
    report = tmp_path / "report.zip"
    snakemake("--report", str(report), "--configfile", str(TINY), "--directory", str(work))
    import zipfile

    names = zipfile.ZipFile(report).namelist()
    assert any(n.endswith("summary.csv") for n in names)
    assert any(n.endswith("speed_accuracy.png") for n in names)
    assert any(n.endswith("errors.png") for n in names)


def test_artefacts_record_config_version_and_seed(tiny_run):
    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_rods/trajectories.h5") as f:
        assert '"youngs_modulus"' in f.attrs["config"] and f.attrs["latentsim_version"]
        assert f["sequences/test_mid"].attrs["split"] == "test"
    with h5py.File(work / "results/autoencoder/tiny_rods/latents.h5") as f:
        assert f.attrs["seed"] == 0 and '"latent_dim"' in f.attrs["config"]


def test_editing_one_scenes_integrator_reruns_only_its_downstream_jobs(tiny_run, tmp_path):
    work, _ = tiny_run
    cfg = yaml.safe_load(TINY.read_text())
    cfg["scenes"]["tiny_rods"]["integrator"]["epochs"] += 1
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(cfg))
    unchanged = planned_jobs(snakemake("-n", "all", "--configfile", str(TINY), "--directory", str(work)).stdout)
    assert unchanged == [], unchanged
    quiet = planned_jobs(snakemake("-n", "all", "--configfile", str(TINY), "--config", "progress=False", "--directory", str(work)).stdout)
    assert quiet == [], f"progress bars must not trigger reruns: {quiet}"
    jobs = planned_jobs(snakemake("-n", "all", "--configfile", str(edited), "--directory", str(work)).stdout)
    methods = ("self_supervised", "supervised")
    assert sorted(jobs, key=str) == sorted(
        [(stage, "tiny_rods") for stage in ("train_integrator", "rollout") for _ in methods]
        + [("evaluate", "tiny_rods"), ("render", "tiny_rods"), ("summary", None), ("all", None)],
        key=str,
    )


def test_editing_a_variant_reruns_only_that_methods_jobs(tiny_run, tmp_path):
    work, _ = tiny_run
    cfg = yaml.safe_load(TINY.read_text())
    cfg["integrator_variants"]["supervised"]["epochs"] = 7
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(cfg))
    jobs = planned_jobs(snakemake("-n", "all", "--configfile", str(edited), "--directory", str(work)).stdout, methods=True)
    assert sorted(jobs, key=str) == sorted(
        [("train_integrator", "tiny_rods", "supervised"), ("rollout", "tiny_rods", "supervised"), ("evaluate", "tiny_rods", None),
         ("render", "tiny_rods", None), ("summary", None, None), ("all", None, None)],
        key=str,
    )  # fmt: skip


def _h5_contents(path):
    out = {}

    def visit(name, obj):
        for k, v in obj.attrs.items():
            if k not in TIMING_ATTRS:
                out[f"{name}@{k}"] = v
        if isinstance(obj, h5py.Dataset) and name.split("/")[-1] not in TIMING_DATASETS:
            out[name] = obj[()]

    with h5py.File(path) as f:
        visit("/", f)
        f.visititems(visit)
    return out


def test_same_seed_gives_identical_artefacts(tiny_run, tmp_path):
    work_a, _ = tiny_run
    work_b = tmp_path / "tiny_b"
    snakemake("all", "--cores", "2", "--configfile", str(TINY), "--directory", str(work_b))
    files = sorted(p.relative_to(work_a) for p in (work_a / "results").rglob("*") if p.suffix in (".h5", ".pt", ".npz") and p.name != "runtime.pt")
    assert len(files) >= 5 * len(SCENES_TINY)
    for rel in files:
        a, b = work_a / rel, work_b / rel
        if rel.suffix == ".npz":  # the exported NumPy runtime
            with np.load(a) as na, np.load(b) as nb:
                assert sorted(na.files) == sorted(nb.files), rel
                assert all(np.array_equal(na[k], nb[k]) for k in na.files), rel
            continue
        if rel.suffix == ".pt":
            ba, bb = torch.load(a, weights_only=True), torch.load(b, weights_only=True)
            key = "state_dict" if "state_dict" in ba else "model"  # modules, or training checkpoints
            sa, sb = ba[key], bb[key]
            assert sa.keys() == sb.keys()
            assert all(torch.equal(sa[k], sb[k]) for k in sa), rel
            continue
        ca, cb = _h5_contents(a), _h5_contents(b)
        assert ca.keys() == cb.keys(), rel
        for k in ca:
            assert np.array_equal(np.asarray(ca[k]), np.asarray(cb[k]), equal_nan=np.asarray(ca[k]).dtype.kind == "f"), f"{rel}:{k}"


def test_sigkill_mid_job_leaves_no_complete_looking_output(tmp_path):
    """Kill the whole Snakemake process group while the simulation runs."""
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "results/sim/tiny_rods/trajectories.h5",
           "--cores", "1", "--configfile", str(TINY), "--directory", str(tmp_path)]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=dict(os.environ, CI="1"))
    log = tmp_path / "logs/sim/tiny_rods.log"
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not (log.exists() and "linear solver" in log.read_text()):
            time.sleep(0.05)
        assert log.exists(), "the simulation never started"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert not (tmp_path / "results/sim/tiny_rods/trajectories.h5").exists()
    jobs = planned_jobs(snakemake("-n", "results/sim/tiny_rods/trajectories.h5", "--configfile", str(TINY), "--directory", str(tmp_path)).stdout)
    assert ("simulate", "tiny_rods") in jobs
