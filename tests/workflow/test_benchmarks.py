"""The benchmark scripts' own bookkeeping (their figures come from runs, not tests)."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_stage_times_put_every_benchmark_file_under_its_stage_and_scene(tmp_path):
    """The Li rules write <stage>/<scene>[/<method>].tsv, the Neural Modes rules neural_modes/<scene>[_<job>].tsv
    (scene names hold underscores): each lands in its own stage and scene, wall and CPU seconds summed."""
    files = {
        "integrator/hair_rotation/self_supervised.tsv": (100.0, 90.0),
        "integrator/hair_rotation/no_noise.tsv": (50.0, 40.0),
        "sim/bunny_ears.tsv": (30.0, 29.0),
        "neural_modes/nm_armadillo.tsv": (600.0, 590.0),
        "neural_modes/nm_armadillo_energy_ground_truth.tsv": (2000.0, 1990.0),
        "neural_modes/nm_armadillo_energy_table.tsv": (500.0, 495.0),
        "neural_modes/nm_armadillo_dynamics.tsv": (120.0, 118.0),
        "neural_modes/nm_sheet_sheet_ground_truth.tsv": (300.0, 299.0),
        "neural_modes/nm_sheet_sheet_study_seed0.tsv": (400.0, 398.0),
        "neural_modes/nm_sheet_sheet_study_seed1.tsv": (410.0, 400.0),
        "neural_modes/nm_sheet_aspect_ratio.tsv": (450.0, 449.0),
        "summary/summary.tsv": (6.0, 5.0),
    }
    for rel, (wall, cpu) in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"s\th:m:s\tcpu_time\n{wall}\t0:00:00\t{cpu}\n")
    df = load("stage_times").stage_times(tmp_path).set_index(["stage", "scene"])
    assert sorted(df.index) == sorted([
        ("integrator", "hair_rotation"), ("sim", "bunny_ears"), ("nm_train", "nm_armadillo"),
        ("nm_ground_truth", "nm_armadillo"), ("nm_energy_table", "nm_armadillo"), ("nm_dynamics", "nm_armadillo"),
        ("nm_ground_truth", "nm_sheet"), ("nm_sheet_study", "nm_sheet"), ("nm_aspect_ratio", "nm_sheet"),
        ("summary", "across scenes"),
    ])  # fmt: skip
    assert df.loc[("integrator", "hair_rotation")].tolist() == [2, 150.0, 130.0]
    assert df.loc[("nm_ground_truth", "nm_armadillo"), "wall_s"] == 2000.0
    assert df.loc[("nm_sheet_study", "nm_sheet")].tolist() == [2, 810.0, 798.0]  # one job per seed


def test_stage_times_compare_two_runs_stage_by_stage(tmp_path, capsys):
    """--before: both runs' jobs, wall and CPU minutes per stage, the CPU ratio (none for a stage the earlier
    run lacks), and the totals."""
    st = load("stage_times")
    runs = {"before": {"sweep/cloth/r2_s0/seed0.tsv": (120.0, 60.0), "sweep/cloth/r2_s0/seed1.tsv": (120.0, 60.0)},
            "now": {"sweep/cloth/r2_s0/seed0.tsv": (60.0, 30.0), "sweep/cloth/r2_s0/seed1.tsv": (6.0, 3.0), "sim/cloth.tsv": (30.0, 30.0)}}  # fmt: skip
    for run, files in runs.items():
        for rel, (wall, cpu) in files.items():
            path = tmp_path / run / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(f"s\th:m:s\tcpu_time\n{wall}\t0:00:00\t{cpu}\n")
    t = st.compare(st.stage_times(tmp_path / "now"), st.stage_times(tmp_path / "before")).set_index("stage")
    assert t.loc["sweep", ["jobs_before", "jobs_now"]].tolist() == [2, 2]
    assert t.loc["sweep", "cpu_min_before"] == 2.0 and t.loc["sweep", "cpu_min_now"] == 33.0 / 60 and t.loc["sweep", "cpu_ratio"] == 33.0 / 120
    assert t.loc["sim", "jobs_before"] == 0 and t.loc["sim", "cpu_ratio"] != t.loc["sim", "cpu_ratio"]  # NaN: nothing before
    assert t.loc["all stages", "cpu_min_now"] == 63.0 / 60 and t.loc["all stages", "wall_min_now"] == 96.0 / 60
    st.main([str(tmp_path / "now"), "--before", str(tmp_path / "before")])
    assert "| sweep | 2 | 2 | 4.0 | 1.1 | 2.0 | 0.6 | 0.28 |" in capsys.readouterr().out


def test_runtime_ab_times_a_revisions_runtime_beside_the_working_trees(tmp_path):
    """bench_runtime_ab loads runtime.py from git (HEAD here) as its own module and steps the same
    runtime file with both; the decoded frames agree to float32 rounding."""
    import numpy as np
    import torch

    from latentsim import runtime
    from latentsim.latent import Autoencoder, LatentIntegrator, RelativeCoordinates

    ab = load("bench_runtime_ab")
    old = ab.load_revision("HEAD")
    assert old is not runtime and old.__name__ == "latentsim._runtime_rev" and hasattr(old, "NumpyStepper")
    torch.manual_seed(0)
    coords = RelativeCoordinates(30, [0, 1], "mean")
    ae = Autoencoder(coords.dim, 3, [8, 8], pca_dim=6).eval()
    integ = LatentIntegrator(3, 6, [8]).eval()
    runtime.export_runtime(ae, integ, coords, tmp_path / "runtime.npz")
    row = ab.compare(tmp_path / "runtime.npz", old, rounds=2, repeats=5)
    assert row["mode"] == "mean" and np.isfinite(row["speedup"]) and row["old_us"] > 0 and row["new_us"] > 0
    assert row["max_dx"] < 1e-5
    # --runtime compiled: runtime_compiled.py from git beside the working tree's, on a file named with --npz
    from latentsim.runtime import compiled as runtime_compiled

    if runtime_compiled.available():
        old_c = ab.load_revision("HEAD", kind="compiled")
        assert old_c is not runtime_compiled and hasattr(old_c, "CompiledStepper")
        row = ab.compare(tmp_path / "runtime.npz", old_c, ab.current_module("compiled"), rounds=2, repeats=5)
        assert row["old_us"] > 0 and row["new_us"] > 0 and row["max_dx"] < 1e-5
        df = ab.main(["--against", "HEAD", "--runtime", "compiled", "--npz", str(tmp_path / "runtime.npz"), "--rounds", "1", "--repeats", "3"])
        assert df["scene"].tolist() == ["runtime"] and df.loc[0, "max_dx"] < 1e-5
    # a model encoded in a rigid frame steps inside each revision's RigidFrameStepper, as a loaded model does
    rest = torch.randn(30, 3, dtype=torch.float64)
    framed = RelativeCoordinates(30, [0, 1, 2], "mean", rigid_rest=rest[[0, 1, 2]])
    ae_f = Autoencoder(framed.dim, 3, [8, 8], pca_dim=6).eval()
    runtime.export_runtime(ae_f, LatentIntegrator(3, 6 + 9, [8]).eval(), framed, tmp_path / "framed.npz")
    for kind in ["numpy"] + (["compiled"] if runtime_compiled.available() else []):
        row = ab.compare(tmp_path / "framed.npz", ab.load_revision("HEAD", kind=kind), ab.current_module(kind), rounds=1, repeats=3)
        assert row["mode"] == "mean (rigid frame)" and row["old_us"] > 0 and row["max_dx"] < 1e-5, kind


def test_nearest_neighbour_order_visits_every_sample_once_along_a_chain_of_neighbours():
    import numpy as np

    nearest_neighbour_order = load("nm_ground_truth_order").nearest_neighbour_order
    z = np.array([[3.0], [-1.0], [0.5], [2.0], [-2.5]])[:, [0, 0]]
    order = nearest_neighbour_order(z)
    assert sorted(order) == list(range(len(z)))
    assert list(order) == [2, 1, 4, 3, 0]  # 0.5 nearest the origin, then -1, -2.5, then back up to 2 and 3
    assert len(nearest_neighbour_order(np.zeros((0, 3)))) == 0


def test_before_after_sets_learned_methods_side_by_side_and_flags_a_median_outside_the_old_range(tmp_path, capsys):
    import pandas as pd

    from latentsim.io import write_csv

    mod = load("before_after")
    cols = ["scene", "method", "seeds", "mean_error", "mean_error_min", "mean_error_max", "seeds_stable", "test_survived", "stress_survived"]

    def run(name, cloth_error, cloth_stable, rods_error):
        folder = tmp_path / name
        folder.mkdir()
        glance = pd.DataFrame([
            ["cloth", "supervised_5x256", 5, cloth_error, 0.004, 0.010, f"{cloth_stable}/5", f"{cloth_stable}/5", "30/40"],
            ["cloth", "full_space", 1, 0.0, 0.0, 0.0, "1/1", "1/1", None],
            ["cloth", "pca_reduced", 1, 0.02, 0.02, 0.02, "1/1", "1/1", None],
            ["rods", "self_supervised", 3, rods_error, 0.001, 0.003, "3/3", "3/3", None],
        ], columns=cols)  # fmt: skip
        write_csv(glance, folder / "glance.csv")
        write_csv(pd.DataFrame({"scene": ["cloth", "rods"], "method": ["supervised_5x256", "self_supervised"],
                                "test_diverged": [f"{5 - cloth_stable}/5", "0/3"]}), folder / "divergence.csv")  # fmt: skip
        return folder

    before = run("before", 0.007, 4, 0.002)
    same = run("same", 0.009, 4, 0.0015)
    table = mod.before_after(before, same)
    assert list(table["method"]) == ["supervised_5x256", "self_supervised"]  # the seedless baselines left out
    assert list(table["inside"]) == ["yes", "yes"]
    row = table.iloc[0]
    assert row["mean error before"] == "0.007 (0.004 to 0.01)" and row["diverged"] == "1/5 / 1/5" and row["stress survived"] == "30/40 / 30/40"
    assert table.iloc[1]["stress survived"] == "- / -"
    worse = run("worse", 0.012, 2, 0.002)
    assert mod.main([str(before), str(worse)]) == 1
    out = capsys.readouterr().out
    assert "| no " in out and "1 of 2 rows with the new median outside the old range" in out
    assert mod.main([str(before), str(same), "--scenes", "rods"]) == 0


def test_plateau_rule_finds_where_the_rule_ends_each_supervised_history(tmp_path, capsys):
    import h5py

    mod = load("plateau_rule")
    flat_from_40 = [1.0 / (1 + e) for e in range(40)] + [0.0251] * 60  # falls for 40 epochs, then flat
    falling = [1.0 / (1 + e) for e in range(100)]  # falls by more than 7% a window to the end
    for method, seed, losses in (("supervised_5x256", 0, flat_from_40), ("supervised_5x256", 1, falling), ("self_supervised", 0, flat_from_40)):
        path = tmp_path / "integrator" / "cloth" / method / f"seed{seed}" / "history.h5"
        path.parent.mkdir(parents=True)
        with h5py.File(path, "w") as f:
            f["loss"] = losses
    table = mod.plateau_table(tmp_path, window=10, tolerance=0.07)
    assert list(table["seed"]) == [0, 1] and set(table["method"]) == {"supervised_5x256"}  # the energy loss left out
    # flat from epoch 40: after 48 epochs the least of the last 10 (1/40) is first not 7% below the least before (1/38)
    assert list(table["stop"]) == [48, 100] and list(table["saved"]) == [0.52, 0.0]
    assert table["stop / last"].iloc[0] == 1.0
    assert mod.main([str(tmp_path), "--window", "10", "--tolerance", "0.07"]) == 0
    assert "26% of the epochs saved on average" in capsys.readouterr().out
