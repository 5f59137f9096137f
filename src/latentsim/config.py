"""Config validation against the JSON schema (draft 2020-12), with defaults.

``validate_config`` fills every default the schema declares and raises
``ConfigError`` at the first problem with a message that names the key (as a
dotted path), the offending value and what is allowed.  The Snakefile calls it
on load, so a malformed config stops the run before any job starts.

Beyond the schema it rejects what the schema cannot say: a NaN or infinite number anywhere
(JSON-schema bounds compare false for NaN, and inf passes ``> 0``; no key takes an infinite
value), two sequences of a scene stored under one name, a scene without a training or a test
sequence, and a latent dimension above the number of independent directions the scene's
training frames can have.
"""

from __future__ import annotations

import copy
import functools
import math
from pathlib import Path

import jsonschema
import yaml

SCHEMA = Path(__file__).resolve().parents[2] / "workflow" / "schemas" / "config.schema.yaml"


class ConfigError(ValueError):
    """The config breaks the schema; the message names the key."""


def _with_defaults(cls):
    validate_properties = cls.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for key, sub in properties.items():
                if "default" in sub and key not in instance:
                    instance[key] = copy.deepcopy(sub["default"])
        yield from validate_properties(validator, properties, instance, schema)

    return jsonschema.validators.extend(cls, {"properties": set_defaults})


_Validator = _with_defaults(jsonschema.Draft202012Validator)


def _describe(error: jsonschema.ValidationError) -> str:
    path = ".".join(str(p) for p in error.absolute_path) or "<top level>"
    v, s = error.validator, error.schema
    if v == "additionalProperties":
        allowed = sorted(s.get("properties", {}))
        extra = sorted(set(error.instance) - set(allowed))
        return f"config key '{path}': unknown key(s) {extra}; allowed: {allowed}"
    if v == "enum":
        return f"config key '{path}': {error.instance!r} is not allowed; allowed values: {s['enum']}"
    if v == "type":
        return f"config key '{path}': {error.instance!r} is a {type(error.instance).__name__}, expected {s['type']}"
    if v in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        bounds = {k: s[k] for k in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum") if k in s}
        why = f" ({' '.join(s['description'].split())})" if s.get("description") else ""
        return f"config key '{path}': {error.instance!r} is out of range; allowed: {bounds}{why}"
    if v == "required":
        return f"config key '{path}': {error.message}"
    if v in ("oneOf", "anyOf"):
        return _describe_alternatives(error, path)
    return f"config key '{path}': {error.message}"


def _describe_alternatives(error: jsonschema.ValidationError, path: str) -> str:
    """A value that fits none of a ``oneOf`` / ``anyOf``'s alternatives.  Where each alternative is an object of
    one kind (its ``type`` a ``const``, as ``contact.colliders``' are): the problems of the alternative of the
    value's kind, or, for a kind not among them, every kind with its fields; otherwise each alternative's
    first problem."""
    branches = error.validator_value
    kinds = {b.get("properties", {}).get("type", {}).get("const"): i for i, b in enumerate(branches)}
    kinds.pop(None, None)
    by_branch: dict[int, list] = {i: [] for i in range(len(branches))}
    for sub in error.context:
        by_branch[sub.relative_schema_path[0]].append(sub)
    if not kinds or len(kinds) < len(branches):
        tried = "; or ".join(subs[0].message for subs in by_branch.values() if subs)
        why = f" ({' '.join(error.schema['description'].split())})" if error.schema.get("description") else ""
        return f"config key '{path}': {error.instance!r} fits none of the alternatives ({tried}){why}"

    def fields(i):
        required = [k for k in branches[i].get("required", []) if k != "type"]
        optional = [k for k in branches[i].get("properties", {}) if k not in required and k != "type"]
        return ", ".join(required) + (f"; optional: {', '.join(optional)}" if optional else "")

    kind = error.instance.get("type") if isinstance(error.instance, dict) else None
    if kind in kinds:
        first, *more = dict.fromkeys(_describe(sub) for sub in by_branch[kinds[kind]])
        here = f"config key '{path}': "  # said once for the problems of the mapping itself
        problems = "; ".join([first] + [m.removeprefix(here) if first.startswith(here) else m for m in more])
        return f"{problems} (type {kind} takes: {fields(kinds[kind])})"
    allowed = "; ".join(f"{k} ({fields(i)})" for k, i in kinds.items())
    if not isinstance(error.instance, dict):
        given = f"{error.instance!r} is not a mapping"
    else:
        given = f"type {kind!r} is not allowed" if "type" in error.instance else "no 'type' given"
    return f"config key '{path}': {given}; give a mapping with 'type' one of {list(kinds)} and its fields: {allowed}"


def _seed_list(value):
    """``seeds`` as written on the command line too: an integer k stands for [k], and the list items that
    ``--config "seeds=[0,1]"`` passes as strings are read as integers (anything else is left to the schema)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return [value]
    if isinstance(value, list):
        return [int(v) if isinstance(v, str) and v.strip().isdigit() else v for v in value]
    return value


def _normalise_seeds(config) -> None:
    if not isinstance(config, dict):
        return
    if "seeds" in config:
        config["seeds"] = _seed_list(config["seeds"])
    for scene in (config.get("scenes") or {}).values():
        if isinstance(scene, dict) and scene.get("seeds") is not None:
            scene["seeds"] = _seed_list(scene["seeds"])


def _material_names(schema: dict) -> None:
    """The schema's ``material.model`` takes the names of the registered materials (``physics.materials``)."""
    from latentsim.physics.materials import material_names  # the terms import torch: only when validating

    schema["$defs"]["material"]["properties"]["model"]["enum"] = list(material_names())


def validate_config(config: dict, schema_path=SCHEMA) -> dict:
    """Validate ``config`` in place (filling defaults) and return it."""
    _check_finite(config)
    if isinstance(config, dict) and "seed" in config:
        raise ConfigError(f"config key 'seed': {config['seed']!r}: the single seed was replaced by a list of seeds, "
                          f"'seeds' (e.g. seeds: [{config['seed']!r}]); every learned method runs once per seed")  # fmt: skip
    _normalise_seeds(config)
    with open(schema_path) as fh:
        schema = yaml.safe_load(fh)
    _material_names(schema)
    validator = _Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: (len(list(e.absolute_path)), list(map(str, e.absolute_path))))
    if errors:
        # the deepest error of the first failing branch is the most specific
        error = max(errors, key=lambda e: len(list(e.absolute_path)))
        raise ConfigError(_describe(error))
    _check_variants(config)
    _check_sequences(config)
    _check_nm_study(config)
    _check_latent_dims(config)
    _check_pca_width(config)
    _check_conditioning(config)
    _check_contact_projection(config)
    _check_d_hat(config)
    _check_sweep_chosen(config)
    return config


