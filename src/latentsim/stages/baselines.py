"""Classical reduced-order baselines on the latent methods' test sequences.

Every baseline steps implicit Euler by minimising the scene's incremental
potential (the same :class:`~latentsim.physics.incremental_potential.IncrementalPotential`
as the full-space solver) over a subspace, with :mod:`latentsim.solve.reduced`:

- ``pca_reduced``: linear subspace of the principal components of the
  training frames (in the autoencoder's relative coordinates), as many as the
  latent dimension unless ``reduced.pca_dim`` says otherwise;
- ``modes_reduced``: linear subspace of the lowest vibration modes of the rest
  state (K e = omega^2 M e with the Dirichlet vertices fixed, sparse
  shift-invert), as many as ``pca_reduced`` takes, in the same relative
  coordinates (the Dirichlet set's motion carries the modes);
- ``fulton_reduced``: the autoencoder's decoder as the subspace map, the
  optimisation-based latent dynamics of Fulton et al. 2019;
- ``neural_modes_reduced``: the scene's Neural Modes (Wang et al. 2024; rule
  ``nm_train`` on the scene's ``neural_modes`` block) as the subspace map,
  ``x = X + l(q) + y(q)`` carried by the best rigid fit of the Dirichlet set
  (:class:`latentsim.neural_modes.dynamics.NeuralModesSubspace`); the subspace dynamics
  of their section 4.5 on the latent methods' test sequences;
- ``newton_1it``: the full-space solver stopped after one Newton iteration per
  frame (the cheap variant of the ground truth).

The reduced baselines evaluate every element unless ``reduced.cubature_tolerance``
is set: then, as Fulton et al. do, a cubature (:mod:`latentsim.solve.cubature`) is fitted
to the reduced elastic forces at the subspace's projections of the training
frames and replaces the elastic energy in the step.

Each writes a rollout file in the trajectory layout of
:func:`latentsim.stages.rollout.rollout_scene`, so :mod:`latentsim.stages.evaluate` reads all
methods alike.  A step that fails (non-finite values, a reduced Hessian that
is not positive definite, a line search that stalls) marks the frame as the
divergence instead of stopping the stage.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from latentsim import latent
from latentsim.labels import BASELINES
from latentsim.io import atomic_h5, open_artefact, write_dataset
from latentsim.neural_modes import load_neural_modes
from latentsim.neural_modes.dynamics import NeuralModesSubspace
from latentsim.scene import potential_from_artefact
from latentsim.solve import reduced
from latentsim.solve.cubature import check_supported, cubature_potential, fit_cubature
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonFailed, NewtonSettings
from latentsim.solve.modes import lowest_modes
from latentsim.latent.subspaces import DecoderSubspace, LinearSubspace
from latentsim.latent.data import load_sequences
from latentsim.latent.serialization import autoencoder_coordinates
from latentsim.latent.timing import time_full_space

log = logging.getLogger(__name__)

def newton_rollout(potential_free, x0, x1, dirichlet_positions, iterations: int = 1, tolerance: float = 1e-6) -> dict:
    """Full-space implicit Euler with at most ``iterations`` Newton iterations per frame (no convergence required).

    The cheap end of the full-space solver: each frame takes the best initial
    guess of :class:`~latentsim.solve.implicit_euler.ImplicitEuler` and ``iterations``
    line-searched Newton steps.  Returns the layout of
    :func:`latentsim.solve.reduced.reduced_rollout` (positions, step_ms, iterations,
    diverged_frame).
    """
    solver = ImplicitEuler(potential_free, NewtonSettings(tolerance=tolerance, max_iterations=int(iterations), accept_unconverged=True))
    xD = np.asarray(dirichlet_positions, dtype=np.float64)
    T = len(xD)
    X = np.full((T,) + np.shape(x0), np.nan)
    X[0], X[1] = x0, x1
    ms = np.full(T, np.nan)
    iters = np.zeros(T, dtype=np.int64)
    diverged = -1
    for t in range(2, T):
        t0 = time.perf_counter()
        try:
            x, info = solver.step(X[t - 1], X[t - 2], xD[t])
        except NewtonFailed:
            diverged = t
            break
        ms[t] = 1e3 * (time.perf_counter() - t0)
        iters[t] = info.iterations
        if not np.isfinite(x).all():
            diverged = t
            break
        X[t] = x
    return {"positions": X, "latents": np.zeros((T, 0)), "step_ms": ms, "iterations": iters, "diverged_frame": int(diverged)}


def make_subspace(method: str, ae, coords, train: dict, settings: dict, potential=None, rest_positions=None, neural_modes=None):
    """The subspace of a baseline (see the module docstring); ``modes_reduced`` needs the
    scene's potential and rest positions, ``neural_modes_reduced`` the potential and the path
    of the scene's trained Neural Modes."""
    r = int(settings.get("pca_dim") or ae.latent_dim)
    if method == "pca_reduced":
        X = np.concatenate([s["positions"] for s in train.values()])
        XD = np.concatenate([s["dirichlet_positions"] for s in train.values()])
        return LinearSubspace.from_frames(coords, X, XD, r)
    if method == "modes_reduced":
        return modes_subspace(coords, potential, rest_positions, r)
    if method == "fulton_reduced":
        return DecoderSubspace(ae, coords)
    if method == "neural_modes_reduced":
        if neural_modes is None:
            raise ValueError("neural_modes_reduced needs the scene's trained Neural Modes (rule nm_train; a neural_modes block in the scene)")
        model = load_neural_modes(neural_modes)
        D = potential.dirichlet.cpu().numpy()
        fixed = np.flatnonzero(model.mask.detach().numpy().reshape(-1, 3).min(1) == 0)
        if not np.array_equal(np.sort(fixed), np.sort(D)):
            raise ValueError(f"{neural_modes}: its fixed vertices ({len(fixed)}) are not the scene's Dirichlet set ({len(D)}); "
                             "train it with neural_modes.boundary: dirichlet")  # fmt: skip
        return NeuralModesSubspace(model, D)
    raise ValueError(f"unknown baseline {method!r}; known: {list(BASELINES)}")


