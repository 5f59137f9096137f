"""Pipeline stages of Neural Modes (``workflow/rules/neural_modes.smk``): linear modes, training, summary,
and the evaluation studies of Wang et al. 2024 that a scene's ``nm_study`` block switches on.

- ``nm_linear_modes``, ``nm_train``, ``nm_summary``: the subspace itself;
- ``nm_ground_truth``: Eq. 9 on the sample sets of a study (``sheet``: grids and random samples;
  ``energy``: uniform samples split in order), its own artefact so retraining never re-solves it;
- ``nm_sheet_study``, ``nm_sheet_tables``: every method of Sec. 4.1-4.4 along its training, then
  Tables 2, 3, 4, A1 and Figs. 2, 3, 4 (``latentsim.neural_modes.sheet``, ``latentsim.neural_modes.figures``);
- ``nm_energy_table``: Table 5 (``latentsim.neural_modes.energy_study``);
- ``nm_dynamics``: the subspace dynamics of Sec. 4.5 against the full simulation, with ParaView series;
- ``nm_keyframes``: Fig. 6, linear interpolation of modal coordinates between keyframes;
- ``nm_aspect_ratio``: Sec. 4.3 / Fig. A2, one network conditioned on a sheet's aspect ratio
  (``latentsim.neural_modes.aspect``).

Each stage reads its inputs, calls the package and writes its artefacts atomically with provenance
(``docs/artefacts.md``, section Neural Modes).  The params each rule passes them are built in
``latentsim.rule_params`` (``nm_*_params``), with both papers' others.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import shutil
import time
from pathlib import Path

import h5py
import meshio
import numpy as np
import pandas as pd
import torch

from latentsim import neural_modes as nm
from latentsim.checksum import KEY as CHECKSUM_KEY
from latentsim.config import with_defaults
from latentsim.io import ArtefactError, atomic_h5, atomic_path, open_artefact, read_mesh_arrays, read_tree, require, write_dataset, write_tree
from latentsim.latent import save_module
from latentsim.neural_modes import aspect as nm_aspect
from latentsim.neural_modes import dynamics as nm_dynamics
from latentsim.neural_modes import energy_study as nm_energy
from latentsim.neural_modes import sheet as nm_sheet
from latentsim.neural_modes.sheet_tables import tables as sheet_tables
from latentsim.neural_modes.sheet_tables import tables_over_seeds
from latentsim.neural_modes.symmetry import half_turn
from latentsim.neural_modes import figures as nm_figures
from latentsim.report.paraview import write_xdmf_series
from latentsim.report.tables import write_table
from latentsim.rule_params import SET_KEYS
from latentsim.latent.timing import time_full_space
from latentsim.labels import DYNAMICS_METHODS, energy_note
from latentsim.physics.materials import energy_description, material_model
from latentsim.scene import build_elastic

log = logging.getLogger(__name__)


def scene_potential(mesh_h5, model: str, material: dict):
    """(potential with every elastic stencil, arrays) of a scene's mesh; no inertia or gravity needed here."""
    arrays = read_mesh_arrays(mesh_h5)
    return build_elastic(model, arrays, material), arrays


def linear_modes_stage(mesh_h5, params: dict, out_h5):
    """Stage ``nm_linear_modes``: the scene's lowest m modes (sparse shift-invert) to ``linear_modes.h5``.

    ``params``: ``rule_params.nm_modes_params`` (or ``nm_train_params``: only the mode keys are read)."""
    cfg = with_defaults("neural_modes", params["neural_modes"], "linear_modes_stage")
    pot, arrays = scene_potential(mesh_h5, params["model"], params["material"])
    X = np.asarray(arrays["rest_positions"], dtype=np.float64)
    t0 = time.perf_counter()
    lm = nm.linear_modes(pot, int(cfg["modes"]), X, boundary=cfg["boundary"], normalization=cfg["normalization"])
    seconds = time.perf_counter() - t0
    log.info("%d modes of %d DoF in %.2f s; omega [rad/s] %s", lm.modes.shape[1], lm.modes.shape[0], seconds, np.sqrt(lm.omega2))
    with atomic_h5(out_h5, config=params) as f:
        f["rest_positions"] = X
        f["masses"] = pot.masses.numpy()
        f["omega2"] = lm.omega2
        f["modes"] = lm.modes
        f["free_dofs"] = lm.free_dofs
        f["fixed_dofs"] = nm.fixed_dofs(arrays["dirichlet"], cfg["boundary"])
        if cfg["boundary"] == "free":
            f["rigid_modes"] = nm.rigid_modes(X, pot.masses.numpy())
        f.attrs.update(rigid_removed=lm.rigid_removed, normalization=lm.normalization, boundary=cfg["boundary"], seconds=seconds)


