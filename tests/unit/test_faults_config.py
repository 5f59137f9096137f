"""Bad input named before it costs a run: non-finite config numbers, sequences that collide or are
missing, a latent dimension the training data (in the config and in the data) or the autoencoder's PCA layer
cannot fill, a divergence bound the rest shape breaks, a collider with a bad field, a barrier distance that is a
large part of the scene, a tet count beyond the maximum; and the frame check run on nothing."""

from __future__ import annotations

import copy
import runpy
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml

from latentsim.config import D_HAT_MAX_FRACTION, SCHEMA, ConfigError, load_config, validate_config, with_defaults
from latentsim.latent.autoencoder import LatentRankError, fit_autoencoder
from latentsim.mesh.build import build_mesh, generated_diagonal
from latentsim.stages.autoencoder import train_autoencoder

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def tiny():
    return yaml.safe_load((ROOT / "config" / "tiny.yaml").read_text())


def _numbers(value, path=()):
    """(path, number) of every int or float leaf (not bool) of a nested config."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, path + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _numbers(v, path + (i,))
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield path, value


def _set(cfg, path, value):
    for k in path[:-1]:
        cfg = cfg[k]
    cfg[path[-1]] = value


# --- non-finite numbers ----------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_a_non_finite_value_in_any_numeric_key_is_named(tiny, bad):
    """Every number of the tiny config with its defaults filled (the schema's bounds let NaN, and inf
    where only a lower bound is given, through)."""
    full = validate_config(copy.deepcopy(tiny))
    leaves = list(_numbers(full))
    assert len(leaves) > 300  # every scene's material, dt, gravity, solver, training, study settings
    for path, _ in leaves:
        cfg = copy.deepcopy(full)
        _set(cfg, path, bad)
        key = ".".join(map(str, path))
        with pytest.raises(ConfigError, match=rf"^config key '{key}': {bad!r} is not a finite number$"):
            validate_config(cfg)


def test_yaml_nan_and_inf_are_named_with_the_file(tiny, tmp_path):
    text = (ROOT / "config" / "tiny.yaml").read_text()
    for yaml_value, shown in ((".nan", "nan"), (".inf", "inf"), ("-.inf", "-inf")):
        path = tmp_path / "bad.yaml"
        path.write_text(text.replace("youngs_modulus: 1.0e+7", f"youngs_modulus: {yaml_value}", 1))
        with pytest.raises(ConfigError, match=rf"bad\.yaml: config key 'scenes\.tiny_rods\.material\.youngs_modulus': {shown} is not a finite number"):
            load_config(path)
    # YAML's bare nan is a string: the schema's type check names it
    path.write_text(text.replace("youngs_modulus: 1.0e+7", "youngs_modulus: nan", 1))
    with pytest.raises(ConfigError, match=r"'scenes\.tiny_rods\.material\.youngs_modulus': 'nan' is a str, expected number"):
        load_config(path)


# --- sequences --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: c["scenes"]["tiny_rods"]["sequences"][1].update(name="train_slow"),
         r"'scenes\.tiny_rods\.sequences\.1\.name': scene tiny_rods stores sequence 1 'train_slow' as 'train_slow', as it does sequence 0 'train_slow'"),
        # a sequence with train_frames is also stored as <name>_train
        (lambda c: c["scenes"]["tiny_cloth"]["sequences"].append({"name": "line_train", "split": "train", "frames": 10}),
         r"'scenes\.tiny_cloth\.sequences\.1\.name': scene tiny_cloth stores sequence 1 'line_train' as 'line_train', as it does sequence 0 'line' \(its first train_frames frames\)"),
        (lambda c: c["scenes"]["tiny_rods"]["sequences"].pop(),
         r"'scenes\.tiny_rods\.sequences': scene tiny_rods has no sequence of split test .*\[\('train_slow', 'train'\), \('train_fast', 'train'\)\]"),
        (lambda c: c["scenes"]["tiny_rods"]["sequences"].__delitem__(slice(0, 2)),
         r"'scenes\.tiny_rods\.sequences': scene tiny_rods has no sequence of split train .*\[\('test_mid', 'test'\)\]"),
        (lambda c: c["scenes"]["tiny_cloth"]["sequences"][0].pop("train_frames"),
         r"'scenes\.tiny_cloth\.sequences': scene tiny_cloth has no sequence of split train"),
        # the schema's default sequences are one training sequence: a scene must list its own
        (lambda c: c["scenes"]["tiny_cloth"].pop("sequences"),
         r"'scenes\.tiny_cloth\.sequences': scene tiny_cloth has no sequence of split test .*\[\('rest', 'train'\)\]"),
        (lambda c: c["scenes"]["tiny_cloth"]["sequences"][0].update(train_frames=61),
         r"'scenes\.tiny_cloth\.sequences\.0\.train_frames': 61 is more than the sequence's 60 frames"),
    ],
)
def test_sequences_that_collide_or_are_missing_are_named(tiny, edit, message):
    edit(tiny)
    with pytest.raises(ConfigError, match=message):
        validate_config(tiny)


# --- latent dimension above the rank of the training data -----------------------------------------


@pytest.mark.parametrize(
    "edit, message",
    [
        # tiny_nm trains on bounce_train alone: 16 frames from the rest state, 15 directions at most
        (lambda c: c["scenes"]["tiny_nm"]["autoencoder"].update(latent_dim=16),
         r"'scenes\.tiny_nm\.autoencoder\.latent_dim': latent_dim 16 of scene tiny_nm is above the rank of its training data: "
         r"16 training frames in 1 sequence\(s\) of \[16\] frames.* at most 15 independent directions; use latent_dim <= 15"),
        # tiny_rods: 2 x 40 frames, each from the rest state: 78
        (lambda c: c["integrator_variants"]["small"]["autoencoder"].update(latent_dim=79),
         r"'integrator_variants\.small\.autoencoder\.latent_dim': latent_dim 79 of scene tiny_rods .*80 training frames in 2 sequence\(s\) of \[40, 40\].*at most 78"),
        (lambda c: c["scenes"]["tiny_cloth"]["sweep"].update(latent_dims=[2, 40]),
         r"'scenes\.tiny_cloth\.sweep\.latent_dims': latent_dim 40 of scene tiny_cloth .*at most 39"),
        (lambda c: c["scenes"]["tiny_cloth"]["autoencoder"].update(pca_samples=4),
         r"'scenes\.tiny_cloth\.autoencoder\.latent_dim': latent_dim 4 .*the PCA sees pca_samples = 4, give at most 3"),
    ],
)
def test_a_latent_dim_above_the_training_frames_is_named(tiny, edit, message):
    edit(tiny)
    with pytest.raises(ConfigError, match=message):
        validate_config(tiny)


def test_a_latent_dim_the_training_frames_can_fill_passes(tiny):
    tiny["scenes"]["tiny_nm"]["autoencoder"]["latent_dim"] = 15
    tiny["scenes"]["tiny_cloth"]["autoencoder"]["pca_samples"] = 5
    validate_config(tiny)


@pytest.mark.parametrize(
    "edit, message",
    [
        # the case: it stopped inside the autoencoder job with "pca_dim ... 32 < latent_dim 60"
        (lambda c: c["scenes"]["tiny_rods"]["autoencoder"].update(latent_dim=60),
         r"'scenes\.tiny_rods\.autoencoder': latent_dim 60 of scene tiny_rods is above the width of the autoencoder's PCA layer, 32 "
         r"\(pca_dim 0: the first decoder width of widths \[32, 32\]\).*use latent_dim <= 32, or a first width \(or pca_dim\) of at least 60"),
        (lambda c: c["scenes"]["tiny_rods"]["autoencoder"].update(pca_dim=3), r"'scenes\.tiny_rods\.autoencoder': latent_dim 4 .*PCA layer, 3 \(pca_dim 3\)"),
        (lambda c: c["integrator_variants"]["small"]["autoencoder"].update(widths=[1]), r"'integrator_variants\.small\.autoencoder': latent_dim 2 of scene tiny_rods .*PCA layer, 1"),
        (lambda c: c["scenes"]["tiny_cloth"]["sweep"].update(sizes=[{"autoencoder": [3], "integrator": [8]}]),
         r"'scenes\.tiny_cloth\.sweep\.sizes\.0\.autoencoder': latent_dim 4 of scene tiny_cloth .*PCA layer, 3 .*widths \[3\]"),
        (lambda c: c["scenes"]["tiny_cloth"]["conditioning"].update(autoencoder={"widths": [2]}), r"'scenes\.tiny_cloth\.conditioning\.autoencoder': latent_dim 4 .*PCA layer, 2"),
    ],
)  # fmt: skip
def test_a_latent_dim_above_the_pca_layer_is_named_on_load(tiny, edit, message):
    edit(tiny)
    with pytest.raises(ConfigError, match=message):
        validate_config(tiny)


def test_a_latent_dim_the_pca_layer_holds_passes(tiny):
    tiny["scenes"]["tiny_rods"]["autoencoder"].update(latent_dim=32)  # as wide as the first width
    tiny["scenes"]["tiny_nm"]["autoencoder"].update(widths=[])  # a linear autoencoder: the PCA layer is the latent's width
    tiny["scenes"]["tiny_cloth"]["autoencoder"].update(widths=[2], pca_dim=8)  # pca_dim in place of the first width
    validate_config(tiny)


def _low_rank(n_frames, dim, rank, seed=0):
    """(n_frames, dim) float32 rows in a rank-``rank`` affine subspace (spread 1 to 0.1)."""
    g = torch.Generator().manual_seed(seed)
    basis = torch.linalg.qr(torch.randn(dim, rank, generator=g, dtype=torch.float64))[0].T
    coeff = torch.randn(n_frames, rank, generator=g, dtype=torch.float64) * torch.logspace(0, -1, rank, dtype=torch.float64)
    return (coeff @ basis + torch.randn(dim, generator=g, dtype=torch.float64)).float()


@pytest.mark.parametrize("n_frames, dim, rank", [(6, 30, 5), (50, 12, 3)])  # fewer frames than dims, and more
def test_fit_autoencoder_stops_at_a_latent_dim_above_the_data_rank(n_frames, dim, rank):
    U = _low_rank(n_frames, dim, rank)
    cfg = {"latent_dim": rank + 1, "widths": [8], "epochs": 1, "batch_size": 8}
    with pytest.raises(LatentRankError, match=rf"latent_dim {rank + 1} is above the rank of the training data: its {n_frames} training frames "
                                              rf"have {rank} independent directions .*use latent_dim <= {rank}"):
        fit_autoencoder(U, cfg)
    fit_autoencoder(U, {**cfg, "latent_dim": rank})  # as many as there are: trains


def test_the_rank_is_that_of_the_frames_the_pca_sees():
    U = _low_rank(40, 30, 20)
    with pytest.raises(LatentRankError, match=r"its 6 training frames \(a random 6 of 40, pca_samples\) have 5 independent directions"):
        fit_autoencoder(U, {"latent_dim": 6, "widths": [8], "epochs": 1, "batch_size": 8, "pca_samples": 6})


def _trajectories(path, frames=8):
    """A scene's trajectories.h5 as far as the autoencoder stage reads it: 5 vertices, one prescribed."""
    g = np.random.default_rng(0)
    rest = g.normal(size=(5, 3))
    with h5py.File(path, "w") as f:
        f.attrs["model"], f.attrs["scene"] = "shell", "little"
        f["rest_positions"], f["dirichlet"] = rest, np.array([0])
        for name, split in (("walk", "train"), ("run", "test")):
            s = f.create_group(f"sequences/{name}")
            s.attrs["split"] = split
            x = rest + 0.01 * g.normal(size=(frames, 5, 3))
            x[0] = rest
            s["positions"], s["dirichlet_positions"], s["bc"] = x, x[:, :1], np.zeros((frames, 6))
    return path