def condition_name(time_step: float, modulus: float) -> str:
    """A file-name-safe name of a condition, e.g. ``60hz_3e05pa`` (frame rate 1/h, modulus E)."""
    return f"{1.0 / time_step:.4g}hz_{modulus:.3g}pa".replace("+", "").replace(".", "p")


def conditioned(config: dict, scene: str) -> bool:
    """Whether a scene trains a conditioned integrator (its ``conditioning.test`` lists conditions)."""
    return bool(config["scenes"][scene].get("conditioning", {}).get("test"))


def conditions(config: dict, scene: str) -> dict[str, dict]:
    """A conditioned scene's conditions by name (``latent.conditioning.condition_name``): each
    ``{time_step, youngs_modulus, split}``, the training ones (the box's four corners unless listed)
    first."""
    c = config["scenes"][scene]["conditioning"]
    train = c.get("train") or [
        {"time_step": h, "youngs_modulus": E} for h in dict.fromkeys(c["time_step"]) for E in dict.fromkeys(c["youngs_modulus"])
    ]
    out = {}
    for split, items in (("train", train), ("test", c["test"])):
        for q in items:
            out.setdefault(condition_name(q["time_step"], q["youngs_modulus"]), {"time_step": float(q["time_step"]), "youngs_modulus": float(q["youngs_modulus"]), "split": split})
    return out


def conditioned_autoencoder_settings(config: dict, scene: str) -> dict:
    """The settings of a conditioned scene's autoencoder: the scene's, with its ``conditioning.autoencoder``."""
    return {**config["scenes"][scene]["autoencoder"], **config["scenes"][scene]["conditioning"].get("autoencoder", {})}


def conditioned_integrator_settings(config: dict, scene: str, model: str = "conditioned") -> dict:
    """The settings of a conditioned scene's integrators: the scene's, with its ``conditioning.integrator``
    and, for the conditioned integrator (``model`` conditioned; any other: a reference), its
    ``conditioning.conditioned``."""
    c = config["scenes"][scene]["conditioning"]
    return {**config["scenes"][scene]["integrator"], **c.get("integrator", {}), **(c.get("conditioned", {}) if model == "conditioned" else {})}


