"""The Snakemake workflow as users run it: lint, dry runs, the tiny config end to end.

The tiny config runs in temporary working directories (``snakemake -d``), so
the repository's own results/ is never touched.
"""

from __future__ import annotations

import copy
import json
import os
import re
import signal
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml

from latentsim.checksum import KEY as CHECKSUM
from latentsim.config import load_config, scene_methods, scene_seeds, validate_config

from workflow_support import HANG_SECONDS, snakemake

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "config" / "tiny.yaml"
SCENES_TINY = ["tiny_cloth", "tiny_contact", "tiny_nm", "tiny_rods"]
STAGES = ["prepare_mesh", "simulate", "train_autoencoder", "train_integrator", "rollout", "evaluate"]
# values that measure wall time, the only things allowed to differ between two identical runs: these, and
# every dataset or attribute whose name ends in _ms or _seconds, or is "seconds" (is_timing)
TIMING_DATASETS = {"frame_ms", "step_ms"}
TIMING_ATTRS = {"train_seconds", "rollout_seconds", "step_ms", "integrate_ms", "decode_ms", "autoencoder_train_seconds", "integrator_train_seconds",
                "full_ms", "runtime", "jvp_torch_ms", "jvp_forward_ms"} | {f"{r}_{k}_ms" for r in ("numpy", "compiled", "torch_export", "eager") for k in ("step", "integrate", "decode")}  # fmt: skip
# the Neural Modes stages of the default config: (rule, scene) of every job, beside those of every scene (STAGES)
NM_JOBS_DEFAULT = (
    [(r, s) for r in ("nm_linear_modes", "nm_train") for s in ("nm_armadillo", "nm_bunny", "nm_giraffe", "nm_sheet")]
    + [("nm_ground_truth", "nm_sheet"), ("nm_sheet_tables", "nm_sheet")] + 3 * [("nm_sheet_study", "nm_sheet")]  # one per seed
    + [("nm_ground_truth", "nm_armadillo"), ("nm_energy_table", "nm_armadillo")]
    + [("nm_dynamics", s) for s in ("nm_armadillo", "nm_bunny", "nm_giraffe")]
    + [("nm_keyframes", "nm_giraffe"), ("nm_aspect_ratio", "nm_sheet"), ("nm_summary", None)]
    + [(r, s) for r in ("nm_linear_modes", "nm_train") for s in ("bunny_ears", "cantilever", "cloth", "hair_rotation", "hair_translation")]  # for their neural_modes_reduced baselines
)


def is_timing(name: str, explicit: set) -> bool:
    """A wall-time field: named in ``explicit`` or by its suffix."""
    return name in explicit or name == "seconds" or name.endswith(("_ms", "_seconds"))



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


def planned_outputs(output: str) -> list[str]:
    """'rule: outputs' of every job a dry run lists, sorted (the format of tests/workflow/data/default_jobs.txt)."""
    jobs = []
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", output):
        m = re.match(r"(?:local)?rule (\w+):", block.strip())
        if m:
            o = re.search(r"\n\s+output: ([^\n]*)", block)
            jobs.append(f"{m.group(1)}: {o.group(1) if o else '-'}")
    return sorted(jobs)