def test_the_autoencoder_stage_names_scene_file_and_rank_and_writes_nothing(tmp_path):
    traj = _trajectories(tmp_path / "trajectories.h5")
    model, latents = tmp_path / "autoencoder.pt", tmp_path / "latents.h5"
    settings = {"latent_dim": 8, "widths": [16], "epochs": 1, "batch_size": 4}
    with pytest.raises(LatentRankError, match=rf"scene little \({traj}, training sequences \['walk'\]\): latent_dim 8 is above the rank "
                                              r"of the training data: its 8 training frames have 7 independent directions"):
        train_autoencoder(traj, settings, 0, "cpu", model, latents)
    assert not model.exists() and not latents.exists()
    train_autoencoder(traj, {**settings, "latent_dim": 7}, 0, "cpu", model, latents)
    assert model.exists() and latents.exists()


# --- the independent frame check finds nothing to check -------------------------------------------


def test_the_frame_check_of_nothing_fails_naming_the_folder(tmp_path, capsys):
    """benchmarks/check_frames.py on a mistyped folder, or one without trajectories, exits 1 naming it (it printed
    an empty table and exited 0); --help is its usage, not a check of a folder named --help."""
    main = runpy.run_path(str(ROOT / "benchmarks" / "check_frames.py"))["main"]
    for root, found in ((tmp_path / "reslts" / "sim", "no such folder"), (tmp_path, "no <scene>/trajectories.h5 in it")):
        with pytest.raises(SystemExit) as stop:
            main([str(root)])
        out = capsys.readouterr()
        assert stop.value.code == 1 and f"{root}: {found}; nothing to check" in out.err and "| scene |" not in out.out
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0 and capsys.readouterr().out.startswith("usage: ")


