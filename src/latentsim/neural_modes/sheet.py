r"""The square-sheet study of Neural Modes (Wang et al. 2024, Sec. 4.1-4.4): every method along its training.

Methods (all map 3 modal/latent coordinates to the 121-vertex sheet):

- Neural Modes (stoch.) / (grid): self-supervised (``training.train_neural_modes``),
  z uniform in [-b, b]^3 redrawn every epoch, or the fixed 9^3 grid; with the orthogonality or the
  symmetry built into the map, a third run with the paper's own map (penalty, nothing built in);
- the baselines of ``baselines``: L2 supervised (the same network on the grid ground truth),
  PCA+AE on random / grid ground truth, and Sharp et al. 2023 (data-free) for the mode collapse.

Ground truth (Eq. 9) of the sample sets (:func:`sample_sets`, :func:`solve_sets`) is its own
artefact; :func:`run_sheet_study` trains every method, evaluates it on the validation and test sets
at checkpoints of its training (``metrics``), picks each method's checkpoint, and adds the latent
walks (Fig. 3) and the latent directions' correlation (Fig. 4).  ``sheet_tables.tables`` makes the
tables.
"""

from __future__ import annotations

import copy
import logging
import sys
import time
import typing
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from latentsim.config import with_defaults
from latentsim.io import atomic_path
from latentsim.neural_modes.baselines import SHARP, autoencoder_along_training, mode_collapse, train_l2_supervised
from latentsim.neural_modes.compliant_modes import ground_truth
from latentsim.neural_modes.metrics import METRICS, STOPPING, checkpoints, metric_vector, stopping_index
from latentsim.neural_modes.network import from_config
from latentsim.neural_modes.symmetry import half_turn, latent_walk, symmetry_error
from latentsim.neural_modes.training import modal_samples, train_neural_modes
from latentsim.solve.constrained import CompliantInfo

log = logging.getLogger(__name__)

__all__ = ["AUTOENCODERS", "GroundTruthCheckpoint", "SHEET_METHODS", "SUPERVISED", "TRAIN_SET", "WALKS", "run_sheet_study", "sample_sets", "solve_sets"]


def sample_sets(m: int, box: float, train_grid=9, val_grid=7, test_grid=11, random_count=729, seed=0) -> dict:
    """The modal coordinates of every set: train grid, train random, validation and test grids."""
    gen = torch.Generator().manual_seed(seed)
    return {
        "train_grid": modal_samples("grid", m, box, resolution=train_grid).numpy(),
        "train_random": modal_samples("stochastic", m, box, random_count, generator=gen).numpy(),
        "val": modal_samples("grid", m, box, resolution=val_grid).numpy(),
        "test": modal_samples("grid", m, box, resolution=test_grid).numpy(),
    }


def solve_sets(
    potential, X, modes, sets: dict, free_dofs=None, rigid=None, metric="euclidean", max_iter=40, progress=False, checkpoint=None, fingerprint="",
) -> dict:  # fmt: skip
    """Ground truth (Eq. 9) for every set: {name: {z, x (N,n,3), energy, residual, iterations, seconds}}.

    ``free_dofs`` (Dirichlet modes: the prescribed DoFs stay at rest) and ``rigid`` (free-floating:
    the correction is held M-orthogonal to the rigid modes) as :func:`compliant_modes.ground_truth`.
    ``checkpoint``: a file the samples solved so far are written to (:class:`GroundTruthCheckpoint`,
    tagged ``fingerprint``), from which a killed job resumes to the same result; None, none.
    """
    saved = GroundTruthCheckpoint(checkpoint, fingerprint) if checkpoint is not None else None
    out = {}
    for name, z in sets.items():
        x_done, infos_done, seconds_before = saved.resume(name) if saved is not None else ([], [], 0.0)
        t0 = time.perf_counter()
        with tqdm(total=len(z), initial=len(infos_done), desc=f"ground truth {name}", disable=not progress, file=sys.stderr, leave=False) as bar:
            x, e, infos = ground_truth(
                potential, X, modes, z, free_dofs=free_dofs, rigid=rigid, metric=metric, max_iter=max_iter,
                progress=lambda i, info: bar.update(1), resume=(x_done, infos_done) if infos_done else None,
                solved=None if saved is None else saved.recorder(name, seconds_before - t0),
            )  # fmt: skip
        seconds = seconds_before + time.perf_counter() - t0
        if saved is not None:
            saved.write()
        res = np.array([i.residual for i in infos])
        its = np.array([i.iterations for i in infos])
        out[name] = {"z": np.asarray(z), "x": x, "energy": e, "residual": res, "iterations": its, "seconds": seconds}
        log.info("ground truth %s: %d samples in %.0f s, median KKT residual %.1e, iterations %.1f", name, len(z), seconds, np.median(res), its.mean())
    return out


