"""Config validation: defaults filled, malformed configs stopped with the key named."""

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from latentsim.config import (
    SCHEMA,
    ConfigError,
    autoencoder_dir,
    autoencoder_settings,
    integrator_settings,
    load_config,
    schema_defaults,
    sweep_point_method,
    sweep_point_settings,
    validate_config,
    with_defaults,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def tiny():
    return yaml.safe_load((ROOT / "config" / "tiny.yaml").read_text())


@pytest.mark.parametrize("name", ["config.yaml", "tiny.yaml"])
def test_shipped_configs_validate(name):
    cfg = load_config(ROOT / "config" / name)
    for scene in cfg["scenes"].values():
        # defaults filled at every level
        assert scene["newton"]["max_iterations"] >= 1
        assert "noise_scale" in scene["integrator"]
        for seq in scene["sequences"]:
            assert seq["split"] in ("train", "test")


def test_unknown_scene_key_is_named(tiny):
    tiny["scenes"]["tiny_rods"]["materail"] = {}
    with pytest.raises(ConfigError, match=r"scenes\.tiny_rods.*materail"):
        validate_config(tiny)


def test_negative_youngs_modulus_is_named(tiny):
    tiny["scenes"]["tiny_rods"]["material"]["youngs_modulus"] = -1.0
    with pytest.raises(ConfigError, match=r"scenes\.tiny_rods\.material\.youngs_modulus.*-1\.0.*exclusiveMinimum"):
        validate_config(tiny)


def test_string_where_a_number_goes_is_named(tiny):
    tiny["scenes"]["tiny_cloth"]["dt"] = "fast"
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.dt.*'fast'.*number"):
        validate_config(tiny)


def test_a_contact_projection_without_colliders_is_named(tiny):
    tiny["scenes"]["tiny_cloth"]["rollout"] = {"contact_projection": {"enabled": True}}
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.rollout\.contact_projection\.enabled.*no colliders"):
        validate_config(tiny)
    validate_config(copy.deepcopy(yaml.safe_load((ROOT / "config" / "tiny.yaml").read_text())))  # tiny_contact's, with its ball, passes


def test_self_contact_without_colliders_is_named_and_a_solid_without_a_surface_is_refused_by_the_barrier(tiny):
    tiny["scenes"]["tiny_cloth"]["contact"] = {"self_contact": True}
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.contact\.self_contact.*has none"):
        validate_config(tiny)
    from latentsim.scene import contact_barrier

    block = {"colliders": [{"type": "half_space", "point": [0, -1, 0], "normal": [0, 1, 0]}], "d_hat": 1e-3, "kappa": 1.0, "self_contact": True}
    with pytest.raises(ValueError, match="self_contact: the scene's model has no surface"):
        contact_barrier(block, 4, np.zeros((4, 3)), [], 0.03, primitives=None)
    barrier = contact_barrier({**block, "thickness": 0.002}, 4, np.zeros((4, 3)), [], 0.03, primitives=np.array([[0, 1, 2], [1, 3, 2]]))
    assert [t.name for t in barrier.terms()] == ["contact_barrier", "self_contact"] and barrier.self_term().thickness == 0.004


def test_enum_lists_allowed_values(tiny):
    tiny["scenes"]["tiny_rods"]["model"] = "fem"
    with pytest.raises(ConfigError, match=r"scenes\.tiny_rods\.model.*allowed values: \['rods', 'shell', 'tets'\]"):
        validate_config(tiny)


def test_defaults_do_not_leak_between_scenes(tiny):
    cfg = validate_config(copy.deepcopy(tiny))
    cfg["scenes"]["tiny_rods"]["newton"]["tolerance"] = 1.0
    assert cfg["scenes"]["tiny_cloth"]["newton"]["tolerance"] != 1.0


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda sc: sc.update(paper="none"), r"'scenes\.tiny_nm\.nm_study\.\w+\.enabled'.*paper wang2024.*'none'"),
        (lambda sc: sc.update(model="tets"), r"'scenes\.tiny_nm\.nm_study\.sheet\.enabled'.*needs a shell.*'tets'"),
        (lambda sc: sc["nm_study"]["energy"].update(train=15), r"'scenes\.tiny_nm\.nm_study\.energy'.*20 samples leave 1 test samples"),
        (lambda sc: sc["nm_study"]["keyframes"].update(poses=[[0, 0], [1, 0, 0]]), r"'scenes\.tiny_nm\.nm_study\.keyframes\.poses'.*2 modal coordinates"),
        (lambda sc: sc["neural_modes"].update(boundary="free"), r"'scenes\.tiny_nm\.nm_study\.dynamics\.enabled'.*boundary to dirichlet"),
        (lambda sc: sc["nm_study"]["sheet"].update(curve_points=0), r"'scenes\.tiny_nm\.nm_study\.sheet\.curve_points'.*0 is out of range"),
        (lambda sc: sc["nm_study"].update(table6={}), r"'scenes\.tiny_nm\.nm_study'.*unknown key.*table6"),
        (lambda sc: sc["nm_study"]["aspect"].update(ratios=4), r"'scenes\.tiny_nm\.nm_study\.aspect\.ratios'.*4 is even"),
        (lambda sc: sc["nm_study"]["aspect"].update(ratio_min=2.0), r"'scenes\.tiny_nm\.nm_study\.aspect'.*ratio_min 2\.0 must be below ratio_max 2\.0"),
    ],
)
def test_neural_modes_studies_that_do_not_fit_the_scene_are_named(tiny, edit, message):
    edit(tiny["scenes"]["tiny_nm"])
    with pytest.raises(ConfigError, match=message):
        validate_config(tiny)