def test_rules_are_in_snakefmt_form():
    proc = subprocess.run([sys.executable, "-m", "snakefmt", "--check", "Snakefile", "workflow/rules"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


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
    for stage in ("train_integrator", "rollout"):  # one job per method and seed of each scene
        for scene in scenes:
            want = sorted(m for m in scene_methods(cfg, scene) for _ in scene_seeds(cfg, scene))
            assert sorted(m for r, s, m in jobs if r == stage and s == scene) == want, (stage, scene)
    # Fig. 8's paper-size scenes run five seeds, the other Li et al. scenes three
    assert [scene_seeds(cfg, s) for s in ("cloth_paper", "cantilever_paper", "cloth")] == [[0, 1, 2, 3, 4]] * 2 + [[0, 1, 2]]
    assert ("summary", None, None) in jobs
    assert sorted(((r, s) for r, s, _ in jobs if r.startswith("nm_")), key=str) == sorted(NM_JOBS_DEFAULT, key=str)
    # the same jobs, with the same outputs, as recorded (its header says what changed since the restructuring)
    recorded = [line for line in (ROOT / "tests/workflow/data/default_jobs.txt").read_text().splitlines() if not line.startswith("#")]
    assert planned_outputs(out) == recorded


def test_planning_all_imports_no_torch_numba_or_matplotlib(tmp_path):
    """The Snakefile's parse, the config's validation and every rule's params of a dry run of all (the tiny config:
    every stage, Neural Modes captions included) use latentsim.labels and the materials table, not the stages:
    each snakemake command, and each cluster job's parse, would otherwise import torch first (about 4 s a time)."""
    heavy = ("torch", "numba", "matplotlib", "scipy")
    code = ("import atexit, sys\n"
            f"atexit.register(lambda: print('HEAVY', sorted(m for m in {heavy!r} if m in sys.modules)))\n"
            "from snakemake.cli import main\n"
            "main(sys.argv[1:])\n")
    args = ["-n", "all", "--snakefile", str(ROOT / "Snakefile"), "--configfile", str(TINY), "--directory", str(tmp_path)]
    proc = subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True, text=True, timeout=HANG_SECONDS,
                          env=dict(os.environ, CI="1"))
    assert "rule train_integrator" in proc.stdout and "rule nm_dynamics" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "HEAVY []" in proc.stdout, proc.stdout[-500:]


def test_the_sizing_sweeps_are_a_target_of_their_own_and_all_shows_those_that_ran(tmp_path):
    """`all` on the default config plans no sweep job (the dry run above); `sizing` plans every scene's sweep and
    nothing past the methods it measures; once a sweep's choice exists, `all`'s report takes it in."""
    config = str(ROOT / "config" / "config.yaml")
    swept = sorted(n for n, s in load_config(ROOT / "config" / "config.yaml")["scenes"].items() if s["sweep"].get("latent_dims"))
    jobs = planned_jobs(snakemake("-n", "sizing", "--cores", "2", "--configfile", config, "--directory", str(tmp_path)).stdout)
    assert sorted({s for r, s in jobs if r == "sweep_summary"}) == swept
    assert not {r for r, _ in jobs} & {"evaluate", "summary", "rollout", "nm_train"}
    choice = tmp_path / "results/sweep/cloth/choice.csv"
    choice.parent.mkdir(parents=True)
    choice.write_text("latent_dim\n4\n")
    jobs = planned_jobs(snakemake("-n", "all", "--cores", "2", "--configfile", config, "--directory", str(tmp_path)).stdout)
    # (here the cloth's points are missing, so its sweep is planned again; no other scene's)
    assert ("report_sweep_page", "cloth") in jobs and {s for r, s in jobs if r.startswith("sweep_")} == {"cloth"}


def test_a_second_configs_all_is_refused_before_any_job_where_another_configs_summary_is(tmp_path):
    """The summary (and so the report) of one config's run is not replaced by a run whose config lacks its scenes (another
    config's `all` in the same folder): refused while the DAG is built, naming the scenes (a dry run warns); a config
    that holds them (the same, an edited copy, one more scene) goes on."""
    owner = tmp_path / "results/evaluation/summary_config.json"
    owner.parent.mkdir(parents=True)
    owner.write_text(json.dumps({"scenes": ["ring"]}))
    out = snakemake("--cores", "1", "all", "--configfile", str(TINY), "--directory", str(tmp_path), check=False)
    said = out.stdout + out.stderr
    assert out.returncode != 0 and "hold scenes this config lacks (ring)" in said and "this run would replace them" in said
    assert not (tmp_path / "results/mesh").exists()
    dry = snakemake("-n", "all", "--configfile", str(TINY), "--directory", str(tmp_path))
    assert "Warning: results/evaluation/summary.* and the report hold scenes this config lacks (ring)" in dry.stdout + dry.stderr
    owner.write_text(json.dumps({"scenes": ["tiny_rods"]}))
    same = snakemake("-n", "all", "--configfile", str(TINY), "--directory", str(tmp_path))
    assert "Warning: results/evaluation/summary" not in same.stdout + same.stderr


def test_dry_run_of_the_soft_solids_example_plans_every_stage_of_both_scenes(tmp_path):
    """config/examples/soft_solids.yaml (neo-Hookean giraffe and armadillo) validates and plans the simulation,
    the latent methods with their variant and the giraffe's Neural Modes (its full run:
    docs/measurements.md#soft-solids)."""
    config = ROOT / "config" / "examples" / "soft_solids.yaml"
    scenes = yaml.safe_load(config.read_text())["scenes"]
    assert {s["material"]["model"] for s in scenes.values()} == {"neohookean"}
    jobs = planned_jobs(snakemake("-n", "all", "--cores", "2", "--configfile", str(config), "--directory", str(tmp_path)).stdout, methods=True)
    for stage in ("prepare_mesh", "simulate", "train_autoencoder", "evaluate"):
        assert sorted(s for r, s, _ in jobs if r == stage) == sorted(scenes), stage
    for scene in scenes:
        assert sorted(m for r, s, m in jobs if r == "train_integrator" and s == scene) == ["hybrid_w1e4", "self_supervised"], scene
    assert [s for r, s, _ in jobs if r == "nm_train"] == ["giraffe_neohookean"]


def _assert_example_plans_its_scene(config, scene, tmp_path):
    """A contact example's dry run of `all`: every stage of its one scene, an integrator per seed (three), and the
    two reduced baselines."""
    jobs = planned_jobs(snakemake("-n", "all", "--cores", "2", "--configfile", str(config), "--directory", str(tmp_path)).stdout, methods=True)
    for stage in ("prepare_mesh", "simulate", "train_autoencoder", "evaluate"):
        assert {s for r_, s, _ in jobs if r_ == stage} == {scene}, stage
    assert sum(r_ == "train_integrator" for r_, _, _ in jobs) == 3  # one per seed
    assert sorted(m for r_, s, m in jobs if r_ == "reduced_rollout") == ["newton_1it", "pca_reduced"]


def test_the_hair_head_scene_turns_a_ring_of_hair_about_its_head():
    """hair_head (hair on a ring of roots about a sphere collider; the default config's dry run plans it): its ring
    of roots lies outside the head, each root as far from the head's centre (the centre the program turns the
    roots about), so that the head stays where it is (its run: docs/measurements.md#contact)."""
    from latentsim.mesh import rod_bundle

    scene = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["scenes"]["hair_head"]
    mesh, (head,) = scene["mesh"], scene["contact"]["colliders"]
    x, _, roots = rod_bundle(mesh["n_rods"], mesh["vertices_per_rod"], mesh["length"], 0.01, ring_radius=mesh["ring_radius"])
    clamped = np.union1d(roots, roots + 1)
    np.testing.assert_allclose(x[clamped].mean(0), head["centre"], atol=1e-12)  # the program turns about the head's centre
    r = np.linalg.norm(x - np.asarray(head["centre"]), axis=1)
    np.testing.assert_allclose(r[clamped], r[clamped[0]])
    assert r.min() > head["radius"]


def test_the_bunny_drop_scene_throws_a_free_body_straight_up_and_down():
    """bunny_drop (the bunny, free, dropped onto a frictionless ground; the default config's dry run plans it): its
    throws are vertical and without spin (else it slides or turns for ever), and the test throw's speed lies
    between the training ones' (its run: docs/measurements.md#contact)."""
    scene = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["scenes"]["bunny_drop"]
    assert scene["dirichlet"] == {"type": "free"}
    speeds = {q["split"]: [] for q in scene["sequences"]}
    for q in scene["sequences"]:
        v = q.get("initial_velocity", [0.0, 0.0, 0.0])
        assert v[0] == v[2] == 0 and "initial_angular_velocity" not in q and "segments" not in q
        speeds[q["split"]].append(v[1])
    assert min(speeds["train"]) < min(speeds["test"]) <= max(speeds["test"]) < max(speeds["train"])
    assert not set(speeds["test"]) & set(speeds["train"])


def test_dry_run_of_the_cape_example_plans_a_cloth_against_a_body_that_moves_with_it(tmp_path):
    """config/examples/cape.yaml (a cloth held along its top edge, a capsule attached to the held vertices)
    validates and plans every stage of its scene; the held set fixes a pose (not on one line), the body starts
    clear of the cloth, and the test half walks at speeds between the training half's (its run:
    docs/measurements.md#contact)."""
    from latentsim.mesh import cloth_grid
    from latentsim.physics.colliders import Capsule
    from latentsim.scene import bc_parameters

    config = ROOT / "config" / "examples" / "cape.yaml"
    scene = yaml.safe_load(config.read_text())["scenes"]["cape"]
    (body,) = scene["contact"]["colliders"]
    assert body["attached"] is True
    m = scene["mesh"]
    x, _ = cloth_grid(m["nx"], m["ny"], m["width"], m["height"], plane=m["plane"])
    held = np.asarray(x)[scene["dirichlet"]["indices"]]
    assert np.linalg.svd(held - held.mean(0), compute_uv=False)[1] > 0.01  # not on one line
    clearance = Capsule(body["a"], body["b"], body["radius"]).distance(torch.as_tensor(np.asarray(x, dtype=float)))
    assert float(clearance.min()) == pytest.approx(0.01, abs=5e-4)
    (seq,) = scene["sequences"]
    p = bc_parameters(seq, seq["frames"])
    assert not p[:, 3:].any() and not p[:, :2].any()  # it walks along the sheet's normal and never turns
    train, test = p[: seq["train_frames"], 2], p[seq["train_frames"] :, 2]
    assert train.min() < test.min() < 0 < test.max() < train.max()
    assert not set(np.unique(test)) - {0.0} & set(np.unique(train))  # the test's speeds are none of the training's
    _assert_example_plans_its_scene(config, "cape", tmp_path)


def test_dry_run_of_the_bunny_slide_example_plans_a_free_body_thrown_across_a_ground_with_friction(tmp_path):
    """config/examples/bunny_slide.yaml (the bunny thrown sideways onto a ground with friction) validates and plans
    every stage of its scene; the ground has friction, the throws have no spin, and the test throw's sideways speed
    lies between the training throws' (its run: docs/measurements.md#contact)."""
    config = ROOT / "config" / "examples" / "bunny_slide.yaml"
    scene = yaml.safe_load(config.read_text())["scenes"]["bunny_slide"]
    assert scene["dirichlet"] == {"type": "free"} and scene["contact"]["friction"] > 0
    sideways = {q["split"]: [] for q in scene["sequences"]}
    for q in scene["sequences"]:
        assert "initial_angular_velocity" not in q
        sideways[q["split"]].append(q.get("initial_velocity", [0.0, 0.0, 0.0])[0])
    assert min(sideways["train"]) < min(sideways["test"]) <= max(sideways["test"]) < max(sideways["train"])
    _assert_example_plans_its_scene(config, "bunny_slide", tmp_path)


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
        # non-finite numbers (YAML .nan, .inf), which the schema's bounds let through
        (lambda c: c["scenes"]["tiny_rods"]["material"].update(youngs_modulus=float("nan")), "scenes.tiny_rods.material.youngs_modulus': nan is not a finite number"),
        (lambda c: c["scenes"]["tiny_cloth"].update(gravity=[0.0, float("-inf"), 0.0]), "scenes.tiny_cloth.gravity.1': -inf is not a finite number"),
        (lambda c: c["scenes"]["tiny_rods"]["integrator"].update(lr=float("inf")), "scenes.tiny_rods.integrator.lr': inf is not a finite number"),
        # what the config alone shows would go wrong after jobs have run
        (lambda c: c["scenes"]["tiny_rods"]["sequences"][1].update(name="train_slow"), "scenes.tiny_rods.sequences.1.name': scene tiny_rods stores sequence 1 'train_slow' as 'train_slow', as it does sequence 0"),
        (lambda c: c["scenes"]["tiny_rods"]["sequences"].pop(), "scenes.tiny_rods.sequences': scene tiny_rods has no sequence of split test"),
        (lambda c: c["scenes"]["tiny_nm"]["autoencoder"].update(latent_dim=16), "scenes.tiny_nm.autoencoder.latent_dim': latent_dim 16 of scene tiny_nm is above the rank of its training data: 16 training frames"),
    ],
)
def test_malformed_config_stops_before_any_job(tmp_path, edit, key):
    cfg = yaml.safe_load(TINY.read_text())
    edit(cfg)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(cfg))
    proc = snakemake("all", "--cores", "1", "--configfile", str(bad), "--directory", str(tmp_path), check=False)
    assert proc.returncode != 0
    assert f"config key '{key}" in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


def test_a_non_finite_number_on_the_command_line_stops_before_any_job(tmp_path):
    """``--config key=nan`` reaches the config as a float NaN (YAML files give ``.nan``)."""
    for value in ("nan", "inf"):
        proc = snakemake("all", "--cores", "1", "--configfile", str(TINY), "--config", f"seeds={value}", "--directory", str(tmp_path), check=False)
        assert proc.returncode != 0
        assert f"config key 'seeds': {value} is not a finite number" in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


# --- the tiny config end to end -----------------------------------------------------------------


def test_tiny_run_writes_tables_and_figures(tiny_run):
    work, _ = tiny_run
    import pandas as pd

    table = pd.read_csv(work / "results/evaluation/summary.csv")
    assert sorted(table["scene"].unique()) == SCENES_TINY
    assert np.isfinite(table[["full_ms", "latent_ms"]].to_numpy()).all()
    # every method stays stable (tiny_contact's integrator too, with the contact barrier in its loss)
    assert np.isfinite(table["mean_error"]).all()
    for scene in SCENES_TINY:
        assert (work / f"results/evaluation/{scene}/errors.png").stat().st_size > 1000
        assert (work / f"results/evaluation/{scene}/frames.png").stat().st_size > 1000
        assert (work / f"results/evaluation/{scene}/clip.gif").stat().st_size > 1000
        assert list((work / f"results/evaluation/{scene}/paraview").glob("self_supervised_*.xdmf"))
        assert (work / f"results/sim/{scene}/paraview").is_dir()
        assert (work / f"logs/sim/{scene}.log").read_text()
        assert (work / f"results/benchmarks/sim/{scene}.tsv").exists()
    assert (work / "results/evaluation/speed_accuracy.png").stat().st_size > 1000
    assert list((work / "results/integrator").rglob("integrator.pt"))
    assert not list((work / "results/integrator").rglob("checkpoint.pt"))  # a finished training leaves none
    choice = pd.read_csv(work / "results/sweep/tiny_cloth/choice.csv")
    t1 = pd.read_csv(work / "results/evaluation/table1.csv")
    # each step timed beside its floor, a bare pass of its own output layer, in the same rollout job
    assert (t1["floor_ms"] > 0).all() and (t1["step_over_floor"] > 0).all() and (t1["step_over_floor_max"] >= t1["step_over_floor"]).all()
    assert sorted(choice["latent_dim"]) == [2, 4] and choice["chosen"].sum() <= 1
    assert (choice["method"] == "self_supervised").all()  # the loss its points trained with (sweep.method)
    assert (choice["stress_conditions"] == 8).all()  # the rollout stage's conditions, at every point
    assert (choice["passes"] == choice["within_tolerance"] & (choice["stress_failed"] == 0)).all()
    assert (work / "results/sweep/tiny_cloth/sweep.png").stat().st_size > 1000
    sizes = pd.read_csv(work / "results/evaluation/sizes.csv").set_index("scene")
    assert sorted(sizes.index) == SCENES_TINY
    assert sizes.loc["tiny_cloth", "sweep_points"] == len(choice)
    tiny_ae = yaml.safe_load(TINY.read_text())["scenes"]["tiny_cloth"]["autoencoder"]
    assert sizes.loc["tiny_cloth", "latent_dim"] == tiny_ae["latent_dim"]
    assert "Model size per scene" in (work / "results/evaluation/summary.md").read_text()