def scene_symmetry(cfg: dict, basis: dict, arrays: dict):
    """The half turn of ``symmetry.half_turn`` when ``neural_modes.symmetry`` asks for it, else None."""
    if cfg["symmetry"] != "half_turn":
        return None
    cells = arrays["triangles"] if "triangles" in arrays else arrays["tets"]
    return half_turn(basis["X"], cells, basis["modes"], basis["fixed_dofs"])


def train_stage(mesh_h5, modes_h5, params: dict, seed: int, out_pt, out_h5):
    """Stage ``nm_train``: self-supervised Neural Modes (Eq. 13), its history and latent-direction correlation."""
    cfg = with_defaults("neural_modes", params["neural_modes"], "train_stage")
    pot, arrays = scene_potential(mesh_h5, params["model"], params["material"])
    basis = read_linear_modes(modes_h5)
    masses = pot.masses.numpy()
    torch.manual_seed(seed)
    model = nm.from_config(basis, cfg, masses, symmetry=scene_symmetry(cfg, basis, arrays))
    hist = nm.train_neural_modes(model, pot, cfg, seed=seed)
    log.info("trained %d epochs in %.0f s; final energy %.4g, constraint %.3g", cfg["epochs"], hist["seconds"], hist["energy"][-1], hist["constraint"][-1])
    # evaluation on a fixed set of uniform samples: energy of Neural Modes vs linear modes at the same z
    gen = torch.Generator().manual_seed(seed + 1)
    z = nm.modal_samples("stochastic", model.m, cfg["box"], 256, generator=gen)
    with torch.no_grad():
        e_nm = pot.elastic(model(z)).numpy()
        e_lin = pot.elastic((model.X + model.linear(z)).reshape(-1, model.n, 3)).numpy()
        l, y = model.linear(z), model.correction(z)
        cos = ((l * y).sum(-1).abs() / (l.norm(dim=-1) * y.norm(dim=-1)).clamp_min(1e-300)).numpy()
        origin = float((model(torch.zeros(1, model.m, dtype=torch.float64))[0].reshape(-1) - model.X).norm() / model.X.norm())
    C, w = nm.direction_correlation(nm.latent_directions(model, model.m).numpy(), masses)
    save_module(out_pt, model, extra={"config": cfg, "seed": seed})
    with atomic_h5(out_h5, config=params, seed=seed) as f:
        for key in ("loss", "energy", "constraint", "origin"):
            f[key] = np.asarray(hist[key])
        f["eval_z"] = z.numpy()
        f["eval_energy"] = e_nm
        f["eval_energy_linear"] = e_lin
        f["eval_cosine_ly"] = cos
        f["correlation"] = C
        f["correlation_eigenvalues"] = w
        f.attrs.update(train_seconds=hist["seconds"], origin_relative_error=origin)


def summary_stage(history_files: dict, out_csv, out_md):
    """Stage ``nm_summary``: one row per scene (energy vs linear modes, constraint, origin, correlation eigenvalues)."""
    rows, energies = [], []
    for scene, path in sorted(history_files.items()):
        with open_artefact(path) as f:
            params = json.loads(f.attrs["config"])
            cfg = params["neural_modes"]
            energies.append(f"- {scene}: {energy_description(params['model'], params['material'])}")
            e, el = f["eval_energy"][()], f["eval_energy_linear"][()]
            w = f["correlation_eigenvalues"][()]
            rows.append(
                {
                    "scene": scene,
                    "modes": cfg.get("modes"),
                    "boundary": cfg.get("boundary"),
                    "material.model": material_model(params["model"], params["material"]),
                    "E_avg neural": float(e.mean()),
                    "E_avg linear": float(el.mean()),
                    "E ratio": float(e.mean() / max(el.mean(), 1e-300)),
                    "max |cos(l, y)|": float(f["eval_cosine_ly"][()].max()),
                    "|n(0) - X| / |X|": float(f.attrs["origin_relative_error"]),
                    "correlation eigenvalues": " ".join(f"{v:.3f}" for v in w),
                    "train s": float(f.attrs["train_seconds"]),
                }
            )
    df = pd.DataFrame(rows)
    write_table(df, out_csv)
    write_markdown(out_md, {None: df}, "Elastic energy of each scene (every E column):\n\n" + "\n".join(energies) + "\n")


