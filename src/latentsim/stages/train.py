"""Learning stages of Li et al. 2025: autoencoder, latent integrator, rollout.

Each function reads the simulator's ``trajectories.h5`` (and earlier stage
outputs), calls :mod:`latentsim.latent`, and writes its artefacts atomically.
"""

from __future__ import annotations

import logging
import os
import time

import h5py
import numpy as np
import torch

from latentsim import latent
from latentsim import runtime
from latentsim.runtime import compiled as runtime_compiled
from latentsim.latent import stability
from latentsim.report.evaluate import bbox_diagonal
from latentsim.io import atomic_h5, require, write_dataset
from latentsim.scene import potential_from_artefact
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

log = logging.getLogger(__name__)


def load_sequences(f, split=None) -> dict:
    """{name: {positions, dirichlet_positions, bc, split}} of one split (or all)."""
    out = {}
    for name, g in require(f, "sequences").items():
        if split is not None and g.attrs["split"] != split:
            continue
        out[name] = {k: g[k][()] for k in ("positions", "dirichlet_positions", "bc")}
        out[name]["split"] = str(g.attrs["split"])
    if not out:
        raise ValueError(f"{f.filename}: no sequence with split '{split}'")
    return out


def coordinates_for(f, mode: str | None = None) -> latent.RelativeCoordinates:
    """The relative coordinates of a scene's trajectories ``f`` (Li et al. 3.2).

    ``mode`` None (the config's autoencoder ``coordinates`` unset): root-relative for rods,
    Dirichlet-mean-relative otherwise; or any mode of ``latent.RelativeCoordinates``.
    """
    n = f["rest_positions"].shape[0]
    if mode is None:
        mode = "roots" if str(f.attrs["model"]) == "rods" else "mean"
    if mode == "roots":
        if "root_of" not in f:
            raise ValueError(f"{f.filename}: 'roots' coordinates need the rods' root_of array")
        return latent.RelativeCoordinates(n, f["dirichlet"][()], mode="roots", root_of=f["root_of"][()])
    return latent.RelativeCoordinates(n, f["dirichlet"][()], mode=mode)


def autoencoder_coordinates(f, ae_path) -> latent.RelativeCoordinates:
    """The coordinates the autoencoder saved at ``ae_path`` was trained in (its file records them)."""
    extra = torch.load(ae_path, map_location="cpu", weights_only=True).get("extra", {})
    return coordinates_for(f, extra.get("coordinates"))


def reconstruction_errors(ae, coords, seq: dict, diag: float) -> tuple[float, float]:
    """Mean and max vertex error / bbox diagonal of encode-decode over a sequence."""
    x = torch.as_tensor(seq["positions"])
    xD = torch.as_tensor(seq["dirichlet_positions"])
    with torch.no_grad():
        z = latent.encode_positions(ae, coords, x, xD)
        xr = latent.decode_latents(ae, coords, z, xD).cpu().numpy()
    d = np.linalg.norm(xr - seq["positions"], axis=-1) / diag
    return float(d.mean()), float(d.max())


