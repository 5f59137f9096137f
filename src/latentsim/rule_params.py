"""The params each rule passes its stage script, for both papers: plain dicts with sorted keys, built from
the validated config.

A rule's params are part of what Snakemake compares to decide a rerun (``--rerun-triggers params``), so
each builder gives a rule only the config it depends on (editing one study reruns only that study of that
scene), and :func:`canonical` makes every dict plain with sorted keys (reordering a YAML mapping must not
rerun a rule).  ``workflow/rules/common.smk`` turns a job's wildcards into these calls.

- Li et al. 2025: :func:`scene_slice`, :func:`mesh_sources`, :func:`sim_params`, :func:`autoencoder_params`,
  :func:`integrator_params`, :func:`sweep_params`, :func:`sweep_prune_params`, and the conditioned
  integrator's :func:`condition_sim_params`, :func:`conditioned_autoencoder_params`,
  :func:`conditioned_integrator_params`;
- Neural Modes (Wang et al. 2024): :func:`nm_modes_params`, :func:`nm_train_params`,
  :func:`nm_ground_truth_params`, :func:`nm_study_params`.
"""

from __future__ import annotations

import json

from latentsim.config import (
    autoencoder_settings,
    conditioned_autoencoder_settings,
    conditioned_integrator_settings,
    conditions,
    integrator_settings,
    scene_seeds,
    sweep_point_settings,
)

MODE_KEYS = ("modes", "boundary", "normalization")  # all that the linear modes depend on
GROUND_TRUTH_KEYS = MODE_KEYS + ("box", "metric")  # ... and the ground truth
SET_KEYS = {"sheet": ("train_grid", "random_samples", "val_grid", "test_grid"), "energy": ("samples", "train", "validation")}
STUDY_SETS = ("epochs", "batch_size", "sampling", "grid")  # Neural Modes settings the sheet study sets itself


def canonical(obj):
    """Plain dicts with sorted keys: reordering a YAML mapping must not trigger a rerun."""
    return json.loads(json.dumps(obj, sort_keys=True))


# --------------------------------------------------------------------------------------------------
# Li et al. 2025
# --------------------------------------------------------------------------------------------------
def scene_slice(config: dict, scene: str, keys) -> dict:
    """The named keys of the scene's config, as one plain dict."""
    sc = config["scenes"][scene]
    return canonical({k: sc[k] for k in keys})


def mesh_sources(config: dict) -> dict:
    """The config's pinned mesh sources (``meshes``)."""
    return canonical(config["meshes"])


def sim_params(config: dict, scene: str) -> dict:
    """The scene's simulation settings (its contact block only where it has colliders, so that a scene
    without any keeps the params it had before contact existed; the mesh sources only where a collider is a mesh)."""
    sc = config["scenes"][scene]
    keys = ("model", "material", "dt", "gravity", "newton", "sequences")
    out = {k: sc[k] for k in keys}
    if sc["contact"]["colliders"]:
        out["contact"] = sc["contact"]
    if any(q["type"] == "mesh" for q in sc["contact"]["colliders"]):  # where a mesh collider's file is found
        out["mesh_sources"] = config["meshes"]
    return canonical(out)


def autoencoder_params(config: dict, scene: str, seed, method: str = "self_supervised") -> dict:
    """The autoencoder settings of the scene (or of the variant ``method``), seed and device."""
    return canonical({"settings": autoencoder_settings(config, scene, method), "seed": int(seed), "device": config["device"]})


def integrator_params(config: dict, scene: str, method: str, seed) -> dict:
    """A method's integrator settings (the scene's, with the variant's overrides), seed and device."""
    return canonical({"settings": integrator_settings(config, scene, method), "seed": int(seed), "device": config["device"]})


def sweep_params(config: dict, scene: str, latent_dim: int, size_index: int, seed) -> dict:
    """The full settings of one sizing-sweep point (latent size ``latent_dim``, the ``size_index``-th size)."""
    sc = config["scenes"][scene]
    return canonical(
        {
            **sweep_point_settings(config, scene, latent_dim, size_index),
            "rollout": sc["rollout"],
            "stress": sc["sweep"]["stress"],
            "seed": int(seed),
            "device": config["device"],
        }
    )


def earlier_seeds(config: dict, scene: str, seed) -> list[int]:
    """The seeds of the scene that run before ``seed`` (none for the first, or with ``sweep.prune`` off)."""
    seeds = scene_seeds(config, scene)
    if not config["scenes"][scene]["sweep"]["prune"]:
        return []
    return seeds[: seeds.index(int(seed))]