def _check_conditioning(config: dict) -> None:
    """A conditioned scene's box (two values each, lo <= hi), its test conditions inside it and none
    a training condition, a material linear in the modulus, and its integrators' training features
    (:func:`check_training_features`: the self-supervised loss alone, no rigid frame)."""
    for name, scene in config.get("scenes", {}).items():
        c = scene.get("conditioning") or {}
        key = f"scenes.{name}.conditioning"
        if not (c.get("test") or c.get("train") or c.get("time_step") or c.get("youngs_modulus")):
            continue
        for k in ("time_step", "youngs_modulus"):
            v = c.get(k) or []
            if len(v) != 2 or v[0] > v[1]:
                raise ConfigError(f"config key '{key}.{k}': {v!r}: give the range as [lo, hi] with lo <= hi")
        if not c.get("test"):
            raise ConfigError(f"config key '{key}.test': a conditioned scene needs at least one held-out test condition")
        if scene.get("material", {}).get("bending_stiffness") is not None:
            raise ConfigError(f"config key 'scenes.{name}.material.bending_stiffness': a conditioned scene scales every elastic term with the "
                              "modulus; a bending stiffness given apart from it does not scale")  # fmt: skip
        rigid = bool(conditioned_autoencoder_settings(config, name).get("rigid_frame"))
        for model in ("conditioned", "reference"):
            check_training_features(conditioned_integrator_settings(config, name, model), _conditioned_key(name), conditioned=True, rigid_frame=rigid)
        (h0, h1), (e0, e1) = c["time_step"], c["youngs_modulus"]
        train = {condition_name(q["time_step"], q["youngs_modulus"]) for q in c.get("train") or []}
        for i, q in enumerate(c.get("train") or []):
            if not (h0 <= q["time_step"] <= h1 and e0 <= q["youngs_modulus"] <= e1):
                raise ConfigError(f"config key '{key}.train.{i}': {q} lies outside the box time_step {c['time_step']}, youngs_modulus {c['youngs_modulus']}")
        seen = set()
        for i, q in enumerate(c["test"]):
            n = condition_name(q["time_step"], q["youngs_modulus"])
            if not (h0 <= q["time_step"] <= h1 and e0 <= q["youngs_modulus"] <= e1):
                raise ConfigError(f"config key '{key}.test.{i}': {q} lies outside the box time_step {c['time_step']}, youngs_modulus {c['youngs_modulus']}")
            corners = {condition_name(h, E) for h in (h0, h1) for E in (e0, e1)}
            if n in (train or corners):
                raise ConfigError(f"config key '{key}.test.{i}': {q} is a training condition; a test condition is held out")
            if n in seen:
                raise ConfigError(f"config key '{key}.test.{i}': {q} is listed twice")
            seen.add(n)


def _conditioned_key(scene: str):
    """The names of a conditioned scene's settings in :func:`check_training_features`' messages:
    an autoencoder's key under the scene, the integrators' block under its ``conditioning``."""
    return lambda k: f"config key 'scenes.{scene}.{k}'" if k.startswith("autoencoder") else f"config key 'scenes.{scene}.conditioning.{k}' (or '.conditioned')"


def check_training_features(settings: dict, key, conditioned: bool = False, rigid_frame: bool = False) -> None:
    """The one check of an integrator's training features against each other (the conditioning,
    own rollouts and their speeds, the origin input, the loss's mode and supervision), for the
    config (:func:`_check_conditioning`) and for ``latent.training.fit_integrator``.

    Parameters
    ----------
    settings : the integrator's settings (the schema's ``integrator``; keys absent take its defaults).
    key : names a setting in messages: ``key("integrator")`` the settings, ``key("integrator.<name>")``
        one of them, ``key("autoencoder.rigid_frame")`` the autoencoder's.
    conditioned : whether the integrator trains over a box of conditions (or at one: a reference).
    rigid_frame : whether its autoencoder has a rigid frame.

    Raises
    ------
    ConfigError : naming the setting, where a feature is not for another in use.
    """
    settings = {**schema_defaults("integrator"), **settings}
    mode, weight = settings["mode"], float(settings["supervised_weight"])
    speeds, own = settings["own_rollouts_speeds"], int(settings["own_rollouts_every"])
    if conditioned and (mode != "self_supervised" or weight > 0):
        raise ConfigError(f"{key('integrator')}: a conditioned integrator and its references train on "
                          "the incremental potential alone (mode self_supervised, supervised_weight 0)")  # fmt: skip
    if conditioned and rigid_frame:
        raise ConfigError(f"{key('autoencoder.rigid_frame')}: not for a conditioned scene (its timing and own rollouts step the program in the world's frame)")
    if conditioned and settings["origin_input"]:
        raise ConfigError(f"{key('integrator')}: origin_input is not for a conditioned integrator (its own rollouts step the program at other time steps)")
    if own > 0 and mode != "self_supervised":
        raise ConfigError(f"{key('integrator')}: own_rollouts_every needs a self-supervised training")
    if settings["plateau_stop"] is not None and (mode != "supervised" or conditioned):
        raise ConfigError(f"{key('integrator.plateau_stop')} is for a supervised training only (mode {mode}): an energy loss "
                          "flattens while the test error still falls")  # fmt: skip
    if speeds is None:
        return
    what = key("integrator.own_rollouts_speeds")
    if own <= 0:
        raise ConfigError(f"{what} scales the own rollouts' programs, but there are none (own_rollouts_every is 0)")
    if conditioned:
        raise ConfigError(f"{what} is not for a conditioned integrator (its own rollouts are drawn at conditions of its box)")
    if weight > 0:
        raise ConfigError(f"{what} is not for a training with a supervised term (supervised_weight {settings['supervised_weight']}): "
                          "ground truth exists only at the recorded speeds")  # fmt: skip