# --------------------------------------------------------------------------------------------------
# shared readers and writers
# --------------------------------------------------------------------------------------------------
def read_linear_modes(path) -> dict:
    """``linear_modes.h5`` as a dict: X (n,3), masses, modes (3n,m), free_dofs, fixed_dofs, rigid (3n,6) or None."""
    with open_artefact(path) as f:
        names = {"X": "rest_positions", "masses": "masses", "modes": "modes", "free_dofs": "free_dofs", "fixed_dofs": "fixed_dofs"}
        out = {k: require(f, name, path=path)[()] for k, name in names.items()}
        out["rigid"] = f["rigid_modes"][()] if "rigid_modes" in f else None
    return out


def write_markdown(path, sections: dict, preamble: str = ""):
    """Markdown tables, atomically: ``sections`` {heading (or None): DataFrame}."""
    parts = [preamble] if preamble else []
    for heading, df in sections.items():
        parts += ([f"## {heading}", ""] if heading else []) + [df.to_markdown(index=False, floatfmt=".4g"), ""]
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(parts) + "\n")


def read_ground_truth(path) -> dict:
    """``ground_truth.h5``: {set name: {z, x, energy, residual, iterations}}."""
    with open_artefact(path) as f:
        sets = read_tree(require(f, "sets", path=path))
    if not sets:
        raise ArtefactError(f"{path}: no ground-truth sets under /sets")
    return sets


@contextlib.contextmanager
def _new_folder(folder):
    """Write a folder under a temporary name; it replaces ``folder`` once complete (as ``simulate.write_paraview``)."""
    folder = Path(folder)
    with atomic_path(folder) as tmp:
        tmp.mkdir(parents=True)
        yield tmp
        if folder.exists():
            shutil.rmtree(folder)


# --------------------------------------------------------------------------------------------------
# ground truth (Eq. 9) of a study's sample sets
# --------------------------------------------------------------------------------------------------
def study_sets(study: str, m: int, box: float, sets: dict, seed: int) -> dict:
    """The modal coordinates of a study's sets: ``sheet`` (train_grid, train_random, val, test) or
    ``energy`` (train, val, test: uniform samples split in order)."""
    if study == "sheet":
        return nm_sheet.sample_sets(m, box, sets["train_grid"], sets["val_grid"], sets["test_grid"], sets["random_samples"], seed)
    if study == "energy":
        return nm_energy.energy_sets(m, box, sets["samples"], sets["train"], sets["validation"], seed)
    raise ValueError(f"study {study!r} has no ground truth; studies with one: {sorted(SET_KEYS)}")


def ground_truth_stage(mesh_h5, modes_h5, study: str, params: dict, out_h5, progress: bool = False, checkpoint=None):
    """Stage ``nm_ground_truth``: Eq. 9 for every sample of a study's sets (``ground_truth.h5``).

    ``checkpoint``: where the samples solved so far are kept while the job runs
    (:class:`~latentsim.neural_modes.sheet.GroundTruthCheckpoint`), so that a killed job resumes; removed
    once the ground truth is written."""
    pot, _ = scene_potential(mesh_h5, params["model"], params["material"])
    basis = read_linear_modes(modes_h5)
    nmc = params["neural_modes"]
    sets = study_sets(study, basis["modes"].shape[1], float(nmc["box"]), params["sets"], params["seed"])
    what = hashlib.sha256(json.dumps({"study": study, "params": params}, sort_keys=True, default=str).encode())
    for path in (mesh_h5, modes_h5):
        with open_artefact(path) as f:
            what.update(str(f.attrs[CHECKSUM_KEY]).encode())
    gt = nm_sheet.solve_sets(
        pot, basis["X"], basis["modes"], sets, free_dofs=basis["free_dofs"], rigid=basis["rigid"], metric=nmc["metric"],
        max_iter=int(params["max_iterations"]), progress=progress, checkpoint=checkpoint, fingerprint=what.hexdigest(),
    )  # fmt: skip
    tree = {name: {k: (float(v) if k == "seconds" else np.asarray(v)) for k, v in s.items()} for name, s in gt.items()}
    with atomic_h5(out_h5, config=params, seed=params["seed"]) as f:
        write_tree(f.create_group("sets", track_order=True), tree)
    if checkpoint is not None:
        Path(checkpoint).unlink(missing_ok=True)