# --- a divergence bound the rest shape already breaks ---------------------------------------------


@pytest.mark.parametrize("bound", [0.5, 1.0])
def test_a_divergence_bound_at_or_below_the_rest_shape_is_named_on_load(tiny, bound):
    """rollout.max_extent is a multiple of the rest bounding-box diagonal: at or below 1 the rest shape itself is
    beyond it, and every learned method 'diverged at frame 0' (it was accepted)."""
    tiny["scenes"]["tiny_rods"]["rollout"] = {"max_extent": bound}
    with pytest.raises(ConfigError, match=rf"'scenes\.tiny_rods\.rollout\.max_extent': {bound} is out of range; allowed: "
                                          r"\{'exclusiveMinimum': 1\.0\} \(.*rest shape's own extent is 1 times its diagonal.*frame 0"):  # fmt: skip
        validate_config(tiny)
    tiny["scenes"]["tiny_rods"]["rollout"] = {"max_extent": 1.5}
    validate_config(tiny)


# --- a collider with a bad field ------------------------------------------------------------------

KINDS = (r"'type' one of \['half_space', 'sphere', 'capsule', 'mesh'\] and its fields: half_space \(point, normal; optional: attached\); sphere "
         r"\(centre, radius; optional: attached\); capsule \(a, b, radius; optional: attached\); mesh \(file; optional: sha256, scale, rotate_axis, "
         r"rotate_degrees, translate\)")