def train_autoencoder(trajectories, settings: dict, seed: int, device: str, out_model, out_latents, progress=False):
    """Fit the autoencoder on every training frame; encode every sequence."""
    cfg = dict(settings)
    with h5py.File(trajectories, "r") as f:
        coords = coordinates_for(f, cfg.pop("coordinates", None))
        train = load_sequences(f, "train")
        every = load_sequences(f)
        diag = bbox_diagonal(f["rest_positions"][()])
    U = torch.cat([coords.encode(torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])) for s in train.values()])
    cfg["pca_dim"] = cfg.get("pca_dim") or None
    t0 = time.perf_counter()
    ae, history = latent.fit_autoencoder(U.to(torch.float32), cfg, seed=seed, device=device, progress=progress)
    seconds = time.perf_counter() - t0
    ae = ae.cpu()
    log.info(
        "autoencoder: %d frames of %d dims -> %d latents, %.1f s, mse %.3e (PCA start) -> %.3e (kept: %s)",
        U.shape[0], U.shape[1], cfg["latent_dim"], seconds, history["mse_initial"], history["mse_final"], history["kept"],
    )
    latent.save_module(out_model, ae, extra={"coordinates": coords.mode, "train_seconds": seconds})
    with atomic_h5(out_latents, config=settings, seed=seed) as g:
        g.attrs["train_seconds"] = seconds
        g.attrs["kept"] = history["kept"]
        write_dataset(g, "loss", np.asarray(history["loss"], dtype=np.float64))
        grp = g.create_group("sequences", track_order=True)
        for name, s in every.items():
            mean_e, max_e = reconstruction_errors(ae, coords, s, diag)
            z = latent.encode_positions(ae, coords, torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"]))
            h = grp.create_group(name)
            h.attrs["split"] = s["split"]
            h.attrs["mean_error"], h.attrs["max_error"] = mean_e, max_e
            write_dataset(h, "latents", z.numpy())
            log.info("reconstruction %s (%s): mean %.3e, max %.3e of the bbox diagonal", name, s["split"], mean_e, max_e)


def train_integrator(trajectories, ae_path, settings: dict, seed: int, device: str, out_model, out_history, checkpoint=None, progress=False):
    """Fit the latent integrator (self-supervised or supervised) on the training sequences."""
    with h5py.File(trajectories, "r") as f:
        coords = autoencoder_coordinates(f, ae_path)
        train = load_sequences(f, "train")
        potential = potential_from_artefact(f)
    ae = latent.load_autoencoder(ae_path)
    t0 = time.perf_counter()
    integ, history = latent.fit_integrator(
        ae, coords, potential, list(train.values()), dict(settings), seed=seed, device=device, progress=progress, checkpoint_path=checkpoint
    )
    seconds = time.perf_counter() - t0
    log.info("integrator (%s): %d triplets, %.1f s, final loss %.4e", settings.get("mode"), history["n_triplets"], seconds, history["loss"][-1])
    latent.save_module(out_model, integ.cpu(), extra={"mode": settings.get("mode", "self_supervised"), "train_seconds": seconds})
    with atomic_h5(out_history, config=settings, seed=seed) as g:
        g.attrs["train_seconds"] = seconds
        g.attrs["start_epoch"] = int(history["start_epoch"])
        write_dataset(g, "loss", np.asarray(history["loss"], dtype=np.float64))
        write_dataset(g, "latent_mse", np.asarray(history["latent_mse"], dtype=np.float64))
    # the checkpoint serves a killed training only: left behind, a forced rerun of the same training would
    # resume at its last epoch and record a training time of a second
    if checkpoint is not None and os.path.exists(checkpoint):
        os.remove(checkpoint)


def time_steppers(steppers: dict, z1, z0, p, xD, repeats: int) -> dict:
    """Median ms of one latent step with each stepper (``{name}_step_ms`` etc.).

    ``step_ms``, ``integrate_ms`` and ``decode_ms`` are those of the fastest
    stepper (whose name is ``runtime``), the deployable path.
    """
    out: dict = {}
    for name, st in steppers.items():
        r = runtime.time_step(st, z1, z0, p, p, p, xD, repeats=repeats)  # each stepper converts the frame itself
        for k, v in r.items():
            out[f"{name}_{k}"] = v
    best = min(steppers, key=lambda n: out[f"{n}_step_ms"])
    out.update(step_ms=out[f"{best}_step_ms"], integrate_ms=out[f"{best}_integrate_ms"], decode_ms=out[f"{best}_decode_ms"])
    out["runtime"] = best
    return out


def time_jvps(ae, stepper, coords, z, repeats: int) -> dict:
    """Li et al. Table 2: one decoded vertex's Jacobian-vector product w.r.t. the latent, timed two ways.

    ``jvp_torch_ms``: ``torch.func.jvp`` of the PyTorch decoder restricted to
    the vertex (as the paper did); ``jvp_forward_ms``: the hand-written forward
    mode of the NumPy runtime.  The vertex is the free vertex farthest down the
    encoded vector (any free vertex costs the same).
    """
    v = torch.ones_like(torch.as_tensor(z, dtype=torch.float32))
    free = np.setdiff1d(np.arange(coords.n), coords.dirichlet.numpy())
    vertex = int(free[-1])
    row = stepper._row_of_vertex(vertex)
    zt = torch.as_tensor(z, dtype=torch.float32)
    zn, vn = np.asarray(z, dtype=np.float32), v.numpy()
    return {
        "jvp_torch_ms": runtime.time_jvp(lambda: runtime.jvp_vertex_torch(ae, zt, v, row), repeats),
        "jvp_forward_ms": runtime.time_jvp(lambda: stepper.jvp_vertex(zn, vn, vertex), repeats),
    }


def time_full_space(f, sequence: str, frames: int = 20) -> dict:
    """Mean wall time [ms] of full-space Newton frames, timed now (for same-run ratios).

    Steps ``frames`` frames spread evenly over ``sequence`` of an open
    trajectories.h5, each from the stored ground-truth states, with the
    simulator's own solver settings (tolerance from the file).  Spread and
    averaged like the simulator's own ms/frame: a sequence that settles (the
    cantilever's sag) has cheap frames at rest and dear ones while it moves,
    and a window in its middle would see only one kind.
    """
    pot = potential_from_artefact(f, free_only=True)
    tol = float(f.attrs.get("newton_tolerance", 1e-6))
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=tol))
    g = require(f, "sequences")[sequence]
    x, xD = g["positions"], g["dirichlet_positions"]
    T = x.shape[0]
    if T < 3:
        raise ValueError(f"sequence {sequence}: {T} frames, need at least 3 to time a full-space step")
    solver.step(x[1], x[0], xD[2])  # warm-up: first-call costs (JIT, caches)
    ms, iters = [], []
    for t in np.unique(np.linspace(2, T - 1, max(1, frames)).round().astype(int)):
        start = time.perf_counter()
        _, info = solver.step(x[t - 1], x[t - 2], xD[t])
        ms.append(1e3 * (time.perf_counter() - start))
        iters.append(info.iterations)
    return {"full_ms": float(np.mean(ms)), "full_iterations": float(np.mean(iters)), "full_frames_timed": len(ms)}


