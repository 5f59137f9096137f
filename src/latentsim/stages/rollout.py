"""Stage of rule ``rollout`` (workflow/rules/rollout.smk): the autoregressive rollout of one
latent-integrator method on every test sequence of a scene (Li et al. 2025, sec. 3.3), in the
trajectory layout, with the deployable runtime exported and one latent step timed beside
full-space Newton frames (same-run speed-ups, Table 2), and the stress conditions of
:mod:`latentsim.latent.stability`.
"""

from __future__ import annotations

import logging
import time

import torch

from latentsim import runtime
from latentsim.config import with_defaults
from latentsim.io import atomic_h5, open_artefact, write_dataset
from latentsim.latent.autoencoder import encode_positions
from latentsim.latent.data import load_sequences
from latentsim.latent.integrator import boundary_inputs
from latentsim.latent.projection import ContactProjection
from latentsim.latent.rollout import rollout
from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder, load_extra, load_integrator
from latentsim.latent.stability import stress_test
from latentsim.latent.subspaces import DecoderSubspace
from latentsim.latent.timing import EagerStepper, rigid_frame_steppers, time_full_space, time_jvps, time_steppers
from latentsim.runtime import compiled as runtime_compiled
from latentsim.scene import contact_from_artefact, potential_from_artefact

log = logging.getLogger(__name__)

SCENE_ARRAYS = ("rest_positions", "masses", "dirichlet", "edges", "triangles", "tets", "root_of")
SCENE_ATTRS = ("model", "dt", "gravity", "scene")


def rollout_scene(trajectories, ae_path, integrator_path, settings: dict, out, method: str = "self_supervised", runtime_paths=None,
                  seed: int = -1):
    """Autoregressive rollout of every test sequence, in the trajectory layout.

    ``settings``: the scene's ``rollout`` block (keys absent take the schema's defaults), which
    ``out`` records as its config, with ``seed`` (the seed the models were trained with).  ``method`` names the integrator (self_supervised or a config
    variant) in the file's ``method`` attribute; ``mode`` records its loss.
    ``runtime_paths``: (``.npz``, ``.pt``) files to export the deployable
    runtime to (:mod:`latentsim.runtime`): the ``.npz`` holds the encoder too (a user encodes a new
    motion's first two frames with it, :func:`latentsim.runtime.load`), the ``.pt`` the step alone.  One latent step is timed with the
    NumPy runtime, the compiled one (:mod:`latentsim.runtime.compiled`, where
    numba imports), its `torch.export` program and eager PyTorch, and a few full-space Newton
    frames in the same process, so the speed-up is a same-run ratio.
    """
    cfg = with_defaults("rollout", settings, "rollout_scene")
    ae, integ = load_autoencoder(ae_path), load_integrator(integrator_path)
    extra, ae_extra = load_extra(integrator_path), load_extra(ae_path)
    scene = _read_scene(trajectories, ae_path, cfg)
    steppers = _steppers(ae, integ, scene["coords"], runtime_paths)
    scene["projection"] = _projection(ae, scene, cfg["contact_projection"], trajectories)
    with atomic_h5(out, config=settings, seed=seed) as g:
        for k, v in {**scene["attrs"], **scene["full"]}.items():
            g.attrs[k] = v
        g.attrs["method"] = method
        g.attrs["mode"] = extra.get("mode", "self_supervised")
        g.attrs["integrator_train_seconds"] = float(extra.get("train_seconds", float("nan")))
        g.attrs["autoencoder_train_seconds"] = float(ae_extra.get("train_seconds", float("nan")))
        for k, v in scene["arrays"].items():
            write_dataset(g, k, v)
        grp = g.create_group("sequences", track_order=True)
        for name, s in scene["tests"].items():
            _roll_out(grp.create_group(name), name, s, integ, ae, scene, steppers, method, cfg)
        if cfg["stability"]["enabled"] and scene["tests"]:
            _stress(g.create_group("stability", track_order=True), integ, ae, scene, cfg)


def _read_scene(trajectories, ae_path, cfg: dict) -> dict:
    """What the rollout needs of a scene's ``trajectories.h5``: ``coords`` (those the autoencoder at
    ``ae_path`` records), the ``tests``
    sequences, ``train_frames`` (the longest training sequence), the ``potential`` and its
    ``contact`` barrier (None without colliders), the scene's
    ``arrays`` and ``attrs`` (copied to the output) and ``full``, the full-space timing."""
    with open_artefact(trajectories) as f:
        tests = load_sequences(f, "test")
        return {
            "coords": autoencoder_coordinates(f, ae_path),
            "tests": tests,
            "train_frames": max(len(s["positions"]) for s in load_sequences(f, "train").values()),
            "potential": potential_from_artefact(f),
            "contact": contact_from_artefact(f),
            "arrays": {k: f[k][()] for k in SCENE_ARRAYS if k in f},
            "attrs": {k: f.attrs[k] for k in SCENE_ATTRS},
            "full": time_full_space(f, next(iter(tests)), int(cfg["full_frames_timed"])) if tests else {},
        }