def test_tiny_cloth_trains_one_integrator_over_its_box_and_a_reference_at_each_held_out_condition(tiny_run, tmp_path):
    import h5py
    import pandas as pd

    from latentsim.latent.serialization import load_extra, load_integrator

    work, _ = tiny_run
    c = yaml.safe_load(TINY.read_text())["scenes"]["tiny_cloth"]["conditioning"]
    d = work / "results/conditioned/tiny_cloth"
    # the four corners and the two held-out conditions, each at its own time step and modulus
    sims = {p.stem: p for p in (d / "sim").glob("*.h5")}
    assert sorted(sims) == ["15hz_3e04pa", "15hz_3e05pa", "30hz_1e05pa", "60hz_1e05pa", "60hz_3e04pa", "60hz_3e05pa"]
    with h5py.File(sims["60hz_1e05pa"]) as f, h5py.File(sims["30hz_1e05pa"]) as g:
        assert f.attrs["dt"] == pytest.approx(1 / 60) and f.attrs["youngs_modulus"] == 1e5
        assert f["sequences/line"].attrs["split"] == "test" and len(f["sequences/line/positions"]) == 2 * (len(g["sequences/line/positions"]) - 1) + 1
    conditioned = load_integrator(d / "seed0/conditioned/integrator.pt")
    assert conditioned.bc_dim == 8 and load_integrator(d / "seed0/30hz_1e05pa/integrator.pt").bc_dim == 6
    box = load_extra(d / "seed0/conditioned/integrator.pt")["conditioning"]
    assert box["time_step"] == c["time_step"] and box["youngs_modulus"] == c["youngs_modulus"]
    assert box["time_step_weight_power"] == 2.0  # the loss's weight (h / h_0)^p, the schema's p, recorded with the model
    m = pd.read_csv(d / "seed0/metrics.csv")
    assert sorted(zip(m["condition"], m["method"])) == sorted((n, k) for n in ("30hz_1e05pa", "60hz_1e05pa") for k in ("conditioned", "reference"))
    assert np.isfinite(m["mean_error"]).all() and (m["stress_total"] == 8).all()
    fr = pd.read_csv(d / "seed0/frame_rate.csv")
    assert fr[["coarse", "fine", "factor"]].values.tolist() == [["30hz_1e05pa", "60hz_1e05pa", 2]] and fr["shared_frames"].iloc[0] == 60
    summary = pd.read_csv(d / "summary.csv")
    finite = np.isfinite(summary[["conditioned_error", "reference_error"]]).all(axis=1)  # a diverged median has no ratio
    assert len(summary) == 2 and np.allclose(summary["ratio"][finite], (summary["conditioned_error"] / summary["reference_error"])[finite])
    assert summary["ratio"][~finite].isna().all()
    assert (d / "errors.png").stat().st_size > 1000 and (d / "summary.html").exists()
    assert "Frame-rate independence" in (d / "summary.md").read_text()
    # narrowing the box reruns the conditioned study (new corners: new training data), not the scene's own chain
    cfg = yaml.safe_load(TINY.read_text())
    cfg["scenes"]["tiny_cloth"]["conditioning"]["youngs_modulus"] = [4.0e4, 3.0e5]
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(cfg))
    jobs = planned_jobs(snakemake("-n", "all", "--configfile", str(edited), "--directory", str(work)).stdout)
    assert {r for r, _ in jobs} <= {"conditioned_simulate", "conditioned_autoencoder", "conditioned_integrator", "conditioned_evaluate",
                                    "conditioned_summary", "report_conditioned_page", "all"}, jobs  # fmt: skip
    assert ("conditioned_integrator", "tiny_cloth") in jobs
    # the loss's time-step weight retrains the conditioned integrator alone: a reference trains at one point
    cfg = yaml.safe_load(TINY.read_text())
    cfg["scenes"]["tiny_cloth"]["conditioning"]["time_step_weight_power"] = 0
    edited.write_text(yaml.safe_dump(cfg))
    jobs = planned_jobs(snakemake("-n", "all", "--configfile", str(edited), "--directory", str(work)).stdout)
    assert {r for r, _ in jobs} <= {"conditioned_integrator", "conditioned_evaluate", "conditioned_summary", "report_conditioned_page", "all"}, jobs
    assert [r for r, _ in jobs].count("conditioned_integrator") == 1, jobs  # one seed, the conditioned model


def test_tiny_contact_stays_out_of_its_ball_in_the_full_space_and_every_method_is_measured_for_penetration(tiny_run):
    import h5py
    import pandas as pd

    from latentsim.scene import contact_from_artefact

    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_contact/trajectories.h5") as f:
        barrier = contact_from_artefact(f)
        near = f["sequences/line/min_contact_distance"][()]
        positions = f["sequences/line/positions"][()]
    # it touches the ball (comes within the barrier's reach) and never enters it, by every point of its surface
    assert barrier is not None and len(barrier.colliders) == 1 and (near > 0).all() and near.min() < barrier.d_hat
    assert np.allclose(barrier.clearance(torch.as_tensor(positions)).numpy(), near)
    # where it touches, the ball is against the inside of an edge or a triangle: no vertex is within the reach
    touching = near < barrier.d_hat
    vertices = barrier.distances(torch.as_tensor(positions)).amin(-1).numpy()
    assert (vertices[touching] > 2 * barrier.d_hat).any()
    # and a second measure, points sampled on every triangle against the ball (grown by the half thickness), agrees
    ball = barrier.colliders[0]
    tris = np.asarray(barrier.primitives)
    i, j = np.meshgrid(np.arange(11), np.arange(11), indexing="ij")
    w = np.stack([i[i + j <= 10], j[i + j <= 10], 10 - i[i + j <= 10] - j[i + j <= 10]], -1) / 10
    sampled = np.linalg.norm(np.einsum("sk,ftkd->ftsd", w, positions[:, tris]) - np.asarray(ball.centre), axis=-1) - ball.radius
    assert (sampled.reshape(len(positions), -1).min(-1) > 0).all()
    m = pd.read_csv(work / "results/evaluation/tiny_contact/metrics.csv").set_index("method")
    assert {"max_penetration", "penetrating_frames"} <= set(m.columns)
    # one full-space Newton iteration a frame keeps the line search's guarantee: nothing enters
    assert m.loc["newton_1it", "max_penetration"] == 0 and m.loc["newton_1it", "penetrating_frames"] == 0
    assert np.isfinite(m.loc["self_supervised", "max_penetration"])
    # the integrator's frames near the ball are projected out of it (rollout.contact_projection), its own kept beside them
    with h5py.File(work / "results/rollout/tiny_contact/self_supervised/seed0/rollout.h5") as f:
        g = f["sequences/line"]
        own, shown, projected, attrs = g["unprojected_positions"][()], g["positions"][()], g["projected"][()], dict(g.attrs)
    assert projected.tolist() == (barrier.clearance(torch.as_tensor(own)).numpy() < barrier.d_hat).tolist() and projected.any()
    assert np.array_equal(shown[~projected], own[~projected]) and not np.array_equal(shown, own)
    assert (barrier.clearance(torch.as_tensor(shown)).numpy() >= 0).all() and m.loc["self_supervised", "max_penetration"] == 0
    assert attrs["projected_frames"] == projected.sum() and 0 < attrs["projection_ms"] <= attrs["step_ms"]
    assert m.loc["self_supervised", "latent_ms"] == pytest.approx(attrs["step_ms"], rel=1e-4)  # the table keeps 6 digits
    # the stress conditions' frames are projected too: the depth shown is the projected frames', the network's own beside it
    with h5py.File(work / "results/rollout/tiny_contact/self_supervised/seed0/rollout.h5") as f:
        groups = {c: dict(g.attrs) for c, g in f["stability"].items()}
    assert groups and all(a["max_penetration"] <= a["max_penetration_own"] and a["projected_frames"] >= 0 for a in groups.values())
    assert sum(a["projected_frames"] for a in groups.values()) > 0
    st = pd.read_csv(work / "results/evaluation/tiny_contact/stress.csv").set_index(["method", "condition"])
    for c, a in groups.items():
        assert st.loc[("self_supervised", c), "max_penetration_own"] == pytest.approx(a["max_penetration_own"], rel=1e-4, abs=1e-12)
    other = pd.read_csv(work / "results/evaluation/tiny_cloth/metrics.csv")
    assert "max_penetration" not in other.columns  # a scene without colliders has no such column
    # the glance table carries it for the contact scene alone, and the full space never enters
    glance = pd.read_csv(work / "results/evaluation/glance.csv").set_index(["scene", "method"])
    assert glance.loc[("tiny_contact", "full_space"), "max_penetration"] == 0
    assert glance.loc[("tiny_contact", "newton_1it"), "max_penetration"] == 0
    assert glance.loc["tiny_cloth", "max_penetration"].isna().all()
    # the autoencoder's reconstruction of the ground truth, measured the same way: its floor under every latent method
    from latentsim.latent.autoencoder import decode_latents, encode_positions
    from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder
    from latentsim.report.metrics import bbox_diagonal

    rec = pd.read_csv(work / "results/evaluation/tiny_contact/reconstruction.csv").set_index(["seed", "sequence"])
    ae_path = work / "results/autoencoder/tiny_contact/seed0/autoencoder.pt"
    with h5py.File(work / "results/sim/tiny_contact/trajectories.h5") as f:
        coords, xD = autoencoder_coordinates(f, ae_path), torch.as_tensor(f["sequences/line/dirichlet_positions"][()])
        diag = bbox_diagonal(f["rest_positions"][()])
    ae = load_autoencoder(ae_path)
    with torch.no_grad():
        xr = decode_latents(ae, coords, encode_positions(ae, coords, torch.as_tensor(positions), xD), xD).double()
    d = barrier.clearance(xr, xD).numpy()
    assert rec.loc[(0, "line"), "max_penetration"] == pytest.approx(max(-d.min(), 0.0) / diag, rel=1e-4, abs=1e-9)
    assert rec.loc[(0, "line"), "penetrating_frames"] == (d < 0).sum()
    assert "max_penetration" not in pd.read_csv(work / "results/evaluation/tiny_cloth/reconstruction.csv").columns