def rollout_scene(trajectories, ae_path, integrator_path, settings: dict, out, method: str = "self_supervised", runtime_paths=None):
    """Autoregressive rollout of every test sequence, in the trajectory layout.

    ``method`` names the integrator (self_supervised or a config variant) in
    the file's ``method`` attribute; ``mode`` records its loss.
    ``runtime_paths``: (``.npz``, ``.pt``) files to export the deployable
    runtime to (:mod:`latentsim.runtime`).  One latent step is timed with the
    NumPy runtime, the compiled one (:mod:`latentsim.runtime.compiled`, where
    numba imports), TorchScript and eager PyTorch, and a few full-space Newton
    frames in the same process, so the speed-up is a same-run ratio.
    """
    ae = latent.load_autoencoder(ae_path)
    integ = latent.load_integrator(integrator_path)
    extra = torch.load(integrator_path, map_location="cpu", weights_only=True)["extra"]
    mode = extra.get("mode", "self_supervised")
    ae_extra = torch.load(ae_path, map_location="cpu", weights_only=True)["extra"]
    with h5py.File(trajectories, "r") as f:
        coords = coordinates_for(f, ae_extra.get("coordinates"))
        tests = load_sequences(f, "test")
        train_frames = max(len(s["positions"]) for s in load_sequences(f, "train").values())
        rest = f["rest_positions"][()]
        potential = potential_from_artefact(f)
        root = {k: f[k][()] for k in ("rest_positions", "masses", "dirichlet", "edges", "triangles", "tets", "root_of") if k in f}
        attrs = {k: f.attrs[k] for k in ("model", "dt", "gravity", "scene")}
        full = time_full_space(f, next(iter(tests)), int(settings.get("full_frames_timed", 20))) if tests else {}
    steppers = {"eager": runtime.EagerStepper(ae, integ, coords)}
    if runtime_paths is not None:
        npz, pt = runtime_paths
        runtime.export_runtime(ae, integ, coords, npz)
        runtime.export_runtime(ae, integ, coords, pt)
        steppers.update(runtime_compiled.deployable_steppers(runtime._read_npz(npz)))  # numpy, compiled: from the file
        steppers["torchscript"] = runtime.ExportedStepper(runtime.read_runtime(npz))  # the torch.export programs of the step
    with atomic_h5(out, config=settings) as g:
        for k, v in attrs.items():
            g.attrs[k] = v
        for k, v in full.items():
            g.attrs[k] = v
        g.attrs["method"] = method
        g.attrs["mode"] = mode
        g.attrs["integrator_train_seconds"] = float(extra.get("train_seconds", float("nan")))
        g.attrs["autoencoder_train_seconds"] = float(ae_extra.get("train_seconds", float("nan")))
        for k, v in root.items():
            write_dataset(g, k, v)
        grp = g.create_group("sequences", track_order=True)
        for name, s in tests.items():
            x = torch.as_tensor(s["positions"])
            xD = torch.as_tensor(s["dirichlet_positions"])
            z01 = latent.encode_positions(ae, coords, x[:2], xD[:2])
            t0 = time.perf_counter()
            res = latent.rollout(
                integ, ae, coords, z01[0], z01[1], torch.as_tensor(s["bc"]), xD,
                potential=potential, max_extent=settings["max_extent"], rest_positions=torch.as_tensor(rest),
            )
            wall = time.perf_counter() - t0
            timing = time_steppers(steppers, z01[1], z01[0], s["bc"][-1], s["dirichlet_positions"][-1], settings["timing_repeats"])
            if "numpy" in steppers:
                timing.update(time_jvps(ae, steppers["numpy"], coords, z01[1], settings["timing_repeats"]))
            h = grp.create_group(name)
            h.attrs["split"] = "test"
            h.attrs["method"] = method
            h.attrs["diverged_frame"] = int(res["diverged_frame"])
            h.attrs["rollout_seconds"] = wall
            for k, v in timing.items():
                h.attrs[k] = v
            write_dataset(h, "positions", res["positions"].numpy())
            write_dataset(h, "latents", res["latents"].numpy())
            write_dataset(h, "dirichlet_positions", s["dirichlet_positions"])
            write_dataset(h, "bc", s["bc"])
            write_dataset(h, "kinetic_energy", res["kinetic_energy"].numpy())
            log.info("rollout %s: %d frames, diverged at %d, %.3f ms/step (%s)", name, len(x), res["diverged_frame"], timing["step_ms"], timing)
        st = settings.get("stability", {})
        if st.get("enabled", True) and tests:
            name, s = next(iter(tests.items()))
            grp = g.create_group("stability", track_order=True)
            grp.attrs["sequence"] = name
            conditions = stability.stress_test(integ, ae, coords, s, rest, root["dirichlet"], float(attrs["dt"]), train_frames,
                                               st, float(settings["max_extent"]))  # fmt: skip
            for c, r in conditions:
                h = grp.create_group(c.name)
                for k in ("frames", "survived", "dirichlet_error_end"):
                    h.attrs[k] = r[k]
                h.attrs["perturbation"] = c.perturbation
                write_dataset(h, "dirichlet_error", r["dirichlet_error"])
                log.info("stability %s: survived %d of %d frames, Dirichlet error at the end %.3e", c.name, r["survived"], r["frames"], r["dirichlet_error_end"])