# --------------------------------------------------------------------------------------------------
# the sheet study: Tables 2, 3, 4, A1, Figs. 2, 3, 4
# --------------------------------------------------------------------------------------------------
def sheet_study_stage(mesh_h5, modes_h5, gt_h5, params: dict, out_h5, progress: bool = False):
    """Stage ``nm_sheet_study``: every method trained and evaluated along its training (``study.h5``)."""
    pot, arrays = scene_potential(mesh_h5, params["model"], params["material"])
    if "triangles" not in arrays:
        raise ValueError(f"{mesh_h5}: the sheet study needs a shell (membrane stress, Table 4); this mesh has no triangles")
    basis = read_linear_modes(modes_h5)
    gt = read_ground_truth(gt_h5)
    missing = sorted({"train_grid", "train_random", "val", "test"} - set(gt))
    if missing:
        raise ArtefactError(f"{gt_h5}: missing the ground-truth set(s) {missing} of the sheet study")
    study = nm_sheet.run_sheet_study(pot, basis, gt, params["neural_modes"], params["study"], arrays["triangles"], params["seed"], progress)
    with atomic_h5(out_h5, config=params, seed=params["seed"]) as f:
        f.attrs["model"] = params["model"]
        write_dataset(f, "rest_positions", basis["X"])
        write_dataset(f, "triangles", arrays["triangles"])
        write_tree(f, study)


SHEET_TABLES = ("table2", "table3", "table4", "tableA1", "correlation", "structure")
SHEET_HEADINGS = {
    "table2": "Table 2: elastic energy error against the ground truth (validation and test)",
    "table3": "Table 3: early stopping of the supervised methods by validation L2 and by validation energy",
    "table4": "Table 4: membrane stress |S| (first Piola-Kirchhoff, Frobenius) on the test set",
    "tableA1": "Table A1: nodal forces on the test set",
    "correlation": "Fig. 4: eigenvalues of the latent directions' correlation matrix at the origin",
    "structure": "Fig. 3: the origin and the half-turn symmetry (test set)",
}


def sheet_tables_stage(study_h5, out: dict):
    """Stage ``nm_sheet_tables``: the tables (CSV each, all in one Markdown) and Figs. 2, 3, 4 of the sheet
    study, over its seeds.

    ``study_h5``: one ``study.h5`` or a list, one per seed: each table is the median over the seeds with the
    headline errors' least and largest (:func:`latentsim.neural_modes.sheet_tables.tables_over_seeds`); the
    figures show the first seed's study.
    ``out``: paths by name: the keys of :data:`SHEET_TABLES`, ``markdown``, ``learning_curves``,
    ``latent_walk``, ``correlation_figure``.
    """
    paths = [study_h5] if isinstance(study_h5, (str, bytes)) or hasattr(study_h5, "__fspath__") else list(study_h5)
    studies = []
    for path in paths:
        with open_artefact(path) as f:
            one = read_tree(f)
            one["seed"] = int(f.attrs.get("seed", -1))
        for key in ("methods", "walk", "correlation", "rest_positions", "triangles"):
            if key not in one:
                raise ArtefactError(f"{path}: missing '{key}'; rerun nm_sheet_study")
        studies.append(one)
    study = studies[0]
    tabs = tables_over_seeds([sheet_tables(s) for s in studies], [s["seed"] for s in studies])
    for name in SHEET_TABLES:
        write_table(tabs[name], out[name])
    cfg = json.loads(study["config"])
    st, g = cfg["study"], study["ground_truth"]
    preamble = (
        f"# Neural Modes sheet study (Wang et al. 2024, Sec. 4.1-4.4)\n\nOurs beside the paper's numbers (columns `*_paper*`). "
        f"Sets: train {st['train_grid']}^m grid and {st['random_samples']} random samples, validation {st['val_grid']}^m, "
        f"test {st['test_grid']}^m grid (the paper: 9^3, 729, 7^3, 11^3). Neural Modes {st['epochs']} L-BFGS epochs, "
        f"L2 supervised {st['l2_epochs']}, PCA+AE {st['ae_epochs']} Adam epochs. {energy_note(cfg['model'], cfg['material'])} Ground truth on the test set (constrained Newton, at most "
        f"{st['gt_max_iterations']} iterations): KKT residual relative to the force at X + l, median {g['residual_median']:.1e}, "
        f"90th percentile {g['residual_p90']:.1e}; {g['iterations_mean']:.1f} iterations on average. "
        + (f"Every method trained with {len(studies)} seeds ({', '.join(str(s['seed']) for s in studies)}): each number is the median "
           f"over them, the headline errors with their least and largest (`_min`, `_max`); the figures show seed {study['seed']}.\n"
           if len(studies) > 1 else f"One seed ({study['seed']}).\n")
    )
    write_markdown(out["markdown"], {SHEET_HEADINGS[k]: tabs[k] for k in SHEET_TABLES}, preamble)
    nm_figures.learning_curves(study, out["learning_curves"])
    nm_figures.correlation_heatmaps(study["correlation"], out["correlation_figure"])
    columns = {}
    for w in study["walk"].values():
        for i, pos in enumerate(w["positions"]):
            columns[f"{w['label']} z{i + 1}"] = pos
    steps = next(iter(study["walk"].values()))["positions"].shape[1]
    nm_figures.shape_strips(
        columns, study["rest_positions"], study["triangles"], "shell", out["latent_walk"],
        f"Latent walks (Fig. 3): frame k = coordinate z_i at k/{steps - 1} of its range, the others 0",
    )  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Table 5