def test_tiny_contacts_rollout_with_its_projection_fed_back_starts_each_step_from_the_projected_state(tiny_run, tmp_path):
    """tiny_contact's rollout stage again with ``contact_projection.feedback``: up to the first frame the network
    brings within d_hat of the ball the rollout is the tiny run's; from there on its stored latents are
    the projected states (their decodes the frames written, all outside), so the motion differs from the run that
    projected the frames alone; each frame's prediction depth is kept, and the stress conditions' frames are out."""
    from latentsim.latent.autoencoder import decode_latents
    from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder
    from latentsim.scene import contact_from_artefact
    from latentsim.stages.rollout import rollout_scene

    work = tiny_run[0]
    cfg = validate_config(yaml.safe_load(TINY.read_text()))
    settings = copy.deepcopy(cfg["scenes"]["tiny_contact"]["rollout"])
    settings["contact_projection"]["feedback"] = True
    settings["full_frames_timed"] = 2
    traj = work / "results/sim/tiny_contact/trajectories.h5"
    ae_path = work / "results/autoencoder/tiny_contact/seed0/autoencoder.pt"
    out = tmp_path / "rollout.h5"
    rollout_scene(traj, ae_path, work / "results/integrator/tiny_contact/self_supervised/seed0/integrator.pt", settings, out, seed=0)
    with h5py.File(traj) as f:
        barrier, coords = contact_from_artefact(f), autoencoder_coordinates(f, ae_path)
    with h5py.File(out) as f, h5py.File(work / "results/rollout/tiny_contact/self_supervised/seed0/rollout.h5") as g:
        fed, plain = f["sequences/line"], g["sequences/line"]
        Z, X, xD, projected = fed["latents"][()], fed["positions"][()], fed["dirichlet_positions"][()], fed["projected"][()]
        depth, Z_plain = fed["predicted_depth"][()], plain["latents"][()]
        attrs, stress = dict(fed.attrs), {c: dict(h.attrs) for c, h in f["stability"].items()}
    assert attrs["projection_fed_back"] and attrs["projected_frames"] == projected.sum() > 0
    first = int(np.flatnonzero(projected)[0])
    # (to a tolerance: the job and this process may run on different numbers of threads)
    assert np.allclose(Z[:first], Z_plain[:first], rtol=1e-4, atol=1e-5) and not np.allclose(Z[first:], Z_plain[first:], rtol=1e-4, atol=1e-5)
    with torch.no_grad():
        decoded = decode_latents(load_autoencoder(ae_path), coords, torch.as_tensor(Z), torch.as_tensor(xD)).double().numpy()
    np.testing.assert_allclose(decoded, X, atol=1e-12)  # the frames written are the states the rollout went on from
    assert (barrier.clearance(torch.as_tensor(X)).numpy() >= 0).all()
    assert (depth >= 0).all() and (depth[~projected] == 0).all()
    assert stress and all(a["max_penetration"] == 0 and a["max_penetration_own"] >= 0 for a in stress.values())


def test_a_sweep_point_that_is_the_scenes_model_measures_it_instead_of_training_it_again(tiny_run):
    """tiny_cloth's latent-4 point has the scene's own settings: its job measures the pipeline's trained model
    (its training time is the two files' own), and training the point afresh, one thread as a job runs,
    gives that model to the bit, so nothing the sweep reports changes."""
    import pandas as pd

    from latentsim.config import sweep_point_settings
    from latentsim.latent.serialization import load_autoencoder, load_extra, load_integrator
    from latentsim.stages.sweep import train_point

    work = tiny_run[0]
    cfg = validate_config(yaml.safe_load(TINY.read_text()))
    ae_path = work / "results/autoencoder/tiny_cloth/seed0/autoencoder.pt"
    integ_path = work / "results/integrator/tiny_cloth/self_supervised/seed0/integrator.pt"
    reused = pd.read_csv(work / "results/sweep/tiny_cloth/r4_s0/seed0/metrics.csv")
    assert np.allclose(reused["train_seconds"], load_extra(ae_path)["train_seconds"] + load_extra(integ_path)["train_seconds"])
    trained = pd.read_csv(work / "results/sweep/tiny_cloth/r2_s0/seed0/metrics.csv")
    assert (trained["train_seconds"] > 0).all()
    point = sweep_point_settings(cfg, "tiny_cloth", 4, 0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fresh = train_point(work / "results/sim/tiny_cloth/trajectories.h5", point["autoencoder"], point["integrator"], seed=0)
    finally:
        torch.set_num_threads(threads)
    for model, stored in ((fresh["ae"], load_autoencoder(ae_path)), (fresh["integrator"], load_integrator(integ_path))):
        a, b = model.state_dict(), stored.state_dict()
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_sweep_trains_a_points_second_seed_only_where_its_first_leaves_it_a_chance(tiny_run, tmp_path):
    """tiny_cloth with seeds [0, 1], in a copy of the tiny run, the sweep alone: each point's seed 1 runs after
    its seed 0 and is pruned exactly where seed 0 failed (pass_fraction 1); the choice counts both seeds."""
    import shutil

    import pandas as pd

    from latentsim.stages.sweep import _normalised, _per_seed

    work = tmp_path / "latentsim"
    shutil.copytree(tiny_run[0], work, symlinks=True)
    shared = ROOT.parent / "shared"
    if shared.is_dir():
        (tmp_path / "shared").symlink_to(shared.resolve(), target_is_directory=True)
    cfg = yaml.safe_load(TINY.read_text())
    cfg["scenes"]["tiny_cloth"]["seeds"] = [0, 1]
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(cfg))
    snakemake("--cores", "2", "results/sweep/tiny_cloth/choice.csv", "--configfile", str(edited), "--directory", str(work), "--config", "progress=False")
    tolerance = cfg["scenes"]["tiny_cloth"]["sweep"]["tolerance"]
    choice = pd.read_csv(work / "results/sweep/tiny_cloth/choice.csv")
    assert (choice["seeds"] == 2).all()
    for point in ("r2_s0", "r4_s0"):
        first = pd.read_csv(work / f"results/sweep/tiny_cloth/{point}/seed0/metrics.csv")
        second = pd.read_csv(work / f"results/sweep/tiny_cloth/{point}/seed1/metrics.csv")
        passed = bool(_per_seed(_normalised(first), tolerance)["passes"].iloc[0])
        pruned = bool(second["pruned"].iloc[0]) if "pruned" in second else False
        assert pruned == (not passed), (point, passed, second)
        assert pruned or (second["seed"] == 1).all() and np.isfinite(second["mean_error"]).all()
    assert (choice["seeds_pruned"] == (~choice["seeds_passing"].astype(bool)).astype(int)).all()


def test_reduced_baselines_step_with_a_cubature(tiny_run):
    """tiny_cloth asks for a 1% cubature: the PCA, linear-modes and Fulton rollouts record one that
    fits and leaves out most elements, and still finish their test sequence."""
    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_cloth/trajectories.h5") as f:
        n_tri = len(f["triangles"])
    for method in ("pca_reduced", "modes_reduced", "fulton_reduced/seed0"):  # the decoder's baseline: once per seed
        with h5py.File(work / f"results/rollout/tiny_cloth/{method}/rollout.h5") as g:
            assert g.attrs["cubature_force_error"] <= 0.01
            k = int(g.attrs["cubature_elements"])
            assert 0 < k == len(g["cubature_index"]) < n_tri  # triangles + hinges together: far fewer
            assert (g["cubature_weights"][()] > 0).all()
            assert g["sequences/line"].attrs["diverged_frame"] == -1


def test_hard_mean_coordinates_hold_the_prescribed_vertices_in_every_learned_frame(tiny_run):
    """tiny_nm's autoencoder encodes its free vertices only (coordinates: hard_mean): the autoencoder
    records it, and every frame the integrator rolls out puts the held edges exactly on their targets."""
    work, _ = tiny_run
    extra = torch.load(work / "results/autoencoder/tiny_nm/seed0/autoencoder.pt", weights_only=True)["extra"]
    assert extra["coordinates"] == "hard_mean"
    with h5py.File(work / "results/sim/tiny_nm/trajectories.h5") as f:
        D = f["dirichlet"][()]
    with h5py.File(work / "results/rollout/tiny_nm/self_supervised/seed0/rollout.h5") as f:
        seq = f["sequences/bounce"]
        x, xD = seq["positions"][()], seq["dirichlet_positions"][()]
    ok = np.isfinite(x).all(axis=(1, 2))
    assert ok.sum() > 2 and np.array_equal(x[ok][:, D], xD[ok])


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
    """The XDMF time series holds every frame's displacement, equal to the stored positions; every series of
    the run is one block (the animation) for ParaView."""
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
    # ParaView reads each series as one block, the animation: no static copy of the mesh beside it
    import xml.etree.ElementTree as ET

    series = sorted((work / "results").rglob("*.xdmf"))
    assert {p.parts[len(work.parts) + 1] for p in series} == {"sim", "evaluation", "neural_modes", "conditioned"}
    for path in series:
        grids = ET.parse(path).getroot().find("Domain").findall("Grid")
        assert [g.get("CollectionType") for g in grids] == ["Temporal"], path


