# Shared helpers: config validation on load and the params each rule receives.
import json

from snakemake.exceptions import WorkflowError

from latentsim.baselines import BASELINES
from latentsim.config import (
    ConfigError,
    integrator_settings,
    scene_methods,
    validate_config,
)

try:
    validate_config(config, workflow.source_path("../schemas/config.schema.yaml"))
except ConfigError as e:
    raise WorkflowError(f"invalid config: {e}")

SCENES = sorted(config["scenes"])


INTEGRATOR_METHODS = ["self_supervised"] + sorted(config["integrator_variants"])
METHODS = INTEGRATOR_METHODS + list(BASELINES)


wildcard_constraints:
    scene="|".join(SCENES) if SCENES else "NO_SCENE",
    method="|".join(METHODS),


def canonical(obj):
    """Plain dicts with sorted keys: reordering a YAML mapping must not trigger a rerun."""
    return json.loads(json.dumps(obj, sort_keys=True))


def scene_cfg(*keys):
    """Input function: the named keys of the scene's config, as one plain dict."""

    def get(wildcards):
        sc = config["scenes"][wildcards.scene]
        return canonical({k: sc[k] for k in keys})

    return get


def mesh_sources():
    return canonical(config["meshes"])


def training_params(key):
    """Input function: a training stage's config plus seed and device."""

    def get(wildcards):
        sc = config["scenes"][wildcards.scene]
        return canonical(
            {"settings": sc[key], "seed": config["seed"], "device": config["device"]}
        )

    return get


def integrator_params(wildcards):
    """Input function: a method's integrator settings (scene's, with the variant's overrides)."""
    return canonical(
        {
            "settings": integrator_settings(config, wildcards.scene, wildcards.method),
            "seed": config["seed"],
            "device": config["device"],
        }
    )


def scene_rollouts(wildcards):
    """Input function: the rollout of every latent-integrator method of a scene."""
    return [
        f"results/rollout/{wildcards.scene}/{m}/rollout.h5"
        for m in scene_methods(config, wildcards.scene)
        + config["scenes"][wildcards.scene]["baselines"]
    ]


def gpu_count(wildcards):
    return 1 if config["device"] == "cuda" else 0


def all_targets():
    out = [
        f"results/rollout/{scene}/{method}/rollout.h5"
        for scene in SCENES
        for method in scene_methods(config, scene)
        + config["scenes"][scene]["baselines"]
    ]
    out += expand("results/evaluation/{scene}/metrics.csv", scene=SCENES)
    out += expand("results/evaluation/{scene}/frames.png", scene=SCENES)
    out += ["results/evaluation/summary.csv", "results/evaluation/summary.md"]
    return out