def test_a_variant_of_another_size_overrides_the_autoencoder_apart_from_the_integrator(tiny):
    cfg = validate_config(tiny)
    assert tiny["integrator_variants"]["small"]["autoencoder"] == {"latent_dim": 2, "widths": [16]}
    own, small = autoencoder_settings(cfg, "tiny_rods"), autoencoder_settings(cfg, "tiny_rods", "small")
    assert (own["latent_dim"], own["widths"], small["latent_dim"], small["widths"]) == (4, [32, 32], 2, [16])
    assert {k: v for k, v in small.items() if k not in ("latent_dim", "widths")} == {k: v for k, v in own.items() if k not in ("latent_dim", "widths")}
    assert autoencoder_settings(cfg, "tiny_rods", "supervised") == own  # a variant without the block shares the scene's
    integ = integrator_settings(cfg, "tiny_rods", "small")
    assert "autoencoder" not in integ and integ["widths"] == [16] and integ["epochs"] == cfg["scenes"]["tiny_rods"]["integrator"]["epochs"]
    assert autoencoder_dir(cfg, "tiny_rods", "small") == "results/autoencoder/tiny_rods/small/seed0"
    assert autoencoder_dir(cfg, "tiny_rods", "small", 1) == "results/autoencoder/tiny_rods/small/seed1"
    assert autoencoder_dir(cfg, "tiny_rods", "supervised") == autoencoder_dir(cfg, "tiny_rods") == "results/autoencoder/tiny_rods/seed0"
    with pytest.raises(ConfigError, match="no integrator variant 'small'"):
        autoencoder_settings(cfg, "tiny_cloth", "small")  # the scene does not list it


def test_unknown_key_of_a_variants_autoencoder_is_named(tiny):
    tiny["integrator_variants"]["small"]["autoencoder"]["coordinates"] = "mean"
    with pytest.raises(ConfigError, match=r"integrator_variants\.small\.autoencoder'.*coordinates"):
        validate_config(tiny)


def test_a_sweep_trains_its_points_with_the_method_it_names(tiny):
    cfg = validate_config(copy.deepcopy(tiny))
    own = sweep_point_settings(cfg, "tiny_cloth", 2, 0)
    assert own["integrator"] == dict(cfg["scenes"]["tiny_cloth"]["integrator"], widths=[32, 32])
    assert own["autoencoder"] == dict(cfg["scenes"]["tiny_cloth"]["autoencoder"], latent_dim=2, widths=[32, 32])
    tiny["integrator_variants"]["hybrid"] = {"supervised_weight": 3.0, "widths": [99], "autoencoder": {"latent_dim": 7, "epochs": 11}}
    tiny["scenes"]["tiny_cloth"]["variants"] = ["hybrid"]
    tiny["scenes"]["tiny_cloth"]["sweep"]["method"] = "hybrid"
    cfg = validate_config(tiny)
    point = sweep_point_settings(cfg, "tiny_cloth", 2, 0)
    # the variant's loss and settings, the point's latent size and widths
    assert point["integrator"]["supervised_weight"] == 3.0 and point["integrator"]["widths"] == [32, 32]
    assert point["autoencoder"]["epochs"] == 11 and point["autoencoder"]["latent_dim"] == 2 and point["autoencoder"]["widths"] == [32, 32]