# Every table the tiny run writes (CSV), which the report must show as an HTML page: evaluation, sizing
# sweep, Neural Modes summary and studies.
REPORT_TABLES = (
    ["evaluation/" + t for t in ("glance.csv", "table1.csv", "table2.csv", "stability.csv", "sizes.csv", "summary.csv")]
    + ["sweep/tiny_cloth/choice.csv", "neural_modes/summary.csv", "mesh/quality.csv"]
    + ["neural_modes/tiny_nm/sheet/" + t for t in ("table2.csv", "table3.csv", "table4.csv", "tableA1.csv", "correlation.csv", "structure.csv")]
    + ["neural_modes/tiny_nm/" + t for t in ("energy/table5.csv", "dynamics/dynamics.csv", "aspect/aspect.csv")]
)


class _Tables(HTMLParser):
    """The tables of an HTML page: [(header cells, body rows of cells)]."""

    def __init__(self, text):
        super().__init__()
        self.tables, self._row, self._cell = [], [], None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append(([], []))
        elif tag == "tr" and self.tables:
            self._row = []
        elif tag in ("th", "td"):
            self._cell = []

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)

    def handle_endtag(self, tag):
        if tag in ("th", "td") and self._cell is not None:
            self._row.append(("".join(self._cell).strip(), tag))
            self._cell = None
        elif tag == "tr" and self.tables:
            head, body = self.tables[-1]
            if all(kind == "th" for _, kind in self._row):
                head.extend(text for text, _ in self._row)
            else:
                body.append([text for text, _ in self._row])


def _same_cell(value, text: str) -> bool:
    """A CSV value as a page shows it: numbers to 4 significant digits, NaN blank, the rest verbatim."""
    if isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
        return text == "" if np.isnan(value) else bool(text) and float(text) == pytest.approx(float(value), rel=1e-3, abs=1e-300)
    return text == str(value)


def test_report_shows_every_table_as_html_and_names_both_papers(tiny_run, tmp_path):
    """snakemake --report after the tiny run, as report.zip and report.html: every CSV table is an HTML page
    in it (every column, every row), the figures are in it, and the landing page names both papers and
    shows the glance grid."""
    import base64
    import zipfile

    import pandas as pd

    work, _ = tiny_run
    snakemake("--report", str(tmp_path / "report.zip"), "--configfile", str(TINY), "--directory", str(work))
    snakemake("--report", str(tmp_path / "report.html"), "--configfile", str(TINY), "--directory", str(work))
    with zipfile.ZipFile(tmp_path / "report.zip") as z:
        names = z.namelist()
        zip_pages = [(Path(n).name, _Tables(z.read(n).decode()).tables) for n in names if n.endswith(".html") and "/data/raw/" in n]
    for name in ("speed_accuracy.png", "errors.png", "learning_curves.png", "latent_walk.png", "correlation.png", "keyframes.png", "aspect_ratio.png",
                 "sweep.png", "stress_map.png", "tables.html"):  # fmt: skip
        assert any(n.endswith(name) for n in names), name
    text = (tmp_path / "report.html").read_text()
    embedded = re.findall(r"data:text/html;charset=utf8;filename=([^;]+);base64,([A-Za-z0-9+/=]+)", text)
    html_pages = [(name, _Tables(base64.b64decode(b).decode()).tables) for name, b in embedded]
    for pages, where in ((zip_pages, "report.zip"), (html_pages, "report.html")):
        for rel in REPORT_TABLES:
            df = pd.read_csv(work / "results" / rel)
            page = Path(rel).stem + ".html"  # its own page, beside it in results/ (several scenes' pages share a name)
            shown = [t for name, tables in pages if name == page for t in tables]
            match = [body for head, body in shown if head == list(df.columns) and len(body) == len(df)]
            assert match, f"{where}: no page {page} with a table of the columns and {len(df)} rows of {rel}"
            assert any(all(map(_same_cell, df.iloc[:, 0], [r[0] for r in body])) for body in match), f"{where}: {rel}: first column"
    desc = json.loads(re.search(r"var workflow_desc = (\".*?(?<!\\)\");", text, re.S).group(1))
    assert "Li et al. 2025" in desc and "Wang et al. 2024" in desc
    grid = _Tables(desc).tables
    assert grid and grid[0][0][0] == "scene" and sorted(r[0] for r in grid[0][1]) == SCENES_TINY  # the glance grid, one row per scene


def test_every_table_states_the_spread_over_the_seeds(tiny_run):
    """tiny_rods runs two seeds: each learned method trained and rolled out once per seed, and every table
    states them: the glance's medians with least and largest equal to the per-seed rows', divergence counts
    as k/n seeds, the claims generated from those tables, the stress map by seed."""
    import pandas as pd

    work, _ = tiny_run
    df = pd.read_csv(work / "results/evaluation/summary.csv")
    rods = df[df["scene"] == "tiny_rods"]
    assert sorted(rods.groupby("method")["seed"].apply(lambda s: sorted(set(s))).map(tuple).unique()) == [(0, 1)]
    own = rods[rods["method"] == "self_supervised"].groupby("seed")["mean_error"].mean()
    assert own[0] != own[1]  # two trainings, not one copied
    glance = pd.read_csv(work / "results/evaluation/glance.csv", keep_default_na=False).set_index(["scene", "method"])
    row = glance.loc[("tiny_rods", "self_supervised")]
    assert int(row["seeds"]) == 2 and row["seeds_stable"] == "2/2" and row["test_survived"] == "2/2"
    assert np.isclose(float(row["mean_error"]), own.median()) and np.isclose(float(row["mean_error_min"]), own.min())
    assert np.isclose(float(row["mean_error_max"]), own.max())
    assert int(glance.loc[("tiny_cloth", "self_supervised"), "seeds"]) == 1
    div = pd.read_csv(work / "results/evaluation/divergence.csv", keep_default_na=False).set_index(["scene", "method"])
    d = div.loc[("tiny_rods", "self_supervised")]
    assert d["test_diverged"] == "0/2" and d["frames_survived"] == "0:60 1:60"
    stress = pd.read_csv(work / "results/evaluation/stress.csv")
    failed = stress[(stress["scene"] == "tiny_rods") & (stress["method"] == "self_supervised")].groupby("seed")["diverged"].any()
    assert d["stress_failed"] == f"{int(failed.sum())}/2"
    claims = (work / "results/evaluation/claims.md").read_text()
    line = next(ln for ln in claims.splitlines() if ln.startswith("- tiny_rods, self_supervised:"))
    assert f"median of 2 seeds; {own.min():.3g} to {own.max():.3g}" in line and "every test sequence in 2 of 2 seeds" in line
    assert "tiny_cloth" not in claims  # one seed: no claim of a spread
    assert claims.strip() in (work / "results/evaluation/summary.md").read_text()


def test_artefacts_record_config_version_and_seed(tiny_run):
    work, _ = tiny_run
    with h5py.File(work / "results/sim/tiny_rods/trajectories.h5") as f:
        assert '"youngs_modulus"' in f.attrs["config"] and f.attrs["latentsim_version"]
        assert f["sequences/test_mid"].attrs["split"] == "test"
    for seed in (0, 1):
        with h5py.File(work / f"results/autoencoder/tiny_rods/seed{seed}/latents.h5") as f:
            assert f.attrs["seed"] == seed and '"latent_dim"' in f.attrs["config"]


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
    methods, seeds = ("self_supervised", "supervised", "small"), (0, 1)
    assert sorted(jobs, key=str) == sorted(
        [(stage, "tiny_rods") for stage in ("train_integrator", "rollout") for _ in methods for _ in seeds]
        + [("evaluate", "tiny_rods"), ("render", "tiny_rods"), ("summary", None), ("report_summary_pages", None), ("all", None)],
        key=str,
    )