@pytest.mark.parametrize(
    "collider, message",
    [
        ({"type": "sphere", "center": [0, 0, 0], "radius": 0.1},
         r"'scenes\.tiny_contact\.contact\.colliders\.0': unknown key\(s\) \['center'\]; allowed: \['attached', 'centre', 'radius', 'type'\]; "
         r"'centre' is a required property \(type sphere takes: centre, radius; optional: attached\)"),
        ({"type": "sphere", "centre": [0, 0, 0], "radius": -1.0}, r"'scenes\.tiny_contact\.contact\.colliders\.0\.radius': -1\.0 is out of range.*\(type sphere takes"),
        ({"type": "capsule", "a": [0, 0], "b": [1, 0, 0], "radius": 0.1}, r"'scenes\.tiny_contact\.contact\.colliders\.0\.a': \[0, 0\] is too short \(type capsule takes: a, b, radius"),
        ({"type": "ball", "centre": [0, 0, 0], "radius": 0.1}, rf"'scenes\.tiny_contact\.contact\.colliders\.0': type 'ball' is not allowed; give a mapping with {KINDS}"),
        ({"centre": [0, 0, 0], "radius": 0.1}, rf"colliders\.0': no 'type' given; give a mapping with {KINDS}"),
        ("sphere", rf"colliders\.0': 'sphere' is not a mapping; give a mapping with {KINDS}"),
    ],
)  # fmt: skip
def test_a_collider_with_a_bad_field_names_the_field_and_the_kinds(tiny, collider, message):
    """It said only "is not valid under any of the given schemas"."""
    tiny["scenes"]["tiny_contact"]["contact"]["colliders"] = [collider]
    with pytest.raises(ConfigError, match=message):
        validate_config(tiny)


def test_a_value_none_of_the_alternatives_take_says_what_each_wanted(tiny):
    tiny["scenes"]["tiny_contact"]["contact"]["d_hat"] = -1.0
    with pytest.raises(ConfigError, match=r"'scenes\.tiny_contact\.contact\.d_hat': -1\.0 fits none of the alternatives \(-1\.0 is less than or equal "
                                          r"to the minimum of 0; or -1\.0 is not of type 'null'\) \(Activation distance of the barrier"):  # fmt: skip
        validate_config(tiny)


# --- a barrier distance a large part of the scene -------------------------------------------------