def _check_finite(value, path: str = "") -> None:
    """Every number in ``value`` (nested dicts and lists) must be finite: YAML reads ``.nan`` and
    ``.inf``, and ``--config key=nan`` gives a float NaN, all of which the schema's bounds let
    through.  No key of the schema takes an infinite value."""
    if isinstance(value, dict):
        for k, v in value.items():
            _check_finite(v, f"{path}.{k}" if path else str(k))
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_finite(v, f"{path}.{i}" if path else str(i))
    elif isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"config key '{path or '<top level>'}': {value!r} is not a finite number")


def schema_defaults(definition: str, schema_path=SCHEMA) -> dict:
    """The defaults the schema declares for the properties of ``$defs/<definition>`` (e.g.
    ``"autoencoder"``, ``"integrator"``, ``"neural_modes"``): the one table of defaults, for code
    called outside the pipeline with a partial settings dict.  Nested objects get their own defaults
    filled, as ``validate_config`` fills them."""
    return copy.deepcopy(_schema_defaults(definition, str(schema_path)))


@functools.lru_cache(maxsize=None)
def _schema_defaults(definition: str, schema_path: str) -> dict:
    """Read once per process (about 40 ms a read): callers get deep copies."""
    with open(schema_path) as fh:
        schema = yaml.safe_load(fh)
    if definition not in schema.get("$defs", {}):
        raise KeyError(f"the config schema has no definition '{definition}'; it has {sorted(schema['$defs'])}")
    out: dict = {}
    _Validator({**schema["$defs"][definition], "$defs": schema["$defs"]}).validate(out)
    return out


def with_defaults(definition: str, settings: dict | None, what: str) -> dict:
    """``settings`` over the schema's defaults for ``$defs/<definition>`` (nested objects merged key
    by key); a key the schema does not know raises a ``ConfigError`` naming ``what`` (the function
    that was called) and the key.  Values are not validated: the pipeline validates its config on
    load; code called outside it takes responsibility for its settings."""
    return _over(schema_defaults(definition), settings or {}, what)


def _over(defaults: dict, settings: dict, what: str, path: str = "") -> dict:
    """``settings`` over ``defaults``, nested objects merged key by key (so a partial nested block
    keeps the defaults of the keys it leaves out)."""
    unknown = sorted(set(settings) - set(defaults))
    if unknown:
        raise ConfigError(f"{what}: unknown setting(s) {[path + k for k in unknown]}; allowed: {sorted(path + k for k in defaults)}")
    out = dict(defaults)
    for k, v in settings.items():
        nested = isinstance(defaults[k], dict) and isinstance(v, dict) and defaults[k]
        out[k] = _over(defaults[k], v, what, f"{path}{k}.") if nested else copy.deepcopy(v)
    return out


def _check_variants(config: dict) -> None:
    """Every scene's ``variants`` entry must name a defined integrator variant; its sweep, one of its methods."""
    known = config.get("integrator_variants", {})
    for name, scene in config.get("scenes", {}).items():
        for v in scene.get("variants", []):
            if v not in known:
                raise ConfigError(f"config key 'scenes.{name}.variants': unknown variant {v!r}; defined in integrator_variants: {sorted(known)}")
        method = scene.get("sweep", {}).get("method", "self_supervised")
        if method != "self_supervised" and method not in scene.get("variants", []):
            raise ConfigError(f"config key 'scenes.{name}.sweep.method': {method!r} is not one of the scene's methods: {['self_supervised', *scene.get('variants', [])]}")
        for method in scene_methods(config, name):
            check_training_features(integrator_settings(config, name, method), _method_key(name, method))