def sweep_prune_params(config: dict, scene: str, seed) -> dict:
    """What decides whether a sweep point's earlier seeds leave it a chance to pass; none for a seed that runs
    whatever the others measured."""
    if not earlier_seeds(config, scene, seed):
        return {}
    sw = config["scenes"][scene]["sweep"]
    return {"tolerance": sw["tolerance"], "pass_fraction": sw["pass_fraction"], "seeds": len(scene_seeds(config, scene))}


def condition_sim_params(config: dict, scene: str, condition: str) -> dict:
    """The scene's simulation settings and one condition of it (time step, modulus, split)."""
    return canonical({"sim": sim_params(config, scene), "condition": conditions(config, scene)[condition]})


def conditioned_autoencoder_params(config: dict, scene: str, seed) -> dict:
    """The conditioned scene's autoencoder settings, seed and device."""
    return canonical({"settings": conditioned_autoencoder_settings(config, scene), "seed": int(seed), "device": config["device"]})


def conditioned_integrator_params(config: dict, scene: str, model: str, seed) -> dict:
    """The settings, seed and device of the conditioned integrator (``model`` conditioned: the box) or of the
    reference at one test condition (``model`` that condition's name: the point)."""
    c = config["scenes"][scene]["conditioning"]
    if model == "conditioned":
        box = {"time_step": c["time_step"], "youngs_modulus": c["youngs_modulus"], "time_step_weight_power": c["time_step_weight_power"]}
    else:  # one point, where the loss's weight (h / h_0)^p is one constant factor
        q = conditions(config, scene)[model]
        box = {"time_step": [q["time_step"]] * 2, "youngs_modulus": [q["youngs_modulus"]] * 2}
    settings = conditioned_integrator_settings(config, scene, model)
    return canonical({"settings": settings, "seed": int(seed), "device": config["device"], "conditioning": box})


# --------------------------------------------------------------------------------------------------
# Neural Modes (Wang et al. 2024)
# --------------------------------------------------------------------------------------------------
def nm_train_params(config: dict, scene: str) -> dict:
    """The params of ``nm_train``: the scene's model, material and whole neural_modes block."""
    sc = config["scenes"][scene]
    return canonical({"model": sc["model"], "material": sc["material"], "neural_modes": sc["neural_modes"]})


def nm_modes_params(config: dict, scene: str) -> dict:
    """The params of ``nm_linear_modes``: model, material and the mode keys of the neural_modes block."""
    sc = config["scenes"][scene]
    return canonical({"model": sc["model"], "material": sc["material"], "neural_modes": {k: sc["neural_modes"][k] for k in MODE_KEYS}})


def nm_ground_truth_params(config: dict, scene: str, study: str) -> dict:
    """The params of ``nm_ground_truth``: what the sample sets and Eq. 9 depend on, nothing of any training."""
    sc = config["scenes"][scene]
    st = sc["nm_study"][study]
    return canonical(
        {
            "model": sc["model"], "material": sc["material"], "neural_modes": {k: sc["neural_modes"][k] for k in GROUND_TRUTH_KEYS},
            "sets": {k: st[k] for k in SET_KEYS[study]}, "max_iterations": st["gt_max_iterations"], "seed": scene_seeds(config, scene)[0],
        }
    )  # fmt: skip


def nm_study_params(config: dict, scene: str, study: str, seed: int | None = None) -> dict:
    """The params of a study's rule: its ``nm_study`` block, the seed (default: the scene's first; the sheet
    study runs once per seed of the scene), and what else it reads of the scene."""
    sc = config["scenes"][scene]
    nmc = sc["neural_modes"]
    out = {"study": sc["nm_study"][study], "seed": scene_seeds(config, scene)[0] if seed is None else int(seed)}
    if study == "sheet":
        out.update(model=sc["model"], material=sc["material"], neural_modes={k: v for k, v in nmc.items() if k not in STUDY_SETS})
    elif study == "energy":
        out.update(model=sc["model"], material=sc["material"], widths=nmc["widths"])
    elif study == "aspect":  # its own modes, widths and sampling; the scene's map and loss settings
        out.update(model=sc["model"], material=sc["material"], neural_modes={k: v for k, v in nmc.items() if k not in STUDY_SETS + ("modes", "widths")})
    else:
        out.update(box=nmc["box"])
    return canonical(out)
