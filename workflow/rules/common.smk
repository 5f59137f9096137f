# Shared helpers: config validation on load and the params each rule receives.
import json

from snakemake.exceptions import WorkflowError

from latentsim.config import ConfigError, validate_config

try:
    validate_config(config, workflow.source_path("../schemas/config.schema.yaml"))
except ConfigError as e:
    raise WorkflowError(f"invalid config: {e}")

SCENES = sorted(config["scenes"])


wildcard_constraints:
    scene="|".join(SCENES) if SCENES else "NO_SCENE",


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


def gpu_count(wildcards):
    return 1 if config["device"] == "cuda" else 0


def progress():
    return bool(config["progress"])


def all_targets():
    out = expand("results/rollout/{scene}/rollout.h5", scene=SCENES)
    out += expand("results/evaluation/{scene}/metrics.csv", scene=SCENES)
    out += ["results/evaluation/summary.csv", "results/evaluation/summary.md"]
    return out
