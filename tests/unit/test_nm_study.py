"""The Neural Modes evaluation studies (Wang et al. 2024, Sec. 4): learning curves and early stopping,
the latent structure (origin, half-turn symmetry), Table 5's intervals, subspace dynamics, keyframing.

Each case is tiny (a 4x4-cell sheet, a 6x2x2 beam, a handful of samples and epochs) and checks what
the tables and figures rest on: the early-stopped rows are the curves' minima, the PCA+AE checkpoints
are one run seen along its training, the intervals partition the test set, the full-space row of the
dynamics has zero error, keyframes are hit exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from latentsim import neural_modes as nm
from latentsim.neural_modes import dynamics as nm_dynamics
from latentsim.neural_modes import energy_study as nm_energy
from latentsim.neural_modes import baselines as nm_baselines
from latentsim.neural_modes import metrics as nm_metrics
from latentsim.neural_modes import sheet as nm_sheet
from latentsim.neural_modes import sheet_tables as nm_tables
from latentsim.neural_modes import symmetry as nm_symmetry
from latentsim.latent import fit_autoencoder
from latentsim.mesh import beam_tets, cloth_grid
from latentsim.labels import DYNAMICS_METHODS
from latentsim.latent.timing import time_full_space
from latentsim.scene import build_elastic

ONE_THREAD = True  # tiny networks (conftest)


def sheet(cells=4, dirichlet=()):
    V, F = cloth_grid(cells, cells, 0.2, 0.2, plane="xz")
    arrays = {"rest_positions": V, "triangles": F, "dirichlet": np.asarray(dirichlet, dtype=np.int64)}
    mat = {"youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 1000.0, "thickness": 0.003}
    return build_elastic("shell", arrays, mat), V, F


# --- learning curves and early stopping ------------------------------------------------------------
def test_checkpoints_are_log_spaced_and_end_at_the_last_epoch():
    assert nm_metrics.checkpoints(100, 5).tolist() == [0, 1, 3, 10, 32, 100]
    assert nm_metrics.checkpoints(3, 10).tolist() == [0, 1, 2, 3]  # repeats dropped
    with pytest.raises(ValueError, match="at least 1"):
        nm_metrics.checkpoints(0, 5)


def test_stopping_index_is_the_least_validation_criterion_after_training_starts():
    epochs = np.array([0, 1, 3, 10, 30])
    assert nm_metrics.stopping_index(epochs, [0.1, 5.0, 2.0, 2.0, 3.0]) == 2  # epoch 0 excluded; first of a tie
    assert nm_metrics.stopping_index(epochs, [9.0, 5.0, np.nan, 4.0, 4.5]) == 3  # NaN never chosen


def test_autoencoder_checkpoints_are_what_a_run_stopped_there_returns():
    """The model after epoch k of one run (fit_autoencoder's snapshots) is the model a run of k epochs
    returns, the PCA start included (epoch 0, and any epoch that ended above its error)."""
    gen = torch.Generator().manual_seed(0)
    U = torch.randn(40, 30, generator=gen, dtype=torch.float64) @ torch.randn(30, 30, generator=gen, dtype=torch.float64) * 0.01
    cfg = {"latent_dim": 2, "widths": [8], "lr": 1e-3, "batch_size": 16}
    got = list(nm_baselines.autoencoder_along_training(U, cfg, [0, 3, 7], seed=0))
    assert [k for k, _, _ in got] == [0, 3, 7]
    assert got[0][2] <= got[1][2] <= got[2][2]  # training time so far
    for k, model, _ in got:
        alone, hist = fit_autoencoder(U, {**cfg, "epochs": k}, seed=0)
        sd, sk = alone.double().state_dict(), model.state_dict()
        assert all(torch.equal(sd[name], sk[name]) for name in sd), k
    with pytest.raises(ValueError, match="outside"):
        fit_autoencoder(U, {**cfg, "epochs": 3}, seed=0, snapshots=[4])


@pytest.fixture(scope="module")
def sheet_study():
    """The whole sheet study on a free 4x4-cell sheet with 2 modes (seconds)."""
    torch.set_num_threads(1)
    pot, V, F = sheet()
    lm = nm.linear_modes(pot, 2, V, boundary="free", normalization="euclidean")
    R = nm.rigid_modes(V, pot.masses.numpy())
    basis = {"X": V, "modes": lm.modes, "fixed_dofs": np.zeros(0, dtype=np.int64), "rigid": R}
    gt = nm_sheet.solve_sets(pot, V, lm.modes, nm_sheet.sample_sets(2, 0.3, 4, 3, 5, 16, seed=0), rigid=R, max_iter=30)
    cfg = {"epochs": 6, "batch_size": 16, "train_grid": 4, "l2_epochs": 6, "ae_epochs": 30, "ae_lr": 1e-3, "ae_batch_size": 8,
           "curve_points": 4, "sharp_epochs": 3, "sharp_batch_size": 16, "sharp_w_iso": 1.0, "walk_steps": 5}  # fmt: skip
    study = nm_sheet.run_sheet_study(pot, basis, gt, {"widths": [16, 16], "box": 0.3, "lam": 1e6, "eta": 1e6}, cfg, F, seed=0)
    return study, gt, V


def test_sheet_tables_report_the_early_stopped_checkpoints(sheet_study):
    study, _, _ = sheet_study
    tabs = nm_tables.tables(study)
    col = {k: nm_metrics.METRICS.index(k) for k in ("l2", "E_avg", "dE_avg")}
    for slug, r in study["methods"].items():
        epochs, val, test = r["epochs"], r["val"], r["test"]
        assert epochs[0] == 0 and epochs[-1] == {"l2_supervised": 6, "pca_ae": 30, "pca_ae_grid": 30}.get(slug, 6)
        trained = epochs >= 1
        k = r["stop_val_l2"]
        assert val[k, col["l2"]] == val[trained, col["l2"]].min()
        assert r["stop_val_energy"] == np.flatnonzero(trained)[np.argmin(val[trained, col["E_avg"]])]
        row = tabs["table2"].set_index("method").loc[r["label"]]
        want = k if slug in nm_sheet.SUPERVISED else len(epochs) - 1  # Neural Modes: the last epoch, no validation data
        assert row["epoch"] == epochs[want]
        assert row["test_dE_avg"] == test[want, col["dE_avg"]] and row["val_E_avg"] == val[want, col["E_avg"]]
    t3 = tabs["table3"].set_index("method")
    assert sorted(t3.index) == sorted(nm_sheet.SHEET_METHODS[s] for s in nm_sheet.SUPERVISED)
    for slug in nm_sheet.SUPERVISED:
        r = study["methods"][slug]
        assert t3.loc[r["label"], "val_E_avg_val_energy"] == r["val"][r["stop_val_energy"], col["E_avg"]]
        assert t3.loc[r["label"], "val_E_avg_val_energy"] <= t3.loc[r["label"], "val_E_avg_val_l2"]
        assert t3.loc[r["label"], "test_E_avg_val_l2_paper"] == nm_tables.PAPER_TABLE3[r["label"]][2]


def test_neural_modes_keep_the_origin_and_the_half_turn(sheet_study):
    """Fig. 3's numbers: n(0) = X to round-off; the free sheet's two lowest modes are even under the
    half turn, and a correction that starts at zero stays in the even subspace (its gradient does; on
    this small sheet round-off does not grow in six epochs, on the paper's sheet it does, see
    workflow/report/nm_structure.rst)."""
    study, gt, V = sheet_study
    for slug in ("nm_stochastic", "nm_grid"):
        r = study["methods"][slug]
        assert r["origin_relative_error"] < 1e-12
        assert r["symmetry_max"] < 1e-8
    assert study["methods"]["pca_ae_grid"]["origin_relative_error"] > 1e-6  # dec(0) is not X
    walk = study["walk"]["nm_grid"]
    assert walk["positions"].shape == (2, 5, len(V), 3)
    assert np.allclose(walk["positions"][:, 2], V, atol=1e-15)  # the middle of the walk is z = 0
    eig = {c["label"]: c["eigenvalues"] for c in study["correlation"].values()}
    assert all(0.5 < w < 2 for w in eig["Neural Modes (grid)"])


def test_half_turn_symmetry_is_found_and_measured():
    pot, V, F = sheet()
    lm = nm.linear_modes(pot, 2, V, boundary="free", normalization="euclidean")
    sym = nm_symmetry.half_turn(V, F, lm.modes)
    assert sym is not None
    perm, R, parity = sym
    u = np.random.default_rng(0).normal(size=(3, len(V), 3))
    assert np.allclose(nm_symmetry.turn(nm_symmetry.turn(u, perm, R), perm, R), u)  # a half turn twice is the identity
    z = np.array([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.2], [0.0, -0.2]])
    x = V + np.einsum("km,nm->kn", z, lm.modes).reshape(len(z), -1, 3)  # linear modes: symmetric by construction
    # eigenvectors from Lanczos are exact to ~1e-12 of their scale, not to the bit
    assert nm_symmetry.symmetry_error(x, z, V, sym)[1] < 1e-10
    x[0, 3, 1] += 1e-3  # one vertex pushed: no longer symmetric
    assert nm_symmetry.symmetry_error(x, z, V, sym)[1] > 1e-3
    # a sheet held at one corner only has no half-turn symmetry
    pot1, V1, F1 = sheet(dirichlet=[0])
    lm1 = nm.linear_modes(pot1, 2, V1, boundary="dirichlet", normalization="euclidean")
    assert nm_symmetry.half_turn(V1, F1, lm1.modes, fixed_dofs=[0, 1, 2]) is None
    assert np.isnan(nm_symmetry.symmetry_error(x, z, V, None)[0])


# --- Table 5 --------------------------------------------------------------------------------------
def test_intervals_partition_the_test_set():
    for count, k in ((300, 5), (7, 5), (5, 5), (11, 1)):
        parts = nm_energy.interval_slices(count, k)
        idx = np.concatenate([np.arange(count)[p] for p in parts])
        assert idx.tolist() == list(range(count))  # every sample once, in order
        sizes = [p.stop - p.start for p in parts]
        assert len(sizes) == k and max(sizes) - min(sizes) <= 1
    e = np.random.default_rng(1).random(7)
    parts = nm_energy.interval_slices(7, 5)
    assert sum(e[p].mean() * (p.stop - p.start) for p in parts) / 7 == pytest.approx(e.mean(), rel=1e-14)
    with pytest.raises(ValueError, match="cannot split 3 samples into 5"):
        nm_energy.interval_slices(3, 5)


def test_energy_sets_split_uniform_samples_in_order():
    a = nm_energy.energy_sets(3, 2.0, 20, 12, 3, seed=4)
    b = nm_energy.energy_sets(3, 2.0, 20, 12, 3, seed=4)
    assert [len(a[s]) for s in ("train", "val", "test")] == [12, 3, 5]
    assert all(np.array_equal(a[s], b[s]) for s in a)
    z = np.concatenate([a["train"], a["val"], a["test"]])
    assert np.abs(z).max() <= 2.0 and len(np.unique(z, axis=0)) == 20
    with pytest.raises(ValueError, match="cannot be split"):
        nm_energy.energy_sets(3, 2.0, 10, 8, 2)


def beam(n=(6, 2, 2)):
    V, T = beam_tets(n[0], n[1], n[2], 0.3, 0.05, 0.05, tets_per_cell=5)
    D = np.flatnonzero(V[:, 0] < 1e-12)
    arrays = {"rest_positions": V, "tets": T, "dirichlet": D}
    mat = {"youngs_modulus": 2e6, "poisson_ratio": 0.3, "density": 1000.0}
    return arrays, mat


def test_energy_table_rows_are_the_energies_of_each_method():
    arrays, mat = beam()
    pot = build_elastic("tets", arrays, mat)
    V, D = arrays["rest_positions"], arrays["dirichlet"]
    lm = nm.linear_modes(pot, 2, V, boundary="dirichlet", normalization="euclidean")
    gt = nm_sheet.solve_sets(pot, V, lm.modes, nm_energy.energy_sets(2, 0.05, 16, 8, 3, seed=0), free_dofs=lm.free_dofs, max_iter=20)
    torch.manual_seed(0)
    model = nm.NeuralModes(V, lm.modes, [8], fixed_dofs=(3 * D[:, None] + np.arange(3)).reshape(-1))  # untrained: the linear modes
    settings = {"widths": [8], "ae_epochs": 6, "ae_lr": 1e-3, "ae_batch_size": 4, "curve_points": 3, "intervals": 5}
    table, hist = nm_energy.energy_table(pot, V, gt, model, settings, seed=0)
    t = table.set_index("method")
    assert np.isclose(t.loc["Ground truth", "all"], gt["test"]["energy"].mean(), rtol=1e-10)
    with torch.no_grad():
        e_lin = pot.elastic((model.X + model.linear(torch.as_tensor(gt["test"]["z"]))).reshape(5, -1, 3)).numpy()
    assert np.isclose(t.loc["Neural Modes", "all"], e_lin.mean(), rtol=1e-10)
    assert t.loc["Neural Modes", "all"] >= t.loc["Ground truth", "all"]  # Eq. 9 is the constrained minimum
    assert list(t.columns[:5]) == ["0-20%", "20-40%", "40-60%", "60-80%", "80-100%"]
    assert t.loc["Ground truth", "0-20%"] == pytest.approx(gt["test"]["energy"][0], rel=1e-10)  # 5 samples: one each
    assert hist["stop"] == nm_metrics.stopping_index(hist["epochs"], hist["val_l2"])
    assert t.loc["PCA+AE", "epoch"] == hist["epochs"][hist["stop"]]


# --- subspace dynamics and keyframing -------------------------------------------------------------
def test_keyframe_interpolation_hits_the_keyframes():
    poses = np.array([[0.0, 0.0], [0.3, -0.1], [0.1, 0.7], [0.0, 0.0]])
    z, keys = nm_dynamics.keyframe_coordinates(poses, 3)
    assert keys.tolist() == [0, 3, 6, 9] and len(z) == 10
    assert np.array_equal(z[keys], poses)  # exactly, not to round-off
    assert np.allclose(z[4], poses[1] + (poses[2] - poses[1]) / 3)
    assert np.allclose(np.diff(z[3:7], 2, axis=0), 0)  # linear within a segment
    with pytest.raises(ValueError, match="two keyframes"):
        nm_dynamics.keyframe_coordinates(poses[:1], 3)


@pytest.fixture(scope="module")
def beam_trajectories(tmp_path_factory):
    """A short simulation of a clamped tet beam whose root moves sideways (the scene's trajectories.h5)."""
    from latentsim.stages.simulate import simulate_scene

    arrays, mat = beam()
    path = tmp_path_factory.mktemp("beam")
    mesh = path / "mesh.h5"
    import h5py

    with h5py.File(mesh, "w") as f:
        for k, v in arrays.items():
            f[k] = v
        f.attrs["model"] = "tets"
    cfg = {"model": "tets", "material": mat, "dt": 1 / 30, "gravity": [0.0, -9.81, 0.0], "newton": {},
           "sequences": [{"name": "sway", "split": "test", "frames": 8, "segments": [{"velocity": [0.0, 0.0, 0.2]}]}]}  # fmt: skip
    simulate_scene("beam", mesh, cfg, path / "trajectories.h5")
    return path / "trajectories.h5", arrays


def test_the_scenes_full_space_time_is_one_row_of_the_first_test_sequence(beam_trajectories, tmp_path):
    from latentsim.stages.evaluate import read_full_space_time, write_full_space_time

    table = write_full_space_time(beam_trajectories[0], tmp_path / "full_space_time.csv", frames=3)
    assert len(table) == 1 and table["sequence"].iloc[0] == "sway" and table["full_frames_timed"].iloc[0] == 3
    assert table["full_iterations"].iloc[0] >= 1 and read_full_space_time(tmp_path / "full_space_time.csv") > 0


def test_dynamics_rows_against_the_full_simulation(beam_trajectories):
    import h5py

    traj, arrays = beam_trajectories
    pot = build_elastic("tets", arrays, beam()[1])
    D = arrays["dirichlet"]
    lm = nm.linear_modes(pot, 2, arrays["rest_positions"], boundary="dirichlet", normalization="euclidean")
    torch.manual_seed(0)
    model = nm.NeuralModes(arrays["rest_positions"], lm.modes, [8], fixed_dofs=(3 * D[:, None] + np.arange(3)).reshape(-1))
    settings = {"frames": 0, "max_iterations": 50, "cubature_tolerance": 0.05, "cubature_samples": 12, "cubature_max_elements": 50}
    with h5py.File(traj) as f:
        full = time_full_space(f, nm_dynamics.first_test_sequence(f), 2)
        res = nm_dynamics.subspace_dynamics(f, model, 0.05, settings, full)
        ref = f["sequences/sway/positions"][()]
    rows = res["rows"].set_index("method")
    assert res["sequence"] == "sway" and len(rows) == 1 + len(DYNAMICS_METHODS)
    assert rows.loc["full space, Newton", "error mean"] == 0 and rows.loc["full space, Newton", "error max"] == 0
    diag = np.linalg.norm(np.ptp(arrays["rest_positions"], axis=0))
    for slug, (label, _, _, cubature) in DYNAMICS_METHODS.items():
        run = res["runs"][slug]
        assert run["positions"].shape == ref.shape and run["diverged_frame"] == -1
        err = np.sqrt(((run["positions"] - ref) ** 2).sum(-1).mean(-1)) / diag
        assert np.allclose(run["error"], err) and rows.loc[label, "error mean"] == pytest.approx(err.mean())
        assert np.allclose(run["positions"][:, D], f_xD(traj), atol=1e-12)  # the subspace carries the prescribed set exactly
        assert 0 < err.max() < 0.2  # a reduced motion, not the full one, nor far from it
        if cubature:
            assert rows.loc[label, "elements"] < rows.loc["full space, Newton", "elements"]
    # an untrained network has no correction: its subspace is the linear modes' and so is its motion
    assert np.allclose(res["runs"]["nm_newton"]["positions"], res["runs"]["linear_newton"]["positions"], atol=1e-10)


def f_xD(traj):
    import h5py

    with h5py.File(traj) as f:
        return f["sequences/sway/dirichlet_positions"][()]
