"""The params the rules pass their stages (latentsim.rule_params): plain, sorted, and only what each rule reads."""

import copy
import json
from pathlib import Path

import pytest

from latentsim import rule_params as rp
from latentsim.config import load_config, scene_seeds

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def config():
    return load_config(ROOT / "config" / "config.yaml")


def _reversed(obj):
    """Every mapping in ``obj`` with its keys in reverse order (a YAML file written the other way round)."""
    if isinstance(obj, dict):
        return {k: _reversed(obj[k]) for k in reversed(list(obj))}
    if isinstance(obj, list):
        return [_reversed(v) for v in obj]
    return obj


def _every_param(config) -> dict:
    """Each builder's params for a Li et al. scene (with variants, colliders, a conditioning, a sweep) and a
    Neural Modes scene, as JSON text (key order included)."""
    out = {
        "slice": rp.scene_slice(config, "cantilever", ("model", "mesh", "dirichlet")),
        "meshes": rp.mesh_sources(config),
        "sim": rp.sim_params(config, "cantilever_floor"),
        "autoencoder": rp.autoencoder_params(config, "cantilever", "3", "no_noise"),
        "integrator": rp.integrator_params(config, "cantilever", "no_noise", 3),
        "prune": rp.sweep_prune_params(config, "cantilever", scene_seeds(config, "cantilever")[-1]),
        "conditioned_ae": rp.conditioned_autoencoder_params(config, "cloth", 0),
        "conditioned": rp.conditioned_integrator_params(config, "cloth", "conditioned", 0),
        "nm_modes": rp.nm_modes_params(config, "nm_sheet"),
        "nm_train": rp.nm_train_params(config, "nm_sheet"),
        "nm_ground_truth": rp.nm_ground_truth_params(config, "nm_sheet", "sheet"),
        "nm_sheet": rp.nm_study_params(config, "nm_sheet", "sheet", 2),
    }
    return {k: json.dumps(v) for k, v in out.items()}


def test_params_are_plain_and_do_not_change_with_the_order_of_the_yaml(config):
    assert rp.canonical({"b": (1, 2), "a": {"d": 1, "c": 2}}) == {"a": {"c": 2, "d": 1}, "b": [1, 2]}
    assert list(rp.canonical({"b": 1, "a": 2})) == ["a", "b"]
    assert _every_param(_reversed(copy.deepcopy(config))) == _every_param(config)


def test_each_rule_gets_only_what_it_reads(config):
    modes = rp.nm_modes_params(config, "nm_sheet")
    assert sorted(modes["neural_modes"]) == sorted(rp.MODE_KEYS)
    sheet = rp.nm_study_params(config, "nm_sheet", "sheet")
    assert not set(rp.STUDY_SETS) & set(sheet["neural_modes"])
    assert sheet["seed"] == scene_seeds(config, "nm_sheet")[0]
    assert "contact" not in rp.sim_params(config, "cantilever") and "contact" in rp.sim_params(config, "cantilever_floor")
    # where a mesh collider's file is found: in a mesh scene's params only (the others' are as before meshes existed)
    assert "mesh_sources" not in rp.sim_params(config, "cloth_sphere") and rp.sim_params(config, "cloth_drape")["mesh_sources"] == rp.mesh_sources(config)
    assert rp.sweep_prune_params(config, "cantilever", scene_seeds(config, "cantilever")[0]) == {}  # the first seed always runs