def test_tiny_neural_modes_studies_write_tables_and_figures(tiny_run):
    """tiny_nm switches on every Neural Modes study: each writes its tables beside the paper's and its figures."""
    import meshio
    import pandas as pd

    from latentsim.neural_modes import load_neural_modes
    from latentsim.neural_modes.sheet import SHEET_METHODS
    from latentsim.utils import working_directory

    work, _ = tiny_run
    res = work / "results/neural_modes/tiny_nm"
    cfg = yaml.safe_load(TINY.read_text())["scenes"]["tiny_nm"]
    st = cfg["nm_study"]
    with h5py.File(res / "sheet/ground_truth.h5") as f:  # the configured set sizes, 2 modes
        sizes = {k: len(f[f"sets/{k}/z"]) for k in ("train_grid", "train_random", "val", "test")}
    assert sizes == {"train_grid": 3**2, "train_random": 9, "val": 2**2, "test": 3**2}
    with h5py.File(res / "energy/ground_truth.h5") as f:
        assert [len(f[f"sets/{k}/x"]) for k in ("train", "val", "test")] == [10, 4, 6]
    t2 = pd.read_csv(res / "sheet/table2.csv")
    assert t2["method"].tolist() == list(SHEET_METHODS.values())  # tiny_nm's built-in constraint adds the paper's map
    assert t2["test_dE_avg_paper"].tolist() == [386, 245, 245, 2074, 2259, 2649]
    assert np.isfinite(t2[["val_dE_avg", "test_dE_avg", "test_E_avg"]].to_numpy()).all()
    assert len(pd.read_csv(res / "sheet/table3.csv")) == 3
    structure = pd.read_csv(res / "sheet/structure.csv").set_index("method")
    assert structure.loc["Neural Modes (grid)", "origin |n(0) - X| / |X|"] < 1e-6  # the target
    assert np.isfinite(structure["symmetry error max"]).all()  # the clamped sheet has the half-turn symmetry
    for label in ("Neural Modes (stoch.)", "Neural Modes (grid)", "L2 Supervised"):  # built into their map
        assert structure.loc[label, "symmetry error max"] < 1e-10, label
    md = (res / "sheet/tables.md").read_text()
    assert all(f"## {h}" in md for h in ("Table 2", "Table 3", "Table 4", "Table A1", "Fig. 4", "Fig. 3"))
    for png in ("sheet/learning_curves.png", "sheet/latent_walk.png", "sheet/correlation.png", "keyframes/keyframes.png"):
        assert (res / png).stat().st_size > 1000, png
    t5 = pd.read_csv(res / "energy/table5.csv").set_index("method")
    assert t5.index.tolist() == ["Ground truth", "PCA+AE", "Neural Modes"] and t5.loc["Ground truth", "paper all (x1e4)"] == 11.3
    dyn = pd.read_csv(res / "dynamics/dynamics.csv").set_index("method")
    assert len(dyn) == 7 and dyn.loc["full space, Newton", "error max"] == 0
    assert (dyn["diverged frame"] == -1).all() and np.isfinite(dyn["error mean"]).all()
    with h5py.File(res / "dynamics/nm_newton.h5") as f:
        pos = f["sequences/bounce/positions"][()]
    with h5py.File(work / "results/sim/tiny_nm/trajectories.h5") as f:
        ref = f["sequences/bounce/positions"][()]
    with working_directory(res / "dynamics/paraview"), meshio.xdmf.TimeSeriesReader("nm_newton.xdmf") as r:
        points, _ = r.read_points_cells()
        assert r.num_steps == len(pos)
        _, data, _ = r.read_data(len(pos) - 1)
    assert np.allclose(points + data["displacement"], pos[-1]) and np.allclose(data["error"], np.linalg.norm(pos[-1] - ref[-1], axis=1))
    model = load_neural_modes(res / "neural_modes.pt")
    with h5py.File(res / "keyframes/keyframes.h5") as f:
        g = f["sequences/neural_modes"]
        keys, kx = g.attrs["keyframes"], g["positions"][()]
    with torch.no_grad():
        want = model(torch.as_tensor(np.asarray(st["keyframes"]["poses"], dtype=np.float64) * cfg["neural_modes"]["box"])).numpy()
    assert np.allclose(kx[keys], want, atol=1e-14)
    # the aspect-ratio example (Fig. A2): both ends train, the middle is held out; the files agree with the model
    from latentsim.neural_modes.aspect import load_family_model

    asp = pd.read_csv(res / "aspect/aspect.csv")
    assert asp["ratio"].tolist() == [1.0, 1.5, 2.0] and asp["split"].tolist() == ["train", "held out", "train"]
    assert (asp["max |cos(l, y)|"] < 1e-10).all()  # tiny_nm builds l^T y = 0 into the map
    assert np.isfinite(asp.drop(columns="split").to_numpy()).all() and (asp["E_avg ground truth"] > 0).all()
    family_model = load_family_model(res / "aspect/neural_modes.pt")
    with h5py.File(res / "aspect/family.h5") as f:
        decoded, X = f["evaluation/modes_plus"][()], f["X"][()]
    with torch.no_grad():
        amplitude = st["aspect"].get("figure_amplitude", 0.5)  # the schema's default
        want = family_model(torch.as_tensor(amplitude * cfg["neural_modes"]["box"] * np.eye(2)), 1).numpy()
    assert np.allclose(decoded[1], want, atol=1e-14)
    vtu = meshio.read(res / "aspect/paraview/ratio_1.500_mode_2.vtu")
    assert np.allclose(vtu.points, X[1]) and np.allclose(vtu.points + vtu.point_data["displacement"], decoded[1, 1])
    assert (res / "aspect/aspect_ratio.png").stat().st_size > 1000
    for stage in ("sheet_ground_truth", "sheet_study_seed0", "energy_table", "dynamics", "aspect_ratio"):
        assert (work / f"results/benchmarks/neural_modes/tiny_nm_{stage}.tsv").exists(), stage
        assert (work / f"logs/neural_modes/tiny_nm_{stage}.log").read_text(), stage


def test_editing_one_study_reruns_only_that_study(tiny_run, tmp_path):
    """Study settings rerun their own study; Neural Modes training settings rerun what uses the trained
    model, never the linear modes or the ground truth; the sample sets rerun their ground truth."""
    work, _ = tiny_run

    def jobs_after(edit):
        cfg = yaml.safe_load(TINY.read_text())
        edit(cfg["scenes"]["tiny_nm"])
        path = tmp_path / "edited.yaml"
        path.write_text(yaml.safe_dump(cfg))
        return sorted(planned_jobs(snakemake("-n", "all", "--configfile", str(path), "--directory", str(work)).stdout), key=str)

    def studies(sc):
        sc["nm_study"]["sheet"]["epochs"] += 1
        sc["nm_study"]["energy"]["ae_epochs"] += 1

    # and the report's pages of the tables they rewrite
    assert jobs_after(studies) == sorted([(r, "tiny_nm") for r in ("nm_sheet_study", "nm_sheet_tables", "nm_energy_table", "report_nm_sheet_pages", "report_nm_energy_page")]
                                         + [("all", None)], key=str)  # fmt: skip
    assert jobs_after(lambda sc: sc["nm_study"]["aspect"].update(epochs=4)) == sorted([("nm_aspect_ratio", "tiny_nm"), ("report_nm_aspect_page", "tiny_nm"), ("all", None)], key=str)
    # the model also serves tiny_nm's neural_modes_reduced baseline: that rollout and what reads it rerun too
    assert jobs_after(lambda sc: sc["neural_modes"].update(epochs=sc["neural_modes"]["epochs"] + 1)) == sorted(
        [(r, "tiny_nm") for r in ("nm_train", "nm_energy_table", "nm_dynamics", "nm_keyframes", "reduced_rollout", "evaluate", "render", "report_nm_energy_page",
                                   "report_nm_dynamics_page")]
        + [("nm_summary", None), ("summary", None), ("report_nm_summary_page", None), ("report_summary_pages", None), ("all", None)], key=str
    )  # fmt: skip
    assert jobs_after(lambda sc: sc["nm_study"]["sheet"].update(test_grid=4)) == sorted(
        [(r, "tiny_nm") for r in ("nm_ground_truth", "nm_sheet_study", "nm_sheet_tables", "report_nm_sheet_pages")] + [("all", None)], key=str
    )


def test_editing_a_variant_reruns_only_that_methods_jobs(tiny_run, tmp_path):
    work, _ = tiny_run
    cfg = yaml.safe_load(TINY.read_text())
    cfg["integrator_variants"]["supervised"]["epochs"] = 7
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(cfg))
    jobs = planned_jobs(snakemake("-n", "all", "--configfile", str(edited), "--directory", str(work)).stdout, methods=True)
    assert sorted(jobs, key=str) == sorted(
        2 * [("train_integrator", "tiny_rods", "supervised"), ("rollout", "tiny_rods", "supervised")]  # tiny_rods' two seeds
        + [("evaluate", "tiny_rods", None), ("render", "tiny_rods", None), ("summary", None, None), ("report_summary_pages", None, None),
           ("all", None, None)],
        key=str,
    )  # fmt: skip


def test_a_rollout_that_diverges_at_frame_0_is_scored_as_failed_and_the_scene_still_evaluated(tiny_run, tmp_path):
    """tiny_cloth's self-supervised rollout made one that diverged at frame 0 (non-finite from its first frame, every
    stress condition survived for 0 frames, checksummed as the stage writes it; a config can no longer ask for it:
    ``rollout.max_extent`` at or below 1 is refused), in a copy of the tiny run.  The scene's evaluation keeps its
    four baselines' metrics as they were; the diverged method's row says diverged at frame 0 with infinite errors,
    and it is off every front (glance, grid), named in Table 1."""
    import shutil

    import pandas as pd

    work = tmp_path / "latentsim"
    shutil.copytree(tiny_run[0], work, symlinks=True)
    shared = ROOT.parent / "shared"
    if shared.is_dir():  # the tiny config's meshes, relative to the copy, as in the tiny run
        (tmp_path / "shared").symlink_to(shared.resolve(), target_is_directory=True)
    from latentsim.checksum import KEY
    from latentsim.io import h5_checksum

    with h5py.File(work / "results/rollout/tiny_cloth/self_supervised/seed0/rollout.h5", "r+") as f:
        line = f["sequences/line"]
        line["positions"][...] = np.nan
        line.attrs["diverged_frame"] = 0
        for condition in f["stability"].values():
            condition.attrs["survived"] = 0
        f.attrs[KEY] = h5_checksum(f)
    snakemake("--cores", "2", "all", "--configfile", str(TINY), "--directory", str(work))
    before = pd.read_csv(tiny_run[0] / "results/evaluation/tiny_cloth/metrics.csv").set_index("method")
    after = pd.read_csv(work / "results/evaluation/tiny_cloth/metrics.csv").set_index("method")
    assert sorted(after.index) == sorted(before.index)
    scores = ["frames", "diverged_frame", "mean_error", "max_error", "dirichlet_error", "kinetic_ratio", "end_error", "end_motion",
              "end_motion_truth", "dof", "latent_dim"]  # fmt: skip
    baselines = [m for m in before.index if m != "self_supervised"]
    assert len(baselines) == 4 and after.loc[baselines, scores].equals(before.loc[baselines, scores])
    ss = after.loc["self_supervised"]
    assert ss["diverged_frame"] == 0 and (ss[["mean_error", "max_error", "dirichlet_error", "end_error"]] == np.inf).all()
    stress = pd.read_csv(work / "results/evaluation/tiny_cloth/stress.csv")
    assert len(stress) == 8 and (stress["frames_survived"] == 0).all() and stress["diverged"].all()
    glance = pd.read_csv(work / "results/evaluation/glance.csv", keep_default_na=False).set_index(["scene", "method"])
    row = glance.loc[("tiny_cloth", "self_supervised")]
    assert row["test_survived"] == "0/1" and row["stress_survived"] == "0/8" and row["on_front"] in (False, "False")
    assert float(row["mean_error"]) == np.inf
    summary = (work / "results/evaluation/summary.md").read_text()
    assert re.search(r"\| tiny_cloth \|.*\| diverged 0/1 \([0-9.e-]+\) \|", summary)
    t1 = pd.read_csv(work / "results/evaluation/table1.csv")
    assert "self_supervised (diverged on 1/1 test rollouts)" in set(t1.loc[t1["scene"] == "tiny_cloth", "method"])
    assert "self_supervised" in set(t1.loc[t1["scene"] == "tiny_rods", "method"])  # the other scenes as before