def modes_subspace(coords, potential, rest_positions, r: int) -> LinearSubspace:
    """The r lowest vibration modes of the rest state as a :class:`~latentsim.latent.subspaces.LinearSubspace` of
    ``coords`` (zero on the Dirichlet vertices, which follow their prescribed motion)."""
    X = np.asarray(rest_positions, dtype=np.float64)
    _, V, free = lowest_modes(potential, r, X)
    full = np.zeros((X.size, r))
    full[free] = V
    return LinearSubspace.from_vectors(coords, X, potential.dirichlet.cpu().numpy(), full)


def fit_subspace_cubature(potential, subspace, train: dict, settings: dict):
    """Cubature of the scene's elastic term fitted at the subspace's projections of
    ``cubature_frames`` evenly spaced training frames (Fulton et al. fit theirs on training data)."""
    check_supported(potential)
    X = np.concatenate([s["positions"] for s in train.values()])
    XD = np.concatenate([s["dirichlet_positions"] for s in train.values()])
    pick = np.unique(np.linspace(0, len(X) - 1, int(settings.get("cubature_frames", 200))).round().astype(np.int64))
    q = np.stack([subspace.project(X[i], XD[i]) for i in pick])
    return fit_cubature(potential.terms, subspace, q, float(settings["cubature_tolerance"]), int(settings.get("cubature_max_elements", 1000)), xD=XD[pick])