def _method_key(scene: str, method: str):
    """Names an integrator setting of a scene's method in messages: the scene's own integrator block,
    or the variant's block in ``integrator_variants``."""

    def key(k: str) -> str:
        if method == "self_supervised" or not k.startswith("integrator"):
            return f"config key 'scenes.{scene}.{k}'"
        return f"config key 'integrator_variants.{method}{k[len('integrator'):]}' (scene {scene})"

    return key


def _check_sequences(config: dict) -> None:
    """A scene's sequences: one name each (the trajectories file stores them by name, and a
    sequence with ``train_frames`` also as ``<name>_train``), ``train_frames`` within ``frames``,
    and at least one training and one test sequence (the autoencoder and integrator train on the
    first, the rollout and the evaluation step the second)."""
    for name, scene in config.get("scenes", {}).items():
        key = f"scenes.{name}.sequences"
        stored: dict[str, str] = {}  # name in the trajectories file -> what stores it
        for i, q in enumerate(scene.get("sequences", [])):
            names = {q["name"]: f"sequence {i} {q['name']!r}"}
            if q.get("train_frames"):
                if q["train_frames"] > q["frames"]:
                    raise ConfigError(f"config key '{key}.{i}.train_frames': {q['train_frames']} is more than the sequence's {q['frames']} frames")
                names[f"{q['name']}_train"] = f"sequence {i} {q['name']!r} (its first train_frames frames)"
            for n, what in names.items():
                if n in stored:
                    raise ConfigError(
                        f"config key '{key}.{i}.name': scene {name} stores {what} as {n!r}, as it does {stored[n]}; "
                        "one name holds one sequence in the trajectories file: give each sequence its own name"
                    )
                stored[n] = what
            _check_free_body(q, scene, f"{key}.{i}")
        splits = {q.get("split", "train") for q in scene.get("sequences", [])}
        if any(q.get("train_frames") for q in scene.get("sequences", [])):
            splits.add("train")
        for split, use in (("train", "the autoencoder and integrator train on"), ("test", "the rollout and the evaluation step")):
            if split not in splits:
                raise ConfigError(
                    f"config key '{key}': scene {name} has no sequence of split {split} ({use} them); "
                    f"its sequences: {[(q['name'], q.get('split', 'train')) for q in scene.get('sequences', [])]}"
                    + ("; a test sequence with train_frames also trains on its first frames" if split == "train" else "")
                )


def _check_free_body(q: dict, scene: dict, key: str) -> None:
    """A free body (``dirichlet: {type: free}``) has no prescribed set for a segment to move: its sequences
    start it with ``initial_velocity`` / ``initial_angular_velocity`` instead, which only a free body takes."""
    free = scene.get("dirichlet", {}).get("type") == "free"
    initial = [k for k in ("initial_velocity", "initial_angular_velocity") if k in q]
    if initial and not free:
        raise ConfigError(f"config key '{key}.{initial[0]}': only a free body (dirichlet: {{type: free}}) starts with a "
                          "velocity; a prescribed set moves by its sequence's segments")
    if free:
        for j, seg in enumerate(q.get("segments", [])):
            for k in ("velocity", "angular_velocity"):
                if any(float(c) != 0.0 for c in seg.get(k, ())):
                    raise ConfigError(f"config key '{key}.segments.{j}.{k}': a free body (dirichlet: {{type: free}}) has no "
                                      f"prescribed set to move; start it with the sequence's initial_{k} instead")


def _train_frames(scene: dict) -> list[int]:
    """Frames of each training sequence of a scene: those of split train, and the first
    ``train_frames`` of each sequence that sets it."""
    out = [int(q["frames"]) for q in scene.get("sequences", []) if q.get("split", "train") == "train"]
    return out + [int(q["train_frames"]) for q in scene.get("sequences", []) if q.get("train_frames")]


def _check_contact_projection(config: dict) -> None:
    """A scene whose rollouts are projected out of its colliders, or whose surface is held off itself, has colliders
    (contact is on in a scene with colliders)."""
    for name, scene in config.get("scenes", {}).items():
        if (scene.get("contact") or {}).get("self_contact") and not scene["contact"].get("colliders"):
            raise ConfigError(f"config key 'scenes.{name}.contact.self_contact': contact is on in a scene with colliders, and this one "
                              f"has none (give at least one under 'scenes.{name}.contact.colliders', a floor for example)")  # fmt: skip
        if (scene.get("rollout") or {}).get("contact_projection", {}).get("enabled") and not (scene.get("contact") or {}).get("colliders"):
            raise ConfigError(f"config key 'scenes.{name}.rollout.contact_projection.enabled': the scene has no colliders to project its "
                              f"frames out of (give them under 'scenes.{name}.contact.colliders', or leave the projection off)")  # fmt: skip