# --------------------------------------------------------------------------------------------------
def energy_table_stage(mesh_h5, gt_h5, model_pt, params: dict, out_csv, out_md, out_h5, progress: bool = False):
    """Stage ``nm_energy_table``: Table 5 (CSV, Markdown) and PCA+AE's validation curve (``history.h5``)."""
    pot, arrays = scene_potential(mesh_h5, params["model"], params["material"])
    gt = read_ground_truth(gt_h5)
    missing = sorted({"train", "val", "test"} - set(gt))
    if missing:
        raise ArtefactError(f"{gt_h5}: missing the ground-truth set(s) {missing} of the energy study")
    model = nm.load_neural_modes(model_pt)
    st = params["study"]
    table, hist = nm_energy.energy_table(pot, arrays["rest_positions"], gt, model, {**st, "widths": params["widths"]}, params["seed"], progress)
    write_table(table, out_csv)
    sizes = {s: len(gt[s]["z"]) for s in ("train", "val", "test")}
    write_markdown(
        out_md, {None: table},
        f"# Table 5 (Wang et al. 2024): mean elastic energy [J] on the test set, per interval and overall\n\n"
        f"{sizes['train']} / {sizes['val']} / {sizes['test']} uniform modal samples (train / validation / test; the paper: 900 / 100 / 300); "
        f"PCA+AE kept at its least validation L2 (epoch {int(hist['epochs'][hist['stop']])} of {st['ae_epochs']}); "
        f"`l2`: mean squared position error against the ground truth. The paper's row is x1e4 J. {energy_note(params['model'], params['material'])}\n",
    )  # fmt: skip
    with atomic_h5(out_h5, config=params, seed=params["seed"]) as f:
        write_tree(f, {k: (np.asarray(v) if np.ndim(v) else v) for k, v in hist.items()})


# --------------------------------------------------------------------------------------------------
# subspace dynamics and keyframing
# --------------------------------------------------------------------------------------------------
def _copy_root(src, dst):
    """The rest state, masses, elements and scene attributes of a trajectories.h5 (not its sequences)."""
    for k, item in src.items():
        if isinstance(item, h5py.Dataset):
            write_dataset(dst, k, item[()])
    for k, v in src.attrs.items():
        if k not in ("config", "seed", "latentsim_version"):
            dst.attrs[k] = v