def test_a_d_hat_large_for_a_generated_mesh_is_named_on_load(tiny):
    """tiny_contact's cloth is 0.2 x 0.2 m (diagonal 0.283 m): 1.0 m threw it 1.75 diagonals in frame 1 and the run
    completed.  The bound is on the placed mesh: scaled ten times, 0.1 m is within it."""
    schema = yaml.safe_load(SCHEMA.read_text())
    assert f"most {D_HAT_MAX_FRACTION:g} of that diagonal" in " ".join(schema["$defs"]["contact"]["properties"]["d_hat"]["description"].split())
    contact = tiny["scenes"]["tiny_contact"]["contact"]
    for d_hat, shown in ((1.0, r"1\.0 m is 3\.54 times"), (0.1, r"0\.1 m is 0\.354 times")):
        contact["d_hat"] = d_hat
        with pytest.raises(ConfigError, match=rf"'scenes\.tiny_contact\.contact\.d_hat': {shown} the rest bounding-box diagonal \(0\.283 m\).*"
                                              r"at most 0\.05 of the diagonal \(0\.0141 m\), or null"):  # fmt: skip
            validate_config(copy.deepcopy(tiny))
    tiny["scenes"]["tiny_contact"]["mesh"]["scale"] = 10.0
    validate_config(copy.deepcopy(tiny))
    contact["d_hat"] = 0.01  # 0.035 of the diagonal at scale 1
    tiny["scenes"]["tiny_contact"]["mesh"]["scale"] = 1.0
    validate_config(tiny)


@pytest.mark.parametrize(
    "model, mesh",
    [
        ("rods", {"generator": "rod_bundle", "n_rods": 7, "vertices_per_rod": 9, "length": 0.3, "spacing": 0.02, "direction": [1.0, -1.0, 0.0]}),
        ("rods", {"generator": "rod_bundle", "n_rods": 5, "rotate_axis": [1.0, 1.0, 0.0], "rotate_degrees": 30.0, "ring_radius": 0.08}),
        ("shell", {"generator": "cloth_grid", "nx": 7, "ny": 3, "width": 0.4, "height": 0.1, "plane": "xz", "scale": 2.0, "rotate_degrees": 17.0}),
        ("tets", {"generator": "beam_tets", "nx": 6, "ny": 2, "nz": 3, "length": 0.5, "width": 0.1, "height": 0.05, "rotate_axis": [0.0, 1.0, 1.0],
                  "rotate_degrees": 40.0, "translate": [1.0, 2.0, 3.0]}),
    ],
)  # fmt: skip
def test_a_generated_meshs_diagonal_from_its_config_is_the_built_meshs(model, mesh):
    mesh = {**with_defaults("mesh", {k: v for k, v in mesh.items() if k != "ring_radius"}, "test"), **mesh}  # ring_radius: no default
    V = build_mesh(model, mesh, {})["rest_positions"]
    assert generated_diagonal(model, mesh) == pytest.approx(float(np.linalg.norm(V.max(0) - V.min(0))), rel=1e-12)
    assert generated_diagonal(model, {**mesh, "generator": "file"}) is None  # known once the file is read


# --- a tet count that takes the mesh stage minutes, or all the memory -----------------------------


@pytest.mark.parametrize("target", [200_000, 1_000_000_000])
def test_a_target_vertex_count_beyond_the_maximum_is_named_on_load(tiny, target):
    """2e5 ran 14.5 minutes without a word, 1e9 until TetGen ran out of memory."""
    tiny["scenes"]["tiny_rods"]["mesh"]["target_vertices"] = target
    with pytest.raises(ConfigError, match=rf"'scenes\.tiny_rods\.mesh\.target_vertices': {target} is out of range; allowed: \{{'minimum': 0, "
                                          r"'maximum': 50000\} \(.*2e5 took 14\.5 minutes"):  # fmt: skip
        validate_config(tiny)


def test_a_large_target_vertex_count_is_warned_of_in_the_mesh_stages_log(monkeypatch, caplog):
    """Above LARGE_TARGET_VERTICES the warning comes before the meshing (stopped here before it starts)."""
    import latentsim.mesh.build as build

    def stop(*args):
        raise RuntimeError("meshing starts")

    monkeypatch.setattr(build, "build_mesh", stop)
    for target, warned in ((build.LARGE_TARGET_VERTICES, False), (build.LARGE_TARGET_VERTICES + 1, True)):
        caplog.clear()
        with caplog.at_level("WARNING", logger=build.logger.name), pytest.raises(RuntimeError, match="meshing starts"):
            build.scene_mesh("bunny", "tets", {"generator": "file", "file": "bunny.obj", "target_vertices": target}, {"type": "free"}, {})
        assert (f"scene bunny: mesh.target_vertices {target} is above 10000: remeshing and TetGen may take many minutes" in caplog.text) == warned