def test_a_variant_of_another_size_trains_and_decodes_with_its_own_autoencoder(tiny_run, tmp_path):
    """tiny_rods' ``small`` variant (latent 2, 16 wide) beside the scene's own model (latent 4, 32 wide)."""
    import pandas as pd

    work, _ = tiny_run
    for seed in (0, 1):  # tiny_rods runs two seeds
        own = torch.load(work / f"results/autoencoder/tiny_rods/seed{seed}/autoencoder.pt", weights_only=True)["hparams"]
        small = torch.load(work / f"results/autoencoder/tiny_rods/small/seed{seed}/autoencoder.pt", weights_only=True)["hparams"]
        assert (own["latent_dim"], small["latent_dim"]) == (4, 2)
        for method, r in (("self_supervised", 4), ("supervised", 4), ("small", 2)):
            with h5py.File(work / f"results/rollout/tiny_rods/{method}/seed{seed}/rollout.h5") as f:
                assert {g["latents"].shape[-1] for g in f["sequences"].values()} == {r}, method
                assert f.attrs["seed"] == seed
    t1 = pd.read_csv(work / "results/evaluation/table1.csv").set_index(["scene", "method"])
    assert t1.loc[("tiny_rods", "small"), "latent_dof"] == 2 and t1.loc[("tiny_rods", "self_supervised"), "latent_dof"] == 4
    assert ("tiny_rods", "supervised") not in t1.index  # variants of the scene's own size stay out of Table 1
    t2 = pd.read_csv(work / "results/evaluation/table2.csv").set_index(["scene", "method"])
    assert t2.loc[("tiny_rods", "small"), "decoder_layers"] == "16" and t2.loc[("tiny_rods", "small"), "integrator_layers"] == "16"
    sizes = pd.read_csv(work / "results/evaluation/sizes.csv").set_index("scene")
    assert sizes.loc["tiny_rods", "variant_models"] == "small: latent 2, 16 / 16"
    # its autoencoder is its own: editing it reruns the variant's jobs only, once per seed of the scene
    cfg = yaml.safe_load(TINY.read_text())
    cfg["integrator_variants"]["small"]["autoencoder"]["latent_dim"] = 3
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(cfg))
    jobs = planned_jobs(snakemake("-n", "all", "--configfile", str(edited), "--directory", str(work)).stdout, methods=True)
    assert sorted(jobs, key=str) == sorted(
        2 * [("train_variant_autoencoder", "tiny_rods", "small"), ("train_integrator", "tiny_rods", "small"), ("rollout", "tiny_rods", "small")]
        + [("evaluate", "tiny_rods", None), ("render", "tiny_rods", None), ("summary", None, None), ("report_summary_pages", None, None),
           ("all", None, None)],
        key=str,
    )  # fmt: skip


def _h5_contents(path):
    out = {}

    def visit(name, obj):
        for k, v in obj.attrs.items():
            if not is_timing(k, TIMING_ATTRS) and k != CHECKSUM:  # the checksum covers the wall times too
                out[f"{name}@{k}"] = v
        if isinstance(obj, h5py.Dataset) and not is_timing(name.split("/")[-1], TIMING_DATASETS):
            out[name] = obj[()]

    with h5py.File(path) as f:
        visit("/", f)
        f.visititems(visit)
    return out


# one job of each kind that trains or solves, with what it needs: autoencoders, a self-supervised, a supervised, a
# contact and a conditioned integrator, a rollout with its stress conditions and exported runtime, a reduced
# baseline, Neural Modes; the meshes and simulations under them
SAME_SEED_TARGETS = [
    "results/integrator/tiny_rods/supervised/seed1/integrator.pt",
    "results/rollout/tiny_rods/self_supervised/seed0/rollout.h5",
    "results/integrator/tiny_contact/self_supervised/seed0/integrator.pt",
    "results/conditioned/tiny_cloth/seed0/conditioned/integrator.pt",
    "results/rollout/tiny_cloth/pca_reduced/rollout.h5",
    "results/neural_modes/tiny_nm/neural_modes.pt",
]


def test_same_seed_gives_identical_artefacts(tiny_run, tmp_path):
    """The jobs of SAME_SEED_TARGETS run again from nothing in another folder: every array and weight they write
    equals the tiny run's to the bit (timings aside)."""
    work_a, _ = tiny_run
    work_b = tmp_path / "tiny_b"
    snakemake(*SAME_SEED_TARGETS, "--cores", "2", "--configfile", str(TINY), "--directory", str(work_b))
    files = sorted(p.relative_to(work_b) for p in (work_b / "results").rglob("*") if p.suffix in (".h5", ".pt", ".npz") and p.name != "runtime.pt")
    names = {p.name for p in files}
    assert len(files) >= 20 and {"mesh.h5", "trajectories.h5", "autoencoder.pt", "integrator.pt", "rollout.h5", "runtime.npz", "neural_modes.pt"} <= names
    assert all((work_b / t).is_file() for t in SAME_SEED_TARGETS)
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


# The tiny config's artefacts as the commit before the package was restructured by domain (6a0f0f0)
# wrote them: `python -m latentsim.fingerprint record RESULTS tests/workflow/data/tiny_reference.json`.
# Re-recorded when seeds became a pipeline dimension (the per-seed paths, tiny_rods' second seed, the
# tables' seed columns); every seed-0 file that is not a table was first checked equal to the old
# reference to the bit.  Re-recorded again when tiny_cloth's sweep moved to the scene's own widths (its points' rows
# and the sizes table changed; every other file not derived from linear modes was equal to the bit).  Re-recorded when
# tiny_cloth gained its conditioned study and the config tiny_contact (their files added; of the earlier files not
# derived from linear modes only evaluation/summary.csv changed, by its penetration columns).  The conditioned
# models' time_step_weight_power (2.0, the schema's) was added to the reference when the loss weight's power became a
# setting; nothing else changed.  tiny_contact's integrator rollout is left out of the bitwise comparison since its
# frames are projected out of the ball (downstream_of_contact_projection: the change was made on another processor than
# the reference's, which it cannot re-record; on this one every other file was equal to the bit before and after).
# Re-recorded when contact came to hold edges and triangles at the surface's thickness (c76c913, AMD EPYC): only
# tiny_contact's files and its rows of the tables changed.
# Re-record it (and say so in the commit) when a change is meant to change results.
REFERENCE = ROOT / "tests" / "workflow" / "data" / "tiny_reference.json"


def downstream_of_linear_modes(path: str, name: str = "") -> bool:
    """Artefacts computed from linear modes: the Neural Modes stages, the linear-modes and Neural Modes
    reduced baselines (files, and their rows in the tables).  Since the restructuring the stiffness
    matrix comes from the compiled kernels alone (the closed forms were deleted): omega^2 moves by
    ~4e-12, and tiny_nm's second mode, a half-turn-symmetric one whose sign rounding used to decide,
    comes out with the other sign; everything trained or solved from it then differs."""
    return path.startswith("neural_modes/") or "modes_reduced" in path or "modes_reduced" in name


def downstream_of_contact_projection(path: str, name: str = "") -> bool:
    """Artefacts of tiny_contact's integrator rollout, projected out of its ball since rollout.contact_projection was
    turned on for it (after the reference was recorded, on another processor than the change was made on): the rollout
    file, its ParaView file and its rows of the tables.  test_tiny_contact_stays_out_of_its_ball... checks them."""
    return path.startswith(("rollout/tiny_contact/self_supervised/", "evaluation/tiny_contact/paraview/self_supervised_")) or name.startswith(
        "row tiny_contact/self_supervised/")


def test_full_space_artefacts_match_the_reference_on_any_machine(tiny_run):
    """Meshes and simulations converge to the Newton tolerance whatever the processor: every array's
    sum and absolute sum agree with the reference to 1e-7 of their scale (two processors' rounding can
    end Newton an iteration apart, well inside the tolerance; a changed formula moves them by far more).
    The solver's own record of each frame (its final residual and iteration count) is left out: it is
    how Newton got there, which rounding changes (a residual 5e-7 apart, relative, on an Intel machine)."""
    from latentsim.fingerprint import compare, fingerprint_tree, is_physics, is_solver_record

    work, _ = tiny_run
    reference = json.loads(REFERENCE.read_text())["files"]
    assert sum(map(is_physics, reference)) >= 2 * len(SCENES_TINY)  # a mesh and a simulation per scene
    assert any(is_solver_record(p, n) for p in reference for n in reference[p])  # what is left out exists
    problems = compare(reference, fingerprint_tree(work / "results"), rtol=1e-7, only=is_physics, skip_name=is_solver_record)
    assert not problems, "\n".join(problems[:20])


def test_linear_modes_match_the_reference_up_to_sign(tiny_run):
    """omega^2 to 1e-10 and each mode's entries in magnitude (an eigenvector has no sign) to 1e-10."""
    from latentsim.fingerprint import compare, fingerprint_tree

    path = "neural_modes/tiny_nm/linear_modes.h5"
    reference = json.loads(REFERENCE.read_text())["files"][path]
    current = fingerprint_tree(tiny_run[0] / "results")[path]
    assert not compare({path: reference}, {path: current}, skip_name=lambda p, n: n in ("modes", "omega2"))  # the rest exact
    assert not compare({path: reference}, {path: current}, rtol=1e-10, skip_name=lambda p, n: n != "omega2")
    ref, cur = reference["modes"], current["modes"]
    assert ref["shape"] == cur["shape"] and abs(ref["abs"] - cur["abs"]) <= 1e-10 * ref["abs"]