def test_a_sweep_point_is_a_trained_method_only_where_every_setting_matches(tiny):
    cfg = validate_config(copy.deepcopy(tiny))
    assert sweep_point_method(cfg, "tiny_cloth", 4, 0) == "self_supervised"  # the scene's latent 4 at its own widths
    assert sweep_point_method(cfg, "tiny_cloth", 2, 0) is None  # another latent size
    tiny["scenes"]["tiny_cloth"]["sweep"]["sizes"] = [{"autoencoder": [32, 32], "integrator": [32]}]
    assert sweep_point_method(validate_config(copy.deepcopy(tiny)), "tiny_cloth", 4, 0) is None  # other integrator widths
    # a variant with its own autoencoder of the point's size, trained with the sweep's loss: the point is the variant
    tiny["integrator_variants"]["small"] = {"widths": [32], "autoencoder": {"latent_dim": 2}}
    tiny["scenes"]["tiny_cloth"]["variants"] = ["small"]
    cfg = validate_config(copy.deepcopy(tiny))
    assert sweep_point_method(cfg, "tiny_cloth", 2, 0) == "small"
    tiny["scenes"]["tiny_cloth"]["integrator"]["lr"] = 2.0e-3  # now the sweep's loss differs from the variant's settings
    tiny["integrator_variants"]["small"]["lr"] = 1.0e-3
    assert sweep_point_method(validate_config(tiny), "tiny_cloth", 2, 0) is None


def test_a_sweep_method_the_scene_does_not_run_is_named(tiny):
    tiny["scenes"]["tiny_cloth"]["sweep"]["method"] = "supervised"  # defined, but tiny_cloth does not list it
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.sweep\.method'.*'supervised'"):
        validate_config(tiny)


def test_the_default_config_records_every_sweeps_choice_at_the_size_all_trains():
    """`all` runs no sweep: each scene's recorded choice (sweep.chosen) is the size of one of its methods, so the
    tables reproduce the sweep's choice without rerunning it (validation refuses a config where it is not)."""
    cfg = load_config(ROOT / "config" / "config.yaml")
    swept = {n: s["sweep"] for n, s in cfg["scenes"].items() if s["sweep"].get("latent_dims")}
    assert swept and all(sw["chosen"] is not None for sw in swept.values()), [n for n, sw in swept.items() if not sw["chosen"]]
    for name, sw in swept.items():
        if sw["chosen"]["point"] != "none":
            r, i = (int(v) for v in sw["chosen"]["point"][1:].split("_s"))
            assert sweep_point_method(cfg, name, r, i) is not None, name
    # the cloth's three-seed sweep chose the paper's latent 4 and 200 x 3 decoder, the cantilever's the linear decoder
    assert (cfg["scenes"]["cloth"]["autoencoder"]["latent_dim"], cfg["scenes"]["cloth"]["autoencoder"]["widths"]) == (4, [200, 200, 200])
    assert (cfg["scenes"]["cantilever"]["autoencoder"]["latent_dim"], cfg["scenes"]["cantilever"]["autoencoder"]["widths"]) == (2, [])


@pytest.mark.parametrize(
    "point, message",
    [("r2_s0", r"sweep\.chosen\.point'.*latent 2 with decoder \[32, 32\].*none of the scene's methods has that size"),
     ("r6_s0", r"sweep\.chosen\.point'.*'r6_s0' is not a point of the scene's sweep"),
     ("r4_s9", r"sweep\.chosen\.point'.*'r4_s9' is not a point")],
)  # fmt: skip
def test_a_recorded_sweep_choice_no_method_has_or_no_point_is_named(tiny, point, message):
    tiny["scenes"]["tiny_cloth"]["sweep"]["chosen"] = {"point": point, "commit": "abc1234", "seeds": 1}
    with pytest.raises(ConfigError, match=message):
        validate_config(tiny)
    tiny["scenes"]["tiny_cloth"]["sweep"]["chosen"]["point"] = "r4_s0"  # the scene's own size
    validate_config(tiny)


@pytest.mark.parametrize("definition", ["autoencoder", "integrator", "rollout", "stability"])
def test_every_setting_the_latent_code_reads_has_a_description_and_a_default(definition):
    """The schema is the one table of defaults: code called with partial settings fills them from it."""
    defs = yaml.safe_load(SCHEMA.read_text())["$defs"]
    for key, prop in defs[definition]["properties"].items():
        described = prop.get("description") or defs.get(prop.get("$ref", "").rsplit("/", 1)[-1], {}).get("description")
        assert described, f"{definition}.{key} has no description"
        assert "default" in prop, f"{definition}.{key} has no default"


def test_defaults_the_code_kept_before_the_schema_held_them():
    """Keys the pipeline's configs never set ran on the code's own defaults; the schema now holds
    those same values, so the pipeline's trainings are unchanged."""
    ae, integ = schema_defaults("autoencoder"), schema_defaults("integrator")
    assert (ae["train_pca"], ae["pca_samples"], ae["coordinates"]) == (True, 4000, None)
    assert (integ["lr_final"], integ["residual"], integ["supervised_weight"]) == (None, True, 0.0)
    assert (integ["balancing_eps"], integ["use_penalty"]) == (0.01, None)
    assert schema_defaults("rollout")["full_frames_timed"] == 20