#: the largest ``contact.d_hat``, as a fraction of the rest bounding-box diagonal (the schema's d_hat says why)
D_HAT_MAX_FRACTION = 0.05


def check_d_hat(d_hat, diagonal: float, scene: str) -> None:
    """Raise a ``ConfigError`` naming ``scenes.<scene>.contact.d_hat`` when ``d_hat`` [m] (null: IPC's default,
    always below) is above :data:`D_HAT_MAX_FRACTION` of the rest bounding-box ``diagonal`` [m]."""
    if d_hat is not None and float(d_hat) > D_HAT_MAX_FRACTION * diagonal:
        raise ConfigError(
            f"config key 'scenes.{scene}.contact.d_hat': {d_hat!r} m is {float(d_hat) / diagonal:.3g} times the rest bounding-box "
            f"diagonal ({diagonal:.3g} m); the barrier would push every vertex within it away from the colliders: give at most "
            f"{D_HAT_MAX_FRACTION:g} of the diagonal ({D_HAT_MAX_FRACTION * diagonal:.3g} m), or null (IPC's default, 1e-3 of it)"
        )


def _check_d_hat(config: dict) -> None:
    """No ``contact.d_hat`` above :data:`D_HAT_MAX_FRACTION` of a generated mesh's rest diagonal, which its config
    gives (a file's is known once the mesh is built: the simulation stage checks it there)."""
    for name, scene in config.get("scenes", {}).items():
        contact = scene.get("contact") or {}
        if contact.get("d_hat") is None or not contact.get("colliders"):
            continue
        from latentsim.mesh.build import generated_diagonal  # numpy and the mesh code, for a scene that sets d_hat

        diagonal = generated_diagonal(scene["model"], scene["mesh"])
        if diagonal is not None:
            check_d_hat(contact["d_hat"], diagonal, name)


def _check_latent_dims(config: dict) -> None:
    """No latent dimension above the rank the scene's training frames can have.

    Every sequence starts at the rest state, so T frames in s sequences are at most T - s + 1
    distinct rows, and their centred PCA has at most T - s directions (at most ``pca_samples`` - 1
    when the PCA sees a subset).  The autoencoder stage checks the data's actual rank."""
    for name, scene in config.get("scenes", {}).items():
        frames = _train_frames(scene)
        if not frames:
            continue
        points = [(f"scenes.{name}.autoencoder.latent_dim", "self_supervised", None)]
        for m in scene.get("variants", []):
            if own_autoencoder(config, m):
                block = config["integrator_variants"][m]["autoencoder"]
                points.append((f"integrator_variants.{m}.autoencoder.{'pca_samples' if 'latent_dim' not in block else 'latent_dim'}", m, None))
        sweep = scene.get("sweep", {})
        for r in sweep.get("latent_dims", []):
            points.append((f"scenes.{name}.sweep.latent_dims", sweep.get("method", "self_supervised"), r))
        for key, method, r in points:
            ae = autoencoder_settings(config, name, method)
            r = int(ae["latent_dim"] if r is None else r)
            bound = sum(frames) - len(frames)
            why = f"{sum(frames)} training frames in {len(frames)} sequence(s) of {frames} frames, each starting at the rest state"
            if ae.get("pca_samples") is not None and ae["pca_samples"] - 1 < bound:
                bound = ae["pca_samples"] - 1
                why += f", of which the PCA sees pca_samples = {ae['pca_samples']}"
            if r > bound:
                raise ConfigError(
                    f"config key '{key}': latent_dim {r} of scene {name} is above the rank of its training data: "
                    f"{why}, give at most {bound} independent directions; use latent_dim <= {bound} or add training frames"
                )


def _check_pca_width(config: dict) -> None:
    """No latent dimension above the width of its autoencoder's PCA layer (``latent.Autoencoder``: ``pca_dim``,
    0 standing for the first decoder width, or the latent dimension for a linear autoencoder), which keeps the
    directions the latent coordinates are taken from.  Every autoencoder a scene trains: its own, a variant's
    of another size, its conditioned one and each sizing-sweep point's."""
    for name, scene in config.get("scenes", {}).items():
        points = [(f"scenes.{name}.autoencoder", autoencoder_settings(config, name))]
        points += [(f"integrator_variants.{m}.autoencoder", autoencoder_settings(config, name, m)) for m in scene.get("variants", []) if own_autoencoder(config, m)]
        if conditioned(config, name):
            points.append((f"scenes.{name}.conditioning.autoencoder", conditioned_autoencoder_settings(config, name)))
        sweep = scene.get("sweep", {})
        for i in range(len(sweep.get("sizes", []))):
            points += [(f"scenes.{name}.sweep.sizes.{i}.autoencoder", sweep_point_settings(config, name, r, i)["autoencoder"]) for r in sweep.get("latent_dims", [])]
        for key, ae in points:
            r, widths, pca_dim = int(ae["latent_dim"]), list(ae["widths"]), int(ae.get("pca_dim") or 0)
            width = pca_dim or (widths[0] if widths else r)
            if width < r:
                why = f"pca_dim {pca_dim}" if pca_dim else f"pca_dim 0: the first decoder width of widths {widths}"
                raise ConfigError(f"config key '{key}': latent_dim {r} of scene {name} is above the width of the autoencoder's PCA layer, "
                                  f"{width} ({why}), whose directions the latent coordinates are taken from: use latent_dim <= {width}, "
                                  f"or a first width (or pca_dim) of at least {r}")  # fmt: skip