def dynamics_stage(trajectories_h5, model_pt, params: dict, out: dict, progress: bool = False):
    """Stage ``nm_dynamics``: every row of ``labels.DYNAMICS_METHODS`` against the full simulation.

    ``out``: ``csv``, ``markdown``, ``paraview`` (folder), and one path per method slug (trajectory
    layout, the scene's test sequence: positions, latents, step_ms, iterations, error).
    """
    model = nm.load_neural_modes(model_pt)
    st = params["study"]
    with open_artefact(trajectories_h5) as f:
        full = time_full_space(f, nm_dynamics.first_test_sequence(f), int(st["full_frames_timed"]))
        res = nm_dynamics.subspace_dynamics(f, model, float(params["box"]), st, full, progress)
        name = res["sequence"]
        for slug, run in res["runs"].items():
            label, linear, method, cubature = DYNAMICS_METHODS[slug]
            kind = "linear" if linear else "neural"
            with atomic_h5(out[slug], config=params, seed=-1) as g:
                _copy_root(f, g)
                g.attrs.update(method=slug, label=label, mode="reduced", subspace_dim=model.m, solver=method, **res["full"])
                if cubature:
                    c = res["cubatures"][kind]
                    write_dataset(g, "cubature_index", c.index)
                    write_dataset(g, "cubature_weights", c.weights)
                    g.attrs.update(cubature_elements=len(c.index), cubature_force_error=c.train_error, cubature_validation_error=c.validation_error,
                                   cubature_fit_seconds=c.fit_seconds)  # fmt: skip
                h = g.create_group("sequences", track_order=True).create_group(name)
                h.attrs.update(split="test", method=slug, diverged_frame=int(run["diverged_frame"]))
                for k in ("positions", "latents", "step_ms", "iterations", "error", "map_ms", "derivatives_ms", "reduce_ms", "line_search_ms"):
                    write_dataset(h, k, run[k])
                write_dataset(h, "dirichlet_positions", res["dirichlet_positions"])
    rows = res["rows"]
    write_table(rows, out["csv"])
    T = len(res["reference"])
    write_markdown(
        out["markdown"], {None: rows},
        f"# Subspace dynamics (Wang et al. 2024, Eq. 15, Sec. 4.5): sequence `{name}`, {T} frames\n\n"
        "The prescribed Dirichlet motion replayed in each subspace by reduced implicit Euler; error: RMS vertex distance to the "
        "full simulation / rest bounding-box diagonal (mean and max over frames). The full-space Newton frame of the same "
        f"sequence is timed in the same process ({res['full']['full_frames_timed']} frames). Cubature: fitted to "
        f"{st['cubature_tolerance']:.0%} of the reduced elastic forces at {st['cubature_samples']} poses drawn in the modal box.\n",
    )  # fmt: skip
    with _new_folder(out["paraview"]) as tmp:
        for slug in res["runs"]:
            write_xdmf_series(out[slug], name, Path(tmp) / f"{slug}.xdmf", reference=trajectories_h5)


