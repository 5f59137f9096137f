"""Learning stages of Li et al. 2025: autoencoder, latent integrator, rollout.

Each function reads the simulator's ``trajectories.h5`` (and earlier stage
outputs), calls :mod:`latentsim.latent`, and writes its artefacts atomically.
"""

from __future__ import annotations

import logging
import time

import h5py
import numpy as np
import torch

from . import latent, stability
from .evaluate import bbox_diagonal
from .io import atomic_h5, require, write_dataset
from .scene import potential_from_artefact

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


def coordinates_for(f) -> latent.RelativeCoordinates:
    """Root-relative coordinates for rods, Dirichlet-mean-relative otherwise (Li et al. 3.2)."""
    n = f["rest_positions"].shape[0]
    if str(f.attrs["model"]) == "rods":
        return latent.RelativeCoordinates(n, f["dirichlet"][()], mode="roots", root_of=f["root_of"][()])
    return latent.RelativeCoordinates(n, f["dirichlet"][()], mode="mean")


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
    with h5py.File(trajectories, "r") as f:
        coords = coordinates_for(f)
        train = load_sequences(f, "train")
        every = load_sequences(f)
        diag = bbox_diagonal(f["rest_positions"][()])
    U = torch.cat([coords.encode(torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])) for s in train.values()])
    cfg = dict(settings)
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
        coords = coordinates_for(f)
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


def time_latent_step(integ, ae, coords, z1, z0, p, xD, repeats: int) -> dict:
    """Median wall time [ms] of one latent step: integration, decoding, total."""
    args = (z1[None], z0[None], p[None], p[None], p[None])
    xD = xD[None]
    ti, td = [], []
    with torch.inference_mode():
        for _ in range(max(repeats, 1) + 5):
            t0 = time.perf_counter()
            z = integ(*args)
            t1 = time.perf_counter()
            latent.decode_latents(ae, coords, z, xD)
            t2 = time.perf_counter()
            ti.append(t1 - t0)
            td.append(t2 - t1)
    ti, td = np.asarray(ti[5:]) * 1e3, np.asarray(td[5:]) * 1e3
    return {"integrate_ms": float(np.median(ti)), "decode_ms": float(np.median(td)), "step_ms": float(np.median(ti + td))}


def rollout_scene(trajectories, ae_path, integrator_path, settings: dict, out, method: str = "self_supervised"):
    """Autoregressive rollout of every test sequence, in the trajectory layout.

    ``method`` names the integrator (self_supervised or a config variant) in
    the file's ``method`` attribute; ``mode`` records its loss.
    """
    ae = latent.load_autoencoder(ae_path)
    integ = latent.load_integrator(integrator_path)
    extra = torch.load(integrator_path, map_location="cpu", weights_only=True)["extra"]
    mode = extra.get("mode", "self_supervised")
    ae_extra = torch.load(ae_path, map_location="cpu", weights_only=True)["extra"]
    with h5py.File(trajectories, "r") as f:
        coords = coordinates_for(f)
        tests = load_sequences(f, "test")
        train_frames = max(len(s["positions"]) for s in load_sequences(f, "train").values())
        rest = f["rest_positions"][()]
        potential = potential_from_artefact(f)
        root = {k: f[k][()] for k in ("rest_positions", "masses", "dirichlet", "edges", "triangles", "tets", "root_of") if k in f}
        attrs = {k: f.attrs[k] for k in ("model", "dt", "gravity", "scene")}
    with atomic_h5(out, config=settings) as g:
        for k, v in attrs.items():
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
            timing = time_latent_step(integ, ae, coords, z01[1], z01[0], torch.as_tensor(s["bc"][-1], dtype=torch.float32), xD[-1], settings["timing_repeats"])
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
            x = torch.as_tensor(s["positions"])
            xD = torch.as_tensor(s["dirichlet_positions"])
            z = latent.encode_positions(ae, coords, x, xD)
            conditions = stability.stress_conditions(
                s["bc"], rest[root["dirichlet"]], float(attrs["dt"]), train_frames,
                factors=st.get("speed_factors", stability.DEFAULT_FACTORS), long_factor=int(st.get("long_factor", 10)),
                perturbation=float(st.get("perturbation", 0.5)),
            )
            grp = g.create_group("stability", track_order=True)
            grp.attrs["sequence"] = name
            for c in conditions:
                r = stability.survive_latent(
                    integ, ae, coords, z[0], z[0], c, root["dirichlet"], bbox_diagonal(rest), float(settings["max_extent"]),
                    latent_std=z.std(0), seed=0,
                )
                h = grp.create_group(c.name)
                for k in ("frames", "survived", "dirichlet_error_end"):
                    h.attrs[k] = r[k]
                h.attrs["perturbation"] = c.perturbation
                write_dataset(h, "dirichlet_error", r["dirichlet_error"])
                log.info("stability %s: survived %d of %d frames, Dirichlet error at the end %.3e", c.name, r["survived"], r["frames"], r["dirichlet_error_end"])