def test_every_other_artefact_matches_the_reference_bitwise_on_its_processor(tiny_run):
    """On the processor that recorded the reference (training is sensitive to the last bit of rounding,
    which differs between processors), every artefact of the tiny run that does not derive from
    linear modes is the same to the bit as before the restructuring."""
    from latentsim.fingerprint import compare, fingerprint_tree, machine_signature

    recorded = json.loads(REFERENCE.read_text())
    if recorded["machine"] != machine_signature():
        pytest.skip(f"reference recorded on '{recorded['machine']}', this is '{machine_signature()}'")
    current = fingerprint_tree(tiny_run[0] / "results")
    # the scenes' full-space timing tables (added after the reference) hold wall times and Newton's iteration count alone
    timing_table = lambda p: p.endswith("/full_space_time.csv")  # noqa: E731
    left_out = lambda p, n="": downstream_of_linear_modes(p, n) or downstream_of_contact_projection(p, n) or timing_table(p)  # noqa: E731
    compared = [p for p in recorded["files"] if not left_out(p)]
    assert len(compared) > 40
    problems = compare(recorded["files"], current, only=lambda p: not left_out(p), skip_name=left_out)
    assert not problems, "\n".join(problems[:20])


def test_sigkill_mid_job_leaves_no_complete_looking_output(tmp_path):
    """Kill the whole Snakemake process group while the simulation runs."""
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "results/sim/tiny_rods/trajectories.h5",
           "--cores", "1", "--configfile", str(TINY), "--directory", str(tmp_path)]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=dict(os.environ, CI="1"))
    log = tmp_path / "logs/sim/tiny_rods.log"
    try:
        deadline = time.time() + 900  # the job starts within seconds on a quiet machine; this only bounds a hang
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


def test_neural_modes_baseline_steps_in_the_scenes_neural_modes(tiny_run):
    """tiny_nm lists neural_modes_reduced: its rollout lives in the trained Neural Modes' subspace
    (as many coordinates as modes), keeps the held edges on their prescribed path, and is evaluated
    beside the latent methods."""
    import pandas as pd

    work, _ = tiny_run
    modes = yaml.safe_load(TINY.read_text())["scenes"]["tiny_nm"]["neural_modes"]["modes"]
    with h5py.File(work / "results/rollout/tiny_nm/neural_modes_reduced/rollout.h5") as g:
        assert g.attrs["method"] == "neural_modes_reduced" and g.attrs["subspace_dim"] == modes
        seq = g["sequences/bounce"]
        assert seq["latents"].shape[-1] == modes
        D = g["dirichlet"][()]
        last = seq.attrs["diverged_frame"] if seq.attrs["diverged_frame"] >= 0 else len(seq["positions"])
        err = np.abs(seq["positions"][:last][:, D] - seq["dirichlet_positions"][:last]).max()
        assert err < 1e-9  # the Dirichlet set is the subspace's rigid frame: held exactly
        # every frame is the trained Neural Modes' map of its coordinates (not another subspace's)
        from latentsim.neural_modes import load_neural_modes
        from latentsim.neural_modes.dynamics import NeuralModesSubspace

        sub = NeuralModesSubspace(load_neural_modes(work / "results/neural_modes/tiny_nm/neural_modes.pt"), D)
        q, xD, x = seq["latents"][()], seq["dirichlet_positions"][()], seq["positions"][()]
        assert last > 2 and np.abs(q[2:last]).max() > 0
        for t in range(2, last):
            assert np.allclose(sub.map(q[t].astype(np.float64), xD[t]), x[t], atol=1e-5 * np.abs(x).max())
    table = pd.read_csv(work / "results/evaluation/tiny_nm/metrics.csv")
    assert "neural_modes_reduced" in set(table["method"])


@pytest.mark.parametrize("scene", ["tiny_cloth", "tiny_rods"])
def test_compiled_runtime_replays_the_rollout_and_is_timed(tiny_run, scene):
    """The rollout stage timed the compiled runtime beside the others; loaded from the exported runtime.npz
    alone, it replays the stored rollout (from its first two latents and the boundary conditions) to float32
    rounding; the floor benchmark runs on the scene's trajectories and times both runtimes."""
    from latentsim import runtime
    from latentsim.runtime import compiled as runtime_compiled

    work, _ = tiny_run
    out = work / f"results/rollout/{scene}/self_supervised/seed0"
    with h5py.File(out / "rollout.h5") as g:
        name, seq = next(iter(g["sequences"].items()))
        assert seq.attrs["runtime"] in ("numpy", "compiled", "torch_export", "eager")
        assert 0 < seq.attrs["compiled_step_ms"] < seq.attrs["eager_step_ms"]
        Z, bc, xD, X = (seq[k][()] for k in ("latents", "bc", "dirichlet_positions", "positions"))
    T = min(20, len(Z))
    stepper = runtime_compiled.load_runtime(out / "runtime.npz")
    res = runtime.rollout_runtime(stepper, Z[0], Z[1], bc[:T], np.ascontiguousarray(xD[:T]))
    scale = np.abs(X[:T]).max()
    assert np.abs(res["positions"] - X[:T]).max() < 1e-4 * scale
    assert np.abs(np.diff(X[:T], axis=0)).max() > 1e-3 * scale  # the frames move: a replay, not a constant
    bench = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks/bench_step_floor.py"), scene, "--results", str(work / "results"), "--config", str(TINY),
         "--rounds", "1", "--full-frames", "2", "--repeats", "5", "--export", str(work / "floors")],
        capture_output=True, text=True, timeout=HANG_SECONDS, env=dict(os.environ, PYTHONPATH=str(ROOT / "src")),
    )  # fmt: skip
    assert bench.returncode == 0, bench.stderr
    assert "compiled_floor_speedup" in bench.stdout and "bare_floor_speedup" in bench.stdout and scene in bench.stdout
    floor = runtime_compiled.load_runtime(work / "floors" / f"{scene}.npz")  # the floor network, as a runtime file
    assert floor.r == 2 and floor.n == X.shape[1]


@pytest.mark.parametrize("caption", sorted((ROOT / "workflow" / "report").glob("*.rst")), ids=lambda p: p.name)
def test_report_captions_are_valid_restructuredtext(caption):
    """snakemake --report renders every caption as reStructuredText: a bare |x| is a substitution
    reference that is never defined (an error in the report), so norms must be literals."""
    from docutils.core import publish_doctree
    from docutils.utils import Reporter
    from jinja2 import Environment

    from types import SimpleNamespace

    from latentsim.labels import energy_note

    # Snakemake renders a caption as a Jinja template first (the landing page includes the glance grid only
    # when the report holds the glance page: here it holds nothing); the Neural Modes captions insert the
    # rule's params.energy, whose norms hold bars
    material = {"model": "stvk_nm", "youngs_modulus": 4.0e8, "poisson_ratio": 0.2, "thickness": 0.005}
    smk = SimpleNamespace(params=SimpleNamespace(energy=energy_note("shell", material)))
    text = Environment(trim_blocks=True, lstrip_blocks=True).from_string(caption.read_text()).render(snakemake=smk, categories={}, files=[])
    doctree = publish_doctree(text, settings_overrides={"report_level": Reporter.SEVERE_LEVEL + 1, "halt_level": 5})
    found = [n for n in doctree.findall() if n.tagname == "system_message"] + list(doctree.transform_messages)
    messages = [m.astext() for m in found if int(m["level"]) >= Reporter.ERROR_LEVEL]
    assert not messages, messages


@pytest.mark.parametrize("scene", ["tiny_rods", "tiny_cloth"])
def test_the_example_encodes_and_steps_the_trained_model_as_the_rollout(tiny_run, scene):
    """examples/step_trained_model.py, run as a user runs it (from the workflow directory) on the rollout folder and
    the scene's trajectories: it imports latentsim.runtime (with the standalone checksum and provenance modules)
    and no training code; the latents it encodes frames 0
    and 1 to are latents.h5's, and the frames it steps are the rollout stage's, to float32 rounding."""
    import importlib.util

    work, _ = tiny_run
    example = ROOT / "examples" / "step_trained_model.py"
    args = [f"results/rollout/{scene}/self_supervised/seed0", "--trajectories", f"results/sim/{scene}/trajectories.h5"]
    check = ("import runpy, sys; sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__'); "
             "print('training modules:', sorted(m for m in sys.modules if m.startswith('latentsim.') and not m.startswith(('latentsim.runtime', 'latentsim.checksum', 'latentsim.provenance'))))")  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.run([sys.executable, "-c", check, str(example), *args], cwd=work, capture_output=True, text=True, timeout=HANG_SECONDS, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "ms per step" in proc.stdout and "torch.export program" in proc.stdout and "training modules: []" in proc.stdout, proc.stdout
    assert subprocess.run([sys.executable, str(example), "--help"], cwd=work, capture_output=True, env=env).returncode == 0
    spec = importlib.util.spec_from_file_location("step_trained_model", example)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = module.main([str(work / args[0]), "--trajectories", str(work / args[2])])
    with h5py.File(work / f"results/autoencoder/{scene}/seed0/latents.h5") as f:
        stored = f["sequences"][out["sequence"]]["latents"][:2]
    assert np.abs(out["latents"] - stored).max() < 1e-5 * np.abs(stored).max()
    with h5py.File(work / args[0] / "rollout.h5") as g:
        seq = g["sequences"][out["sequence"]]
        X, last = seq["positions"][()], int(seq.attrs["diverged_frame"])
    T = len(X) if last < 0 else last
    scale = np.abs(X[:T]).max()
    for key in ("positions", "torch_export_positions"):
        assert np.abs(out[key][2:T] - X[2:T]).max() < 1e-4 * scale, key
    assert np.abs(np.diff(X[:T], axis=0)).max() > 1e-3 * scale  # the frames move