def _projection(ae, scene: dict, settings: dict, trajectories) -> ContactProjection | None:
    """The contact projection of the rollouts' frames (``rollout.contact_projection``), or None where not enabled."""
    if not settings["enabled"]:
        return None
    if scene["contact"] is None:
        raise ValueError(f"{trajectories}: rollout.contact_projection.enabled, but the scene has no colliders (its config's contact block)")
    pot = scene["potential"]
    return ContactProjection(DecoderSubspace(ae, scene["coords"]), scene["contact"], pot.masses.numpy(), float(pot.dt), settings)


def _steppers(ae, integ, coords, runtime_paths) -> dict:
    """The steppers to time: eager PyTorch, and with ``runtime_paths`` the runtime exported there
    and read back (NumPy, compiled where numba imports) and its ``torch.export`` program."""
    steppers = {"eager": EagerStepper(ae, integ, coords)}
    if runtime_paths is not None:
        npz, pt = runtime_paths
        runtime.export_runtime(ae, integ, coords, npz)
        runtime.export_runtime(ae, integ, coords, pt)
        steppers.update(runtime_compiled.deployable_steppers(runtime.read_runtime(npz)))  # numpy, compiled: from the file
        steppers["torch_export"] = runtime.ExportedStepper(runtime.read_runtime(npz))  # the torch.export programs of the step
    return rigid_frame_steppers(steppers, coords)


def _roll_out(h, name: str, s: dict, integ, ae, scene: dict, steppers: dict, method: str, cfg: dict) -> None:
    """Roll out test sequence ``s`` from its first two frames, time one step, write group ``h``."""
    coords = scene["coords"]
    x, xD = torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])
    z01 = encode_positions(ae, coords, x[:2], xD[:2])
    projection = scene["projection"]
    fed = projection.step(s["dirichlet_positions"]) if projection is not None and projection.feedback else None
    t0 = time.perf_counter()
    res = rollout(integ, ae, coords, z01[0], z01[1], torch.as_tensor(s["bc"]), xD, potential=scene["potential"], max_extent=cfg["max_extent"],
                  rest_positions=torch.as_tensor(scene["arrays"]["rest_positions"]), correct=fed)  # fmt: skip
    wall = time.perf_counter() - t0
    p_last = boundary_inputs(s["bc"], s["dirichlet_positions"], integ.origin, coords)[-1]
    timing = time_steppers(steppers, z01[1], z01[0], p_last, s["dirichlet_positions"][-1], cfg["timing_repeats"])
    if "numpy" in steppers:
        timing.update(time_jvps(ae, steppers["numpy"], coords, z01[1], cfg["timing_repeats"]))
    if projection is not None:  # the frames written are projected; a frame's time includes its share of the projections
        last = len(x) - 1 if res["diverged_frame"] < 0 else int(res["diverged_frame"])
        if fed is not None:  # projected as it went: the state is the projected one
            proj = {"projected": fed.projected, "iterations": fed.iterations, "seconds": fed.seconds}
            write_dataset(h, "predicted_depth", fed.own_depth)
        else:
            unprojected = res["positions"].numpy()
            proj = projection.frames(res["latents"].numpy(), unprojected, s["dirichlet_positions"], last)
            res["positions"] = torch.as_tensor(proj["positions"])
            write_dataset(h, "unprojected_positions", unprojected)
        timing["projection_ms"] = 1e3 * proj["seconds"] / max(last + 1, 1)
        timing["step_ms"] += timing["projection_ms"]
        h.attrs["projected_frames"] = int(proj["projected"].sum())
        h.attrs["projection_fed_back"] = fed is not None
        write_dataset(h, "projected", proj["projected"])
        write_dataset(h, "projection_iterations", proj["iterations"])
        log.info("rollout %s: %d frames projected out of the colliders, %.3f ms a frame", name, int(proj["projected"].sum()), timing["projection_ms"])
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


def _stress(grp, integ, ae, scene: dict, cfg: dict) -> None:
    """The stress conditions of ``cfg["stability"]`` on the first test sequence, one group each (their frames
    projected out of the colliders as the test rollouts' are, where the rollout projects)."""
    name, s = next(iter(scene["tests"].items()))
    grp.attrs["sequence"] = name
    arrays = scene["arrays"]
    conditions = stress_test(integ, ae, scene["coords"], s, arrays["rest_positions"], arrays["dirichlet"], float(scene["attrs"]["dt"]),
                             scene["train_frames"], cfg["stability"], float(cfg["max_extent"]), contact=scene["contact"],
                             projection=scene["projection"])  # fmt: skip
    for c, r in conditions:
        h = grp.create_group(c.name)
        for k in ("frames", "survived", "dirichlet_error_end", "max_penetration", "max_penetration_own", "projected_frames"):
            if k in r:
                h.attrs[k] = r[k]
        h.attrs["perturbation"] = c.perturbation
        write_dataset(h, "dirichlet_error", r["dirichlet_error"])
        log.info("stability %s: survived %d of %d frames, Dirichlet error at the end %.3e", c.name, r["survived"], r["frames"], r["dirichlet_error_end"])