CHECKPOINT_SECONDS = 300.0  # how often a ground truth's checkpoint is rewritten while a set is solved


class GroundTruthCheckpoint:
    """The samples of a ground truth solved so far, per set, in a file rewritten whole (atomically) every
    ``every`` seconds and at the end of each set, so that a killed ``nm_ground_truth`` job resumes where it
    stopped instead of from the first sample (its largest set takes hours on the armadillo).  The file
    holds ``fingerprint`` (what the job computes: settings and inputs); one that does not match is
    ignored, with a warning.  The stage removes it once the ground truth is written.
    """

    def __init__(self, path, fingerprint: str, every: float | None = None):
        self.path, self.fingerprint = Path(path), str(fingerprint)
        self.every = CHECKPOINT_SECONDS if every is None else float(every)
        self.sets = self._read()  # name -> {"x": [flat positions], "infos": [CompliantInfo], "seconds": float}
        self.last_write = time.monotonic()

    def _read(self) -> dict:
        if not self.path.exists():
            return {}
        with np.load(self.path) as f:
            if str(f["fingerprint"]) != self.fingerprint:
                log.warning("%s belongs to another ground truth (settings or inputs): starting over", self.path)
                return {}
            sets = {}
            for name in f["names"].tolist():
                rows = f[f"{name}__info"]
                infos = [CompliantInfo(**{k: cast(v) for (k, cast), v in zip(_INFO_FIELDS, row)}) for row in rows]
                sets[name] = {"x": list(f[f"{name}__x"]), "infos": infos, "seconds": float(f[f"{name}__seconds"])}
        return sets

    def resume(self, name: str) -> tuple[list, list, float]:
        """The positions, infos and seconds of the samples of set ``name`` solved before."""
        s = self.sets.get(name)
        if s is None or not s["infos"]:
            return [], [], 0.0
        log.info("ground truth %s: resuming after %d samples (%.0f s) from %s", name, len(s["infos"]), s["seconds"], self.path)
        return s["x"], s["infos"], s["seconds"]

    def recorder(self, name: str, offset: float):
        """The ``solved`` callback of :func:`ground_truth` for set ``name``: a set's seconds are ``offset``
        plus the clock (its earlier seconds less the start of this job's solve)."""
        s = self.sets.setdefault(name, {"x": [], "infos": [], "seconds": 0.0})

        def solved(done, x, info):
            s["x"].append(np.asarray(x, dtype=np.float64).reshape(-1))
            s["infos"].append(info)
            s["seconds"] = offset + time.perf_counter()
            if len(s["infos"]) != done:
                raise RuntimeError(f"ground truth {name}: {len(s['infos'])} samples recorded for {done} solved")
            if time.monotonic() - self.last_write >= self.every:
                self.write()

        return solved

    def write(self) -> None:
        arrays = {"fingerprint": np.array(self.fingerprint), "names": np.array(list(self.sets))}
        for name, s in self.sets.items():
            arrays[f"{name}__x"] = np.array(s["x"]) if s["x"] else np.empty((0, 0))
            arrays[f"{name}__info"] = np.array([[float(getattr(i, k)) for k, _ in _INFO_FIELDS] for i in s["infos"]]).reshape(-1, len(_INFO_FIELDS))
            arrays[f"{name}__seconds"] = np.array(s["seconds"])
        with atomic_path(self.path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
        self.last_write = time.monotonic()

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


_INFO_FIELDS = tuple(typing.get_type_hints(CompliantInfo).items())  # (name, type) of each field, in order


# --------------------------------------------------------------------------------------------------
# the whole study
# --------------------------------------------------------------------------------------------------
SHEET_METHODS = {  # slug: the paper's label
    "nm_stochastic": "Neural Modes (stoch.)",
    "nm_grid": "Neural Modes (grid)",
    # with the constraint or the symmetry built into the map (orthogonality 'exact', symmetry 'half_turn'),
    # the paper's map too: the penalty lambda (l^T y)^2, nothing built in but n(0) = X
    "nm_grid_penalty": "Neural Modes (grid, penalty, as the paper)",
    "l2_supervised": "L2 Supervised",
    "pca_ae": "PCA+AE",
    "pca_ae_grid": "PCA+AE (grid)",
}
SUPERVISED = ("l2_supervised", "pca_ae", "pca_ae_grid")  # early-stopped on the validation L2 in Tables 2, 4, A1
AUTOENCODERS = ("pca_ae", "pca_ae_grid")  # the methods that reconstruct ground truth (encode, decode); the others map z
TRAIN_SET = {"nm_stochastic": "train_random", "nm_grid": "train_grid", "nm_grid_penalty": "train_grid", "l2_supervised": "train_grid", "pca_ae": "train_random", "pca_ae_grid": "train_grid"}
NM_SAMPLING = {"nm_stochastic": "stochastic", "nm_grid": "grid", "nm_grid_penalty": "grid"}  # the self-supervised runs
WALKS = ("nm_grid", "pca_ae_grid")  # Fig. 3: the two trained on the same grid


class _SheetRun:
    """The methods of one sheet study along their trainings: checkpoints, their metrics and snapshots.

    ``net_cfg`` {slug: Neural Modes settings} of the networks; ``symmetry`` the scene's half turn
    (``symmetry.half_turn``) or None.  ``curves[slug]`` collects, at each checkpoint, the L2 error on
    the method's training set and :func:`metrics.metric_vector` on the validation and test sets;
    ``snapshots[slug][epoch]`` the network's state dict or the autoencoder; ``seconds[slug]`` the
    training time alone (evaluation excluded).
    """

    def __init__(self, potential, basis: dict, gt: dict, net_cfg: dict, symmetry, curve_points: int, seed: int, progress: bool):
        self.potential, self.basis, self.gt, self.net_cfg, self.symmetry = potential, basis, gt, net_cfg, symmetry
        self.curve_points, self.seed, self.progress = curve_points, seed, progress
        self.masses = potential.masses.numpy()
        self.n, self.m = len(basis["X"]), basis["modes"].shape[1]
        self.Xf = basis["X"].reshape(-1)
        self.z_of = {s: torch.as_tensor(gt[s]["z"]) for s in gt}
        self.curves, self.snapshots, self.seconds = {}, {}, {}

    def new_network(self, slug: str):
        """An untrained network of method ``slug`` (seeded: every method starts from the same weights)."""
        torch.manual_seed(self.seed)
        return from_config(self.basis, self.net_cfg[slug], self.masses, symmetry=self.symmetry)

    def of_network(self, model):
        """set name -> positions (N,n,3) of a network at the set's coordinates."""

        @torch.no_grad()
        def predict(s):
            return model(self.z_of[s]).numpy()

        return predict

    def of_autoencoder(self, ae):
        """set name -> positions (N,n,3) of an autoencoder's reconstruction of the set's ground truth."""
        n, Xf = self.n, self.Xf

        @torch.no_grad()
        def predict(s):
            return (ae(torch.as_tensor(self.gt[s]["x"].reshape(-1, 3 * n) - Xf)).numpy() + Xf).reshape(-1, n, 3)

        return predict

    def record(self, slug: str, epoch: int, predict, snapshot) -> None:
        """One checkpoint of ``slug``: its metrics by ``predict`` and its ``snapshot``."""
        t0 = time.perf_counter()
        gt = self.gt
        c = self.curves.setdefault(slug, {"label": SHEET_METHODS[slug], "train_set": TRAIN_SET[slug], "epochs": [], "train_l2": [], "val": [], "test": [],
                                          "eval_seconds": 0.0})  # fmt: skip
        c["epochs"].append(int(epoch))
        c["train_l2"].append(float(((predict(c["train_set"]) - gt[c["train_set"]]["x"]) ** 2).sum((-1, -2)).mean()))
        for s in ("val", "test"):
            c[s].append(metric_vector(self.potential, predict(s), gt[s]["x"]))
        self.snapshots.setdefault(slug, {})[int(epoch)] = snapshot
        c["eval_seconds"] += time.perf_counter() - t0

    def train_network(self, slug: str, epochs: int, train) -> None:
        """Train a fresh network with ``train(model, callback)``, recording the checkpoints."""
        want = set(checkpoints(epochs, self.curve_points).tolist())
        model = self.new_network(slug)
        self.record(slug, 0, self.of_network(model), copy.deepcopy(model.state_dict()))
        bar = tqdm(total=epochs, desc=SHEET_METHODS[slug], disable=not self.progress, file=sys.stderr, leave=False)

        def callback(epoch, model):
            bar.update(1)
            if epoch + 1 in want:
                self.record(slug, epoch + 1, self.of_network(model), copy.deepcopy(model.state_dict()))

        evaluating, t0 = self.curves[slug]["eval_seconds"], time.perf_counter()
        train(model, callback)
        bar.close()
        self.seconds[slug] = time.perf_counter() - t0 - (self.curves[slug]["eval_seconds"] - evaluating)  # training alone
        log.info("%s: %d epochs in %.0f s", SHEET_METHODS[slug], epochs, self.seconds[slug])

    def train_autoencoder(self, slug: str, ae_cfg: dict, epochs: int) -> None:
        """PCA+AE on the method's training set, recorded at the checkpoints of one run of ``epochs``."""
        U = torch.as_tensor(self.gt[TRAIN_SET[slug]]["x"].reshape(-1, 3 * self.n) - self.Xf)
        for k, ae, fit_seconds in autoencoder_along_training(U, ae_cfg, checkpoints(epochs, self.curve_points), self.seed, self.progress):
            self.record(slug, k, self.of_autoencoder(ae), ae)
            self.seconds[slug] = fit_seconds  # the last: one run of epochs
        log.info("%s: %d epochs in %.0f s", SHEET_METHODS[slug], epochs, self.seconds[slug])

    def result(self, slug: str):
        """(method's tree, the model at its chosen checkpoint): curves, stopping indices, origin and symmetry errors."""
        c, m, Xf = self.curves[slug], self.m, self.Xf
        out = {k: c[k] for k in ("label", "train_set")}
        out.update(epochs=np.array(c["epochs"]), train_l2=np.array(c["train_l2"]), val=np.stack(c["val"]), test=np.stack(c["test"]))
        out["stop_final"] = len(c["epochs"]) - 1
        for crit, metric in STOPPING.items():
            out[f"stop_{crit}"] = stopping_index(out["epochs"], out["val"][:, METRICS.index(metric)])
        out["table_stopping"] = "val_l2" if slug in SUPERVISED else "final"
        out["train_seconds"] = float(self.seconds[slug])
        epoch = int(out["epochs"][out[f"stop_{out['table_stopping']}"]])
        snap = self.snapshots[slug][epoch]
        if slug in AUTOENCODERS:
            chosen = snap
            predict = self.of_autoencoder(snap)
            with torch.no_grad():
                origin = snap.decode(torch.zeros(m, dtype=torch.float64)).numpy()
        else:
            model = self.new_network(slug)
            model.load_state_dict(snap)
            chosen = model.eval()
            predict = self.of_network(model)
            with torch.no_grad():
                origin = model(torch.zeros(m, dtype=torch.float64)).numpy().reshape(-1) - Xf
        out["origin_relative_error"] = float(np.linalg.norm(origin) / np.linalg.norm(Xf))
        out["symmetry_mean"], out["symmetry_max"] = symmetry_error(predict("test"), self.gt["test"]["z"], self.basis["X"], self.symmetry)
        return out, chosen

    def walk(self, slug: str, f, box: float, steps: int) -> dict:
        """Fig. 3: shapes along each latent coordinate of ``f`` (a network over the modal box, or an
        autoencoder over the range of its training set's latents)."""
        n, m, Xf = self.n, self.m, self.Xf
        if slug in AUTOENCODERS:
            with torch.no_grad():
                lat = f.encode(torch.as_tensor(self.gt[TRAIN_SET[slug]]["x"].reshape(-1, 3 * n) - Xf)).numpy()
            low, high = lat.min(0), lat.max(0)

            @torch.no_grad()
            def decode(z):
                return (f.decode(torch.as_tensor(z)).numpy() + Xf).reshape(-1, n, 3)
        else:
            low, high = np.full(m, -box), np.full(m, box)

            @torch.no_grad()
            def decode(z):
                return f(torch.as_tensor(z)).numpy()

        coords, pos = latent_walk(decode, low, high, steps)
        return {"label": SHEET_METHODS[slug], "coordinates": coords, "positions": pos}


def run_sheet_study(potential, basis: dict, gt: dict, nm_settings: dict, study: dict, cells, seed: int = 0, progress: bool = False) -> dict:
    """Every method of Wang et al. Sec. 4.1-4.4 on one shell, evaluated along its training.

    Parameters
    ----------
    potential : the scene's potential (elastic terms; a membrane with ``stress_norm``).
    basis : ``X`` (n,3), ``modes`` (3n,m), ``fixed_dofs``, ``rigid`` (3n,6) or None (linear_modes.h5).
    gt : ground truth (:func:`solve_sets`) of the sets train_grid, train_random, val, test.
    nm_settings : the Neural Modes settings (widths, lam, eta, box, metric, ...: keys of the config
        schema's ``neural_modes``; missing ones take its defaults).
    study : epochs, batch_size (Neural Modes), train_grid, l2_epochs, ae_epochs, ae_lr, ae_batch_size,
        curve_points, sharp_epochs, sharp_batch_size, sharp_w_iso, walk_steps.
    cells : (K,k) the mesh's elements (for the symmetry check).

    Every method is evaluated on the validation and test sets (:data:`metrics.METRICS`) and by its L2
    error on its own training set at :func:`metrics.checkpoints` of its training.  Neural Modes (Eq.
    13, stochastic or on the training grid) are taken at their last epoch; the supervised methods at
    the epoch of least validation L2 (Tables 2, 4, A1; the paper's Table 2 equals its Table 3's L2
    column) and, for Table 3, of least validation energy too.

    Returns a tree of arrays and numbers (``io.write_tree`` stores it): ``methods`` {slug: label,
    train_set, epochs (C,), train_l2 (C,), val and test (C, len(METRICS)), stop_<criterion> (checkpoint
    index), table_stopping, train_seconds, origin_relative_error, symmetry_mean, symmetry_max},
    ``correlation`` {slug: label, matrix, eigenvalues}, ``walk`` {slug: label, coordinates (m,S),
    positions (m,S,n,3)}, ``ground_truth`` (its own symmetry error and the test set's KKT residuals:
    median, 90th percentile; mean Newton iterations), ``metrics``.
    """
    cfg = with_defaults("neural_modes", nm_settings, "run_sheet_study")
    X, modes = basis["X"], basis["modes"]
    symmetry = half_turn(X, cells, modes, basis["fixed_dofs"])
    # the networks' settings: with anything built into the map, a third Neural Modes run with the paper's
    net_cfg = {"nm_stochastic": cfg, "nm_grid": cfg, "l2_supervised": cfg}
    if cfg["orthogonality"] == "exact" or cfg["symmetry"] != "none":
        net_cfg["nm_grid_penalty"] = {**cfg, "orthogonality": "paper", "symmetry": "none"}
    run = _SheetRun(potential, basis, gt, net_cfg, symmetry, study["curve_points"], seed, progress)
    for slug in (s for s in net_cfg if s in NM_SAMPLING):
        settings = {**net_cfg[slug], "sampling": NM_SAMPLING[slug], "grid": study["train_grid"], "epochs": study["epochs"], "batch_size": study["batch_size"]}
        run.train_network(slug, study["epochs"], lambda model, cb, settings=settings: train_neural_modes(model, potential, settings, seed=seed, callback=cb))
    run.train_network(
        "l2_supervised", study["l2_epochs"],
        lambda model, cb: train_l2_supervised(model, gt["train_grid"]["z"], gt["train_grid"]["x"], study["l2_epochs"], cfg["lbfgs_max_iter"], callback=cb),
    )  # fmt: skip
    ae_cfg = {"latent_dim": modes.shape[1], "widths": list(cfg["widths"]), "lr": study["ae_lr"], "batch_size": study["ae_batch_size"]}
    for slug in AUTOENCODERS:
        run.train_autoencoder(slug, ae_cfg, study["ae_epochs"])
    methods, chosen = {}, {}
    for slug in run.curves:
        methods[slug], chosen[slug] = run.result(slug)
    walk = {slug: run.walk(slug, chosen[slug], cfg["box"], study["walk_steps"]) for slug in WALKS}
    collapse = mode_collapse(
        potential, X, modes, {SHEET_METHODS[s]: chosen[s] for s in ("nm_stochastic", "nm_grid")}, cfg["widths"], cfg["box"],
        {"epochs": study["sharp_epochs"], "batch_size": study["sharp_batch_size"], "w_iso": study["sharp_w_iso"]}, basis["fixed_dofs"], seed,
    )  # fmt: skip
    correlation = {}
    for slug, label in (("nm_stochastic", SHEET_METHODS["nm_stochastic"]), ("nm_grid", SHEET_METHODS["nm_grid"]), ("sharp", SHARP)):
        correlation[slug] = {"label": label, **collapse[label]}
    gt_sym = symmetry_error(gt["test"]["x"], gt["test"]["z"], X, symmetry)
    residual = np.asarray(gt["test"]["residual"])
    return {
        "metrics": list(METRICS),
        "methods": methods,
        "correlation": correlation,
        "walk": walk,
        "ground_truth": {
            "symmetry_mean": gt_sym[0], "symmetry_max": gt_sym[1], "symmetric": symmetry is not None,
            "residual_median": float(np.median(residual)), "residual_p90": float(np.percentile(residual, 90)),
            "iterations_mean": float(np.mean(gt["test"]["iterations"])),
        },
    }  # fmt: skip