def keyframes_stage(mesh_h5, model_pt, params: dict, out_h5, out_png, out_paraview):
    """Stage ``nm_keyframes`` (Fig. 6): keyframe poses interpolated linearly in modal coordinates, decoded by
    Neural Modes and by the linear modes alone; a trajectory-layout file, a figure and ParaView series."""
    model = nm.load_neural_modes(model_pt)
    arrays = read_mesh_arrays(mesh_h5)
    st = params["study"]
    poses = np.asarray(st["poses"], dtype=np.float64) * float(params["box"])
    if poses.ndim != 2 or poses.shape[1] != model.m:
        raise ValueError(f"nm_study.keyframes.poses: each pose needs {model.m} modal coordinates (the scene's modes), got shape {poses.shape}")
    z, keys = nm_dynamics.keyframe_coordinates(poses, int(st["steps"]))
    with torch.no_grad():
        zt = torch.as_tensor(z)
        shapes = {"neural_modes": model(zt).numpy(), "linear_modes": (model.X + model.linear(zt)).reshape(len(z), -1, 3).numpy()}
    model_kind = arrays["model"]
    with atomic_h5(out_h5, config=params, seed=-1) as f:
        f.attrs.update(model=model_kind, dt=1.0 / int(st["steps"]))
        for k in ("rest_positions", "dirichlet", "triangles", "tets", "surface"):
            if k in arrays:
                write_dataset(f, k, arrays[k])
        grp = f.create_group("sequences", track_order=True)
        for name, pos in shapes.items():
            g = grp.create_group(name)
            g.attrs.update(split="test", method=name, keyframes=keys)
            write_dataset(g, "positions", pos)
            write_dataset(g, "z", z)
    cells = arrays["triangles"] if model_kind == "shell" else arrays["surface"]
    half = max(int(st["steps"]) // 2, 1)
    rows = np.arange(0, len(z), half)
    nm_figures.shape_strips(
        {"Neural Modes": shapes["neural_modes"], "linear modes": shapes["linear_modes"]}, arrays["rest_positions"], cells, model_kind, out_png,
        f"keyframes {', '.join(map(str, keys))}",
        rows=rows, panel_size=3.0, dirichlet=arrays.get("dirichlet"),
    )  # fmt: skip
    with _new_folder(out_paraview) as tmp:
        for name in shapes:
            write_xdmf_series(out_h5, name, Path(tmp) / f"{name}.xdmf")


# --------------------------------------------------------------------------------------------------
# the aspect-ratio example (Sec. 4.3, Fig. A2)
# --------------------------------------------------------------------------------------------------
def aspect_ratios(st: dict) -> tuple[np.ndarray, np.ndarray]:
    """The study's ratios (evenly spaced, ``ratio_min`` to ``ratio_max``) and which train (every other
    one, both ends included; the ones between are held out)."""
    count = int(st["ratios"])
    if count % 2 == 0:
        raise ValueError(f"nm_study.aspect.ratios {count}: use an odd count, so that both ends train and every other ratio is held out")
    if not 0 < float(st["ratio_min"]) < float(st["ratio_max"]):
        raise ValueError(f"nm_study.aspect: need 0 < ratio_min < ratio_max, got {st['ratio_min']} and {st['ratio_max']}")
    ratios = np.linspace(float(st["ratio_min"]), float(st["ratio_max"]), count)
    return ratios, np.arange(count) % 2 == 0


def aspect_stage(mesh_h5, params: dict, out: dict, progress: bool = False):
    """Stage ``nm_aspect_ratio`` (Sec. 4.3, Fig. A2): tracked linear modes of the sheet stretched to each
    ratio, one network conditioned on the ratio trained on every other ratio, evaluated at all of them.

    ``out``: model, family (h5), csv, markdown, figure, paraview (folder)."""
    st = params["study"]
    # the scene's map and loss settings, the study's own modes and widths (its training sets the rest)
    cfg = {**params["neural_modes"], "modes": int(st["modes"]), "widths": [int(w) for w in st["widths"]]}
    arrays = read_mesh_arrays(mesh_h5)
    ratios, train = aspect_ratios(st)
    t0 = time.perf_counter()
    family = nm_aspect.mode_family(arrays, params["model"], params["material"], ratios, cfg["modes"], cfg["boundary"], cfg["normalization"],
                                   extra=int(st["track_extra"]))  # fmt: skip
    log.info("tracked %d modes over %d ratios in %.1f s; smallest overlap between neighbours %.3f", cfg["modes"], len(ratios), time.perf_counter() - t0,
             family.overlap.min())  # fmt: skip
    if family.overlap.min() < 0.5:
        log.warning("a mode's overlap with its match at the next ratio is %.2f: nm_study.aspect.ratios is too coarse to follow the modes", family.overlap.min())
    pots = {k: nm_aspect.ratio_potential(arrays, params["model"], params["material"], family.X[k]) for k in range(len(ratios))}
    torch.manual_seed(int(params["seed"]))
    model = nm_aspect.RatioConditionedModes.build(family, cfg, arrays["triangles"], symmetric=cfg["symmetry"] == "half_turn")
    hist = nm_aspect.train_family(model, {k: pots[k] for k in np.flatnonzero(train)}, cfg, int(st["batch_size"]), int(st["epochs"]),
                                  seed=int(params["seed"]), progress=progress)  # fmt: skip
    log.info("trained %d epochs on %d ratios in %.0f s; final mean energy %.4g", int(st["epochs"]), int(train.sum()), hist["seconds"], hist["energy"][-1])
    model.eval()
    gen = torch.Generator().manual_seed(int(params["seed"]) + 2)
    z = nm.modal_samples("stochastic", cfg["modes"], cfg["box"], int(st["test_samples"]), generator=gen).numpy()
    ev = nm_aspect.evaluate_family(model, family, pots, z, train, cfg, max_iter=int(st["gt_max_iterations"]),
                                  amplitude=float(st["figure_amplitude"]), progress=progress)  # fmt: skip
    save_module(out["model"], model, extra={"config": cfg, "study": st, "seed": int(params["seed"])})
    _write_aspect_family(out["family"], params, family, train, arrays["triangles"], z, ev, hist)
    df, summary = _aspect_tables(ratios, train, family, ev)
    write_table(df, out["csv"])
    write_markdown(out["markdown"], {"Per ratio": df, "Training against held-out ratios": summary}, preamble=_aspect_preamble(st, hist, len(z)))
    normal = nm_aspect.sheet_axes(family.X[0])[2]
    rows = np.unique(np.linspace(0, len(ratios) - 1, min(int(st["figure_rows"]), len(ratios))).round().astype(int))[::-1]
    nm_figures.aspect_ratio_figure(ratios, train, family.X, ev["modes_plus"], arrays["triangles"], normal, ev, out["figure"], rows=rows,
                                   amplitude=float(st["figure_amplitude"]))  # fmt: skip
    with _new_folder(out["paraview"]) as tmp:
        for k, r in enumerate(ratios):
            for j in range(cfg["modes"]):
                u = ev["modes_plus"][k, j] - family.X[k]
                meshio.write(Path(tmp) / f"ratio_{r:.3f}_mode_{j + 1}.vtu",
                             meshio.Mesh(family.X[k], [("triangle", np.asarray(arrays["triangles"]))], point_data={"displacement": u}))  # fmt: skip


def _write_aspect_family(path, params: dict, family, train, triangles, z, ev: dict, hist: dict) -> None:
    """``family.h5`` of the aspect-ratio study: the tracked modes, the splits, the evaluation and the training history."""
    with atomic_h5(path, config=params, seed=int(params["seed"])) as f:
        for key in ("ratios", "X", "modes", "omega2", "overlap", "rank", "fixed_dofs", "masses"):
            write_dataset(f, key, getattr(family, key))
        if family.rigid is not None:
            write_dataset(f, "rigid", family.rigid)
        write_dataset(f, "train", train)
        write_dataset(f, "triangles", triangles)
        write_dataset(f, "test_z", z)
        g = f.create_group("evaluation")
        for key, value in ev.items():
            if key != "gt_seconds":
                write_dataset(g, key, value)
        h = f.create_group("history")
        for key in ("loss", "energy", "constraint"):
            write_dataset(h, key, np.asarray(hist[key]))
        f.attrs.update(train_seconds=hist["seconds"], ground_truth_seconds=ev["gt_seconds"])


def _aspect_tables(ratios, train, family, ev: dict):
    """(per-ratio table, training against held-out summary) of the aspect-ratio study."""
    df = pd.DataFrame(
        {
            "ratio": ratios, "split": np.where(train, "train", "held out"), "E_avg ground truth": ev["E_gt"], "E_avg Neural Modes": ev["E_nm"],
            "E_avg linear modes": ev["E_linear"], "E_avg Neural Modes, far ratio": ev["E_wrong_ratio"], "dE_avg Neural Modes": ev["dE_nm"],
            "dE_avg linear modes": ev["dE_linear"], "mode 1 fold Neural Modes [deg]": ev["fold_nm"], "mode 1 fold linear [deg]": ev["fold_linear"],
            "mode tracking overlap": family.overlap, "max |cos(l, y)|": ev["constraint_max"],
        }
    )  # fmt: skip
    held = ~train
    summary = pd.DataFrame(
        {
            "ratios": ["train", "held out"],
            "dE_avg Neural Modes": [ev["dE_nm"][train].mean(), ev["dE_nm"][held].mean()],
            "dE_avg linear modes": [ev["dE_linear"][train].mean(), ev["dE_linear"][held].mean()],
            "E_avg Neural Modes / ground truth": [(ev["E_nm"] / ev["E_gt"])[train].mean(), (ev["E_nm"] / ev["E_gt"])[held].mean()],
            "E_avg far ratio / right ratio": [(ev["E_wrong_ratio"] / ev["E_nm"])[train].mean(), (ev["E_wrong_ratio"] / ev["E_nm"])[held].mean()],
        }
    )  # fmt: skip
    return df, summary


def _aspect_preamble(st: dict, hist: dict, samples: int) -> str:
    """The aspect-ratio Markdown's introduction: what the paper shows and what the table measures."""
    return (
        "# Neural Modes conditioned on the aspect ratio (Wang et al. 2024, Sec. 4.3, Fig. A2)\n\n"
        "The paper: starting from a 2:1 sheet, the folding direction (of the first mode) smoothly changes from the short axis to the "
        "diagonal as the ratio decreases towards 1:1 (no numbers given). Here: one network y(z, r) with the ratio r as its auxiliary "
        f"input, trained on the ratios marked train ({hist['seconds']:.0f} s, {int(st['epochs'])} epochs), the others held out; "
        f"{samples} uniform test samples in the modal box at every ratio, ground truth by Eq. 9 at that ratio. Fold: the angle between "
        "the long axis and the principal direction of the larger curvature of mode 1 at z_1 = "
        f"{float(st['figure_amplitude']):g} box (0: the long axis bends, i.e. the fold "
        "runs along the short axis; 45: diagonal). 'Far ratio': the same shapes' network told the other end of the range instead of "
        "their own ratio.\n"
    )