def _check_nm_study(config: dict) -> None:
    """The Neural Modes studies a scene switches on must fit the scene (the schema cannot say so)."""
    for name, scene in config.get("scenes", {}).items():
        study, key = scene.get("nm_study", {}), f"scenes.{name}.nm_study"
        on = [s for s, block in study.items() if block.get("enabled")]
        if on and scene.get("paper") != "wang2024":
            raise ConfigError(f"config key '{key}.{on[0]}.enabled': the Neural Modes studies run for scenes with paper wang2024; this one has paper {scene.get('paper')!r}")
        if "sheet" in on and scene.get("model") != "shell":
            raise ConfigError(f"config key '{key}.sheet.enabled': the sheet study needs a shell (membrane stress, Table 4); model is {scene.get('model')!r}")
        e = study.get("energy", {})
        if "energy" in on and e["train"] + e["validation"] + e["intervals"] > e["samples"]:
            raise ConfigError(
                f"config key '{key}.energy': {e['samples']} samples leave {e['samples'] - e['train'] - e['validation']} test samples "
                f"after {e['train']} training and {e['validation']} validation; need at least intervals = {e['intervals']}"
            )
        if "dynamics" in on:
            if scene.get("neural_modes", {}).get("boundary") != "dirichlet":
                raise ConfigError(f"config key '{key}.dynamics.enabled': subspace dynamics carry Dirichlet modes with the prescribed set; set neural_modes.boundary to dirichlet")
            if not any(q.get("split") == "test" for q in scene.get("sequences", [])):
                raise ConfigError(f"config key '{key}.dynamics.enabled': the scene has no sequence of split test to replay")
        if "keyframes" in on:
            poses, m = study["keyframes"]["poses"], scene.get("neural_modes", {}).get("modes")
            if len(poses) < 2 or any(len(p) != m for p in poses):
                raise ConfigError(f"config key '{key}.keyframes.poses': need at least two keyframes of {m} modal coordinates each (neural_modes.modes); got {poses}")
        if "aspect" in on:
            a = study["aspect"]
            if scene.get("model") != "shell":
                raise ConfigError(f"config key '{key}.aspect.enabled': the aspect-ratio study stretches a sheet; model is {scene.get('model')!r}, not 'shell'")
            if a["ratios"] % 2 == 0:
                raise ConfigError(f"config key '{key}.aspect.ratios': {a['ratios']} is even; use an odd count, so that both ends train and every other ratio is held out")
            if not a["ratio_min"] < a["ratio_max"]:
                raise ConfigError(f"config key '{key}.aspect': ratio_min {a['ratio_min']} must be below ratio_max {a['ratio_max']}")


def integrator_settings(config: dict, scene: str, method: str) -> dict:
    """A scene's integrator settings for ``method`` (self_supervised or a variant name)."""
    base = dict(config["scenes"][scene]["integrator"])
    if method == "self_supervised":
        return base
    if method not in config["scenes"][scene].get("variants", []):
        raise ConfigError(f"scene {scene!r} has no integrator variant {method!r}")
    base.update({k: v for k, v in config["integrator_variants"][method].items() if k != "autoencoder"})
    return base


def own_autoencoder(config: dict, method: str) -> bool:
    """Whether ``method`` (self_supervised or a variant name) trains its own autoencoder.

    A variant with an ``autoencoder`` block is a whole model of another size; every other method
    shares its scene's autoencoder.
    """
    return "autoencoder" in config["integrator_variants"].get(method, {})


def autoencoder_settings(config: dict, scene: str, method: str = "self_supervised") -> dict:
    """A scene's autoencoder settings for ``method``: the scene's, with the variant's ``autoencoder`` overrides."""
    base = dict(config["scenes"][scene]["autoencoder"])
    if method != "self_supervised":
        integrator_settings(config, scene, method)  # the scene must list the variant
        base.update(config["integrator_variants"][method].get("autoencoder", {}))
    return base