def test_partial_settings_take_the_schema_defaults_nested_blocks_key_by_key():
    got = with_defaults("rollout", {"max_extent": 3.0, "stability": {"long_factor": 2}}, "rollout_scene")
    full = schema_defaults("rollout")
    assert got["max_extent"] == 3.0 and got["timing_repeats"] == full["timing_repeats"]
    assert got["stability"] == {**full["stability"], "long_factor": 2}
    assert with_defaults("integrator", None, "fit_integrator") == schema_defaults("integrator")
    with pytest.raises(ConfigError, match=r"fit_integrator: unknown setting\(s\) \['checkpoint_every'\]"):
        with_defaults("integrator", {"checkpoint_every": 1}, "fit_integrator")
    with pytest.raises(ConfigError, match=r"stress_test: unknown setting\(s\) \['stability.speed'\]"):
        with_defaults("rollout", {"stability": {"speed": [2.0]}}, "stress_test")


def test_a_free_body_starts_with_a_velocity_and_only_a_free_body_does(tiny):
    """dirichlet type free: a sequence's segments have no prescribed set to move (named, with the keys that
    start the body instead); a pinned scene's sequence cannot take a free body's initial velocity."""
    free = copy.deepcopy(tiny)
    free["scenes"]["tiny_cloth"]["dirichlet"] = {"type": "free"}
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.sequences\.0\.segments\.0\.velocity.*free body.*initial_velocity"):
        validate_config(free)
    for seg in free["scenes"]["tiny_cloth"]["sequences"][0]["segments"]:
        seg["velocity"] = [0, 0, 0]
    free["scenes"]["tiny_cloth"]["sequences"][0]["initial_angular_velocity"] = [0.0, 0.0, 1.0]
    seq = validate_config(free)["scenes"]["tiny_cloth"]["sequences"][0]
    assert seq["initial_angular_velocity"] == [0.0, 0.0, 1.0] and "initial_velocity" not in seq  # no default: at rest
    tiny["scenes"]["tiny_cloth"]["sequences"][0]["initial_velocity"] = [0.0, 1.0, 0.0]
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.sequences\.0\.initial_velocity.*only a free body"):
        validate_config(tiny)


def test_material_names_come_from_the_registry(tiny, monkeypatch):
    """material.model takes the names registered in physics.materials, read on load (not a copy in
    the schema): an unknown name is refused with the registered ones listed; a newly registered
    material validates."""
    from latentsim.physics.materials import MATERIALS, material_names

    assert "enum" not in yaml.safe_load(SCHEMA.read_text())["$defs"]["material"]["properties"]["model"]
    bad = copy.deepcopy(tiny)
    bad["scenes"]["tiny_rods"]["material"]["model"] = "springy"
    with pytest.raises(ConfigError, match=r"scenes\.tiny_rods\.material\.model.*'springy'.*" + r".*".join(material_names())):
        validate_config(bad)
    monkeypatch.setitem(MATERIALS, "springy", dict(MATERIALS["stvk"]))
    validate_config(copy.deepcopy(bad))


def test_a_plateau_stop_on_an_energy_loss_is_refused_on_load_naming_its_block(tiny):
    """The plateau rule is for the supervised baselines: on a variant of the energy loss, or on a scene's
    own (self-supervised) integrator, the config is refused before any job, naming where it is set."""
    rule = {"window": 50, "tolerance": 0.01}
    ok = copy.deepcopy(tiny)
    ok["integrator_variants"]["supervised"]["plateau_stop"] = rule
    assert validate_config(ok)["integrator_variants"]["supervised"]["plateau_stop"] == rule
    bad = copy.deepcopy(tiny)
    bad["integrator_variants"]["small"]["plateau_stop"] = rule
    with pytest.raises(ConfigError, match=r"integrator_variants\.small\.plateau_stop' \(scene tiny_rods\) is for a supervised training only"):
        validate_config(bad)
    own = copy.deepcopy(tiny)
    own["scenes"]["tiny_cloth"]["integrator"]["plateau_stop"] = rule
    with pytest.raises(ConfigError, match=r"scenes\.tiny_cloth\.integrator\.plateau_stop' is for a supervised training only"):
        validate_config(own)
    half = copy.deepcopy(tiny)
    half["integrator_variants"]["supervised"]["plateau_stop"] = {"window": 50}
    with pytest.raises(ConfigError, match=r"plateau_stop.*tolerance"):
        validate_config(half)