def baseline_rollouts(trajectories, ae_path, method: str, settings: dict, out, progress: bool = False, neural_modes=None, seed: int = -1):
    """Roll out every test sequence of a scene with a reduced baseline.

    Parameters
    ----------
    trajectories : the simulator's ``trajectories.h5``.
    ae_path : the scene's autoencoder (coordinates, PCA frames' layout, decoder).
    method : one of ``labels.BASELINES``.
    settings : config ``reduced`` of the scene: ``method`` (newton | lbfgs; ``neural_modes_method``
        for ``neural_modes_reduced``), ``max_iterations``, ``tolerance``, ``pca_dim``.
    out : rollout file to write.
    neural_modes : the scene's trained Neural Modes (``neural_modes_reduced`` only).
    seed : the seed of the learned model it reduces with (``labels.SEEDED_BASELINES``), recorded in
        ``out``; -1 for the others, whose rollout no seed changes.
    """
    ae = latent.load_autoencoder(ae_path)
    with open_artefact(trajectories) as f:
        coords = autoencoder_coordinates(f, ae_path)
        train = load_sequences(f, "train")
        tests = load_sequences(f, "test")
        potential = potential_from_artefact(f)
        root = {k: f[k][()] for k in ("rest_positions", "masses", "dirichlet", "edges", "triangles", "tets", "root_of") if k in f}
        attrs = {k: f.attrs[k] for k in ("model", "dt", "gravity", "scene")}
        full = time_full_space(f, next(iter(tests))) if tests else {}
        potential_free = potential_from_artefact(f, free_only=True)
        tolerance = float(f.attrs.get("newton_tolerance", 1e-6))
    if method == "newton_1it":
        subspace, solver, cub = None, None, None
    else:
        subspace = make_subspace(method, ae, coords, train, settings, potential, root["rest_positions"], neural_modes)
        minimiser = settings.get("neural_modes_method", "lbfgs") if method == "neural_modes_reduced" else settings.get("method", "newton")
        rs = reduced.ReducedSettings(method=minimiser, max_iterations=int(settings.get("max_iterations", 50)), tolerance=float(settings.get("tolerance", 1e-6)))
        step_potential, cub = potential, None
        if float(settings.get("cubature_tolerance", 0.0)) > 0:
            cub = fit_subspace_cubature(potential, subspace, train, settings)
            step_potential = cubature_potential(potential, cub)
            log.info("%s: cubature of %d of %d elements, force error %.4f on the training poses (%.1f s)",
                     method, len(cub.index), cub.n_elements, cub.train_error, cub.fit_seconds)  # fmt: skip
        solver = reduced.ReducedImplicitEuler(subspace, step_potential, rs)
    with atomic_h5(out, config=settings, seed=seed) as g:
        for k, v in attrs.items():
            g.attrs[k] = v
        g.attrs["method"] = method
        g.attrs["mode"] = "reduced"
        g.attrs["subspace_dim"] = int(subspace.dim) if subspace is not None else 3 * len(root["rest_positions"])
        if subspace is not None and cub is not None:
            g.attrs["cubature_elements"] = len(cub.index)
            g.attrs["cubature_force_error"] = cub.train_error
            write_dataset(g, "cubature_index", cub.index)
            write_dataset(g, "cubature_weights", cub.weights)
        for k, v in full.items():
            g.attrs[k] = v
        for k, v in root.items():
            write_dataset(g, k, v)
        grp = g.create_group("sequences", track_order=True)
        for name, s in tests.items():
            x, xD = s["positions"], s["dirichlet_positions"]
            t0 = time.perf_counter()
            if subspace is None:
                res = newton_rollout(potential_free, x[0], x[1], xD, iterations=1, tolerance=tolerance)
            else:
                q0, q1 = subspace.project(x[0], xD[0]), subspace.project(x[1], xD[1])
                res = reduced.reduced_rollout(subspace, potential, q0, q1, xD, solver=solver)
            write_sequence(grp.create_group(name), name, method, s, res, time.perf_counter() - t0, potential)


def write_sequence(h, name: str, method: str, sequence: dict, res: dict, wall: float, potential) -> None:
    """One test sequence's baseline rollout ``res`` (the layout of ``reduced_rollout``) into the
    group h: its attributes (divergence, failure, timings, mean iterations), positions, latents,
    the prescribed motion, per-step times and iterations, and the kinetic energy of the frames."""
    x, xD = sequence["positions"], sequence["dirichlet_positions"]
    ms = res["step_ms"][np.isfinite(res["step_ms"])]
    step_ms = float(np.median(ms)) if len(ms) else float("nan")
    h.attrs["split"] = "test"
    h.attrs["method"] = method
    h.attrs["diverged_frame"] = int(res["diverged_frame"])
    h.attrs["failure"] = res.get("failure", "")  # why the step at diverged_frame failed
    h.attrs["rollout_seconds"] = wall
    h.attrs["step_ms"] = step_ms
    h.attrs["integrate_ms"] = step_ms
    h.attrs["decode_ms"] = 0.0
    h.attrs["mean_iterations"] = float(res["iterations"][2:].mean()) if len(x) > 2 else 0.0
    write_dataset(h, "positions", res["positions"])
    write_dataset(h, "latents", np.asarray(res["latents"], dtype=np.float32))
    write_dataset(h, "dirichlet_positions", xD)
    write_dataset(h, "bc", sequence["bc"])
    write_dataset(h, "step_ms", res["step_ms"])
    write_dataset(h, "iterations", res["iterations"])
    with torch.no_grad():
        X = torch.as_tensor(res["positions"])
        ke = np.full(len(x), np.nan)
        ke[1:] = potential.kinetic_energy(X[1:], X[:-1]).numpy()
    write_dataset(h, "kinetic_energy", ke)
    log.info("%s %s: %d frames, diverged at %d, median %.2f ms/step, %.1f iterations/step",
             method, name, len(x), res["diverged_frame"], step_ms, h.attrs["mean_iterations"])  # fmt: skip
    if res.get("failure"):
        log.warning("%s %s: the step to frame %d failed: %s", method, name, res["diverged_frame"], res["failure"])