def scene_seeds(config: dict, scene: str) -> list[int]:
    """The seeds a scene's learned methods run with: its own ``seeds``, else the config's; the first
    ``max_seeds`` of them where the config caps them."""
    own = config["scenes"][scene].get("seeds")
    seeds = [int(s) for s in (own if own is not None else config["seeds"])]
    cap = config.get("max_seeds")
    return seeds if cap is None else seeds[: int(cap)]


def seed_dir(seed: int) -> str:
    """The folder of one seed's artefacts inside a method's folder: ``seed<k>``."""
    return f"seed{int(seed)}"


def autoencoder_dir(config: dict, scene: str, method: str = "self_supervised", seed: int | None = None) -> str:
    """Where ``method``'s autoencoder of ``scene`` lives for ``seed`` (default: the scene's first seed): the
    scene's, or the variant's own, in the seed's folder."""
    seed = scene_seeds(config, scene)[0] if seed is None else seed
    base = f"results/autoencoder/{scene}/{method}" if own_autoencoder(config, method) else f"results/autoencoder/{scene}"
    return f"{base}/{seed_dir(seed)}"


def _check_sweep_chosen(config: dict) -> None:
    """A sweep's recorded choice (``sweep.chosen.point``) is one of its points, and the size of one of the scene's
    methods: `all` trains the scenes at their recorded sizes without rerunning the sweep."""
    for name, scene in config.get("scenes", {}).items():
        sweep = scene.get("sweep", {})
        chosen = sweep.get("chosen")
        if not chosen or chosen["point"] == "none":
            continue
        key = f"scenes.{name}.sweep.chosen.point"
        r, i = (int(v) for v in chosen["point"][1:].split("_s"))
        if r not in sweep.get("latent_dims", []) or i >= len(sweep.get("sizes", [])):
            raise ConfigError(f"config key '{key}': {chosen['point']!r} is not a point of the scene's sweep (latent_dims "
                              f"{sweep.get('latent_dims', [])}, {len(sweep.get('sizes', []))} sizes)")  # fmt: skip
        if sweep_point_method(config, name, r, i) is None:
            size = sweep["sizes"][i]
            raise ConfigError(f"config key '{key}': the sweep chose latent {r} with decoder {size['autoencoder']} and integrator "
                              f"{size['integrator']} at commit {chosen['commit']}, but none of the scene's methods has that size; "
                              f"set scenes.{name}.autoencoder and integrator to it (or record the sweep's new choice)")  # fmt: skip


def sweep_point_settings(config: dict, scene: str, latent_dim: int, size_index: int) -> dict:
    """{"autoencoder", "integrator"} settings of one sizing-sweep point: those of the scene's
    ``sweep.method`` (its own integrator, or a variant's), at the point's latent size and widths."""
    sweep = config["scenes"][scene]["sweep"]
    method, size = sweep.get("method", "self_supervised"), sweep["sizes"][size_index]
    return {
        "autoencoder": dict(autoencoder_settings(config, scene, method), latent_dim=int(latent_dim), widths=list(size["autoencoder"])),
        "integrator": dict(integrator_settings(config, scene, method), widths=list(size["integrator"])),
    }


def sweep_point_method(config: dict, scene: str, latent_dim: int, size_index: int) -> str | None:
    """The scene's method (its own integrator or a variant) whose trained model is exactly this sweep
    point: the same autoencoder and integrator settings once the schema's defaults fill them in.  Its
    autoencoder and integrator, trained with the same seed, are the point's to the bit on the CPU, so the
    point measures them instead of training them again.  None when no method matches."""
    point = sweep_point_settings(config, scene, latent_dim, size_index)
    want = (with_defaults("autoencoder", point["autoencoder"], "sweep_point_method"), with_defaults("integrator", point["integrator"], "sweep_point_method"))
    for method in scene_methods(config, scene):
        have = (with_defaults("autoencoder", autoencoder_settings(config, scene, method), "sweep_point_method"),
                with_defaults("integrator", integrator_settings(config, scene, method), "sweep_point_method"))  # fmt: skip
        if have == want:
            return method
    return None


def scene_methods(config: dict, scene: str) -> list[str]:
    """Latent-integrator methods trained for a scene: its own, then its variants."""
    return ["self_supervised"] + list(config["scenes"][scene].get("variants", []))


def load_config(path, schema_path=SCHEMA) -> dict:
    """Read a YAML config and validate it."""
    with open(path) as fh:
        config = yaml.safe_load(fh) or {}
    try:
        return validate_config(config, schema_path)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
