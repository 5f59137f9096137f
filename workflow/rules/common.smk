# Shared helpers: config validation on load and the params each rule receives.
import json
import os
import sys

from snakemake.exceptions import WorkflowError

from latentsim import rule_params
from latentsim.labels import (
    BASELINES,
    SEEDED_BASELINES,
    layers_text,
    parse_label,
    point_label,
)
from latentsim.mesh import MeshError
from latentsim.mesh.sources import check_user_mesh, user_mesh_path
from latentsim.config import (
    ConfigError,
    autoencoder_dir,
    autoencoder_settings,
    conditioned,
    conditions,
    integrator_settings,
    own_autoencoder,
    scene_methods,
    scene_seeds,
    seed_dir,
    sweep_point_method,
    validate_config,
)

try:
    validate_config(config, workflow.source_path("../schemas/config.schema.yaml"))
    # a user's own mesh file must exist before any job runs (with outputs present, Snakemake would
    # otherwise skip a missing input silently and keep the old mesh)
    for _name, _scene in config["scenes"].items():
        if _scene["mesh"]["generator"] == "file" and _scene["mesh"].get("file"):
            check_user_mesh(
                _scene["mesh"]["file"],
                config["meshes"],
                f"config key 'scenes.{_name}.mesh.file'",
            )
        for _i, _q in enumerate(_scene["contact"]["colliders"]):
            if _q["type"] == "mesh":
                check_user_mesh(
                    _q["file"],
                    config["meshes"],
                    f"config key 'scenes.{_name}.contact.colliders.{_i}.file'",
                )
except (ConfigError, MeshError) as e:
    raise WorkflowError(f"invalid config: {e}")

SCENES = sorted(config["scenes"])


def run_header():
    """What a run's log records at its start, for its record (tools/run_record.py): the workflow's commit
    (``-dirty`` with uncommitted changes; unknown outside a git checkout) and the machine.
    """
    import subprocess

    from latentsim.provenance import environment

    git = [
        "git",
        "-C",
        workflow.basedir,
        "describe",
        "--always",
        "--dirty",
        "--abbrev=7",
    ]
    commit = subprocess.run(git, capture_output=True, text=True).stdout.strip()
    env = environment()
    return [
        f"latentsim commit: {commit or 'unknown'}",
        f"latentsim machine: {env['processor']}, {env['cpus']} cpus",
    ]


INTEGRATOR_METHODS = ["self_supervised"] + sorted(config["integrator_variants"])
# variants that are whole models of another size: they train their own autoencoder
SIZED_METHODS = [m for m in INTEGRATOR_METHODS if own_autoencoder(config, m)]
METHODS = INTEGRATOR_METHODS + list(BASELINES)


wildcard_constraints:
    scene="|".join(SCENES) if SCENES else "NO_SCENE",
    method="|".join(METHODS),
    point=r"r\d+_s\d+",
    seed=r"\d+",


# The params of the rules: built in latentsim.rule_params (both papers), from the job's wildcards here.
def scene_cfg(*keys):
    """Input function: the named keys of the scene's config, as one plain dict."""

    def get(wildcards):
        return rule_params.scene_slice(config, wildcards.scene, keys)

    return get


def mesh_sources():
    return rule_params.mesh_sources(config)


def user_mesh(wildcards):
    """Input function: a scene's own mesh file (not a pinned one), so that editing it reruns the scene."""
    mesh = config["scenes"][wildcards.scene]["mesh"]
    if mesh.get("generator") != "file" or not mesh.get("file"):
        return []
    path = user_mesh_path(mesh["file"], config["meshes"])
    return [] if path is None else [str(path)]


def collider_files(wildcards):
    """Input function: a scene's own mesh colliders' files (not pinned ones), so that editing one reruns the scene."""
    colliders = config["scenes"][wildcards.scene]["contact"]["colliders"]
    paths = [
        user_mesh_path(q["file"], config["meshes"])
        for q in colliders
        if q["type"] == "mesh"
    ]
    return [str(p) for p in paths if p is not None]


def autoencoder_params(wildcards):
    """Input function: the autoencoder settings of the scene (or of the variant ``method``), seed and device."""
    method = getattr(wildcards, "method", "self_supervised")
    return rule_params.autoencoder_params(
        config, wildcards.scene, wildcards.seed, method
    )


def method_autoencoder(*names):
    """Input function: the named files (autoencoder, latents) of the autoencoder that ``method`` decodes with,
    of the job's seed (the scene's first seed where the job has none)."""

    def get(wildcards):
        seed = int(wildcards.seed) if "seed" in wildcards.keys() else None
        d = autoencoder_dir(config, wildcards.scene, wildcards.method, seed)
        files = {"autoencoder": f"{d}/autoencoder.pt", "latents": f"{d}/latents.h5"}
        return {n: files[n] for n in names}

    return get


def integrator_params(wildcards):
    """Input function: a method's integrator settings (scene's, with the variant's overrides)."""
    return rule_params.integrator_params(
        config, wildcards.scene, wildcards.method, wildcards.seed
    )


def seeded(method):
    """Whether ``method`` is trained (or reduces with a model trained) once per seed."""
    return method in INTEGRATOR_METHODS or method in SEEDED_BASELINES


def rollout_path(scene, method, seed):
    """A method's rollout for one seed: in the seed's folder, or the method's own where no seed changes it."""
    d = f"results/rollout/{scene}/{method}"
    return f"{d}/{seed_dir(seed)}/rollout.h5" if seeded(method) else f"{d}/rollout.h5"


def rollout_paths(scene):
    """The rollout of every method of a scene for every seed: its latent integrators and its reduced baselines."""
    methods = scene_methods(config, scene) + config["scenes"][scene]["baselines"]
    paths = [
        rollout_path(scene, m, s) for m in methods for s in scene_seeds(config, scene)
    ]
    return list(dict.fromkeys(paths))


def first_seed_rollouts(scene):
    """The rollout of every method of a scene for the scene's first seed (what the pictures show)."""
    methods = scene_methods(config, scene) + config["scenes"][scene]["baselines"]
    return [rollout_path(scene, m, scene_seeds(config, scene)[0]) for m in methods]


def scene_rollouts(wildcards):
    """Input function: the rollout of every method of a scene."""
    return rollout_paths(wildcards.scene)


def sweep_points(scene):
    """Wildcard values r<latent_dim>_s<size index> of a scene's sizing sweep."""
    sw = config["scenes"][scene]["sweep"]
    return [
        point_label(r, i) for r in sw["latent_dims"] for i in range(len(sw["sizes"]))
    ]


def sweep_params(wildcards):
    """Input function: the full settings of one sweep point."""
    r, i = parse_label(wildcards.point)
    return rule_params.sweep_params(config, wildcards.scene, r, i, wildcards.seed)


def sweep_point_models(wildcards):
    """Input function: the autoencoder and integrator of the scene's method that is exactly this sweep point
    (same settings, same seed), which the point measures instead of training again; none when no method is.
    """
    r, i = parse_label(wildcards.point)
    method = sweep_point_method(config, wildcards.scene, r, i)
    if method is None:
        return {}
    seed = int(wildcards.seed)
    return {
        "autoencoder": f"{autoencoder_dir(config, wildcards.scene, method, seed)}/autoencoder.pt",
        "integrator": f"results/integrator/{wildcards.scene}/{method}/{seed_dir(seed)}/integrator.pt",
    }


def sweep_earlier_metrics(wildcards):
    """Input function: the point's metrics of the seeds run before this one, which may decide that it cannot
    pass (then this seed is not trained)."""
    earlier = rule_params.earlier_seeds(config, wildcards.scene, wildcards.seed)
    return [
        f"results/sweep/{wildcards.scene}/{wildcards.point}/{seed_dir(s)}/metrics.csv"
        for s in earlier
    ]


def sweep_prune_params(wildcards):
    """Params: what decides whether the point's earlier seeds leave it a chance to pass."""
    return rule_params.sweep_prune_params(config, wildcards.scene, wildcards.seed)


def sweep_tolerance(wildcards):
    return config["scenes"][wildcards.scene]["sweep"]["tolerance"]


def sweep_results(wildcards):
    """Every point of a scene's sweep, for every seed of the scene."""
    return [
        f"results/sweep/{wildcards.scene}/{p}/{seed_dir(s)}/metrics.csv"
        for p in sweep_points(wildcards.scene)
        for s in scene_seeds(config, wildcards.scene)
    ]


def sweep_choices():
    """{scene: results/sweep/<scene>/choice.csv} for the scenes with a sizing sweep (the target ``sizing``)."""
    return {
        scene: f"results/sweep/{scene}/choice.csv"
        for scene in SCENES
        if sweep_points(scene)
    }


SUMMARY_OWNER = "results/evaluation/summary_config.json"


def summary_owner(wildcards):
    """Input function of the summary (it adds no input): refuses, while the DAG is built and so before any job, to
    replace a summary (and so the report) whose scenes this run's config lacks (another config's run in this
    folder: the summary would show only this config's scenes); a dry run warns."""
    if not os.path.exists(SUMMARY_OWNER):
        return []
    with open(SUMMARY_OWNER) as f:
        owner = json.load(f)
    lost = sorted(set(owner.get("scenes", [])) - set(SCENES))
    if not lost:
        return []
    message = (
        f"results/evaluation/summary.* and the report hold scenes this config lacks ({', '.join(lost)}): they were "
        f"written by the run of another config (scenes {', '.join(owner.get('scenes', []))}), and this run would "
        "replace them. Run this config in a folder of its own (a copy of the checkout), or delete "
        "results/evaluation/summary* to let it replace them (each scene's own results stay under its name either way)."
    )
    if workflow.dryrun:
        print(f"Warning: {message}", file=sys.stderr)
        return []
    raise WorkflowError(message)


def reported_sweep_choices():
    """The sweep choices that ``all`` shows: every one with ``sizing_in_all``, else those of the sweeps that have run
    (``all`` trains the scenes at their recorded sizes and reruns no sweep)."""
    return {
        scene: path
        for scene, path in sweep_choices().items()
        if config["sizing_in_all"] or os.path.exists(path)
    }


def model_sizes():
    """{scene: the config's latent size and layers (as Li et al. Table 2 prints them), sweep tolerance}."""
    out = {}
    for scene in SCENES:
        sc = config["scenes"][scene]
        ae, integ = sc["autoencoder"], sc["integrator"]
        out[scene] = {
            "latent_dim": ae["latent_dim"],
            "decoder_layers": layers_text(ae["widths"], ae.get("pca_dim")),
            "integrator_layers": layers_text(integ["widths"]),
        }
        if sweep_points(scene):
            out[scene]["tolerance"] = sc["sweep"]["tolerance"]
        variants = {}
        for m in scene_methods(config, scene):
            if own_autoencoder(config, m):
                a = autoencoder_settings(config, scene, m)
                variants[m] = {
                    "latent_dim": a["latent_dim"],
                    "decoder_layers": layers_text(a["widths"], a.get("pca_dim")),
                    "integrator_layers": layers_text(
                        integrator_settings(config, scene, m)["widths"]
                    ),
                }
        if variants:
            out[scene]["variants"] = variants
    return out


def gpu_count(wildcards):
    return 1 if config["device"] == "cuda" else 0


def scene_artefacts(scene):
    """The data artefacts of a scene's chain up to its rollouts (mesh, simulation, each method's
    autoencoder and integrator, and the deployable runtime its rollout writes): targets of rule all, so that
    one a reader found corrupt and moved aside is written again on the next run (Snakemake skips a missing
    file that no job needs).
    """
    out = [f"results/mesh/{scene}/mesh.h5", f"results/sim/{scene}/trajectories.h5"]
    for m in scene_methods(config, scene):
        for seed in scene_seeds(config, scene):
            d = autoencoder_dir(config, scene, m, seed)
            i = f"results/integrator/{scene}/{m}/{seed_dir(seed)}"
            r = f"results/rollout/{scene}/{m}/{seed_dir(seed)}"
            out += [f"{d}/autoencoder.pt", f"{d}/latents.h5"]
            out += [f"{i}/integrator.pt", f"{i}/history.h5"]
            out += [f"{r}/runtime.npz", f"{r}/runtime.pt"]
    return list(dict.fromkeys(out))


# --- the conditioned integrator (workflow/rules/conditioning.smk) ---
CONDITIONED_SCENES = [s for s in SCENES if conditioned(config, s)]
CONDITION_NAMES = sorted({n for s in CONDITIONED_SCENES for n in conditions(config, s)})


def condition_files(split):
    """Input function: the trajectories of a conditioned scene's conditions of one split, by name."""

    def get(wildcards):
        return {
            n: f"results/conditioned/{wildcards.scene}/sim/{n}.h5"
            for n, c in conditions(config, wildcards.scene).items()
            if c["split"] == split
        }

    return get


def sim_params(wildcards):
    """Input function: the scene's simulation settings."""
    return rule_params.sim_params(config, wildcards.scene)


def condition_sim_params(wildcards):
    """Input function: the scene's simulation settings and the condition (time step, modulus, split)."""
    return rule_params.condition_sim_params(
        config, wildcards.scene, wildcards.condition
    )


def conditioned_autoencoder_params(wildcards):
    """Input function: the conditioned scene's autoencoder settings, seed and device."""
    return rule_params.conditioned_autoencoder_params(
        config, wildcards.scene, wildcards.seed
    )


def conditioned_integrator_params(wildcards):
    """Input function: the settings, seed and device of the conditioned integrator or of one reference."""
    return rule_params.conditioned_integrator_params(
        config, wildcards.scene, wildcards.model, wildcards.seed
    )


def conditioned_models(wildcards):
    """Input function: the conditioned integrator and every test condition's reference, of the job's seed."""
    d = f"results/conditioned/{wildcards.scene}/seed{wildcards.seed}"
    tests = condition_files("test")(wildcards)
    return {"conditioned": f"{d}/conditioned/integrator.pt"} | {
        n: f"{d}/{n}/integrator.pt" for n in tests
    }


def conditioned_targets():
    """The summaries of the conditioned scenes."""
    return [
        f"results/conditioned/{scene}/{name}"
        for scene in CONDITIONED_SCENES
        for name in ("summary.csv", "summary.md", "errors.png")
    ]


def all_targets():
    out = [path for scene in SCENES for path in scene_artefacts(scene)]
    out += [path for scene in SCENES for path in rollout_paths(scene)]
    out += expand("results/evaluation/{scene}/metrics.csv", scene=SCENES)
    out += expand("results/evaluation/{scene}/frames.png", scene=SCENES)
    out += list(reported_sweep_choices().values())
    out += ["results/evaluation/summary.csv", "results/evaluation/summary.md"]
    out += ["results/mesh/quality.csv"]
    out += conditioned_targets()
    return out


def report_pages():
    """The HTML pages of the report's tables (see report.smk), the input of the default target: one per
    Markdown target (its page job names it), one per reported sweep choice and the mesh quality table's.
    """
    md = [t for t in all_targets() + neural_modes_targets() if t.endswith(".md")]
    pages = [t.removesuffix(".md") + ".html" for t in md]
    pages += [
        c.removesuffix(".csv") + ".html" for c in reported_sweep_choices().values()
    ]
    return pages + ["results/mesh/quality.html"]


# --- Neural Modes (workflow/rules/neural_modes.smk) ---
NM_SCENES = sorted(s for s in SCENES if config["scenes"][s].get("paper") == "wang2024")


def nm_study_scenes(study):
    """The Neural Modes scenes whose ``nm_study.<study>`` is enabled."""
    return [s for s in NM_SCENES if config["scenes"][s]["nm_study"][study]["enabled"]]


def neural_modes_targets():
    """Every Neural Modes artefact of the configured wang2024 scenes (rule all's input); none without any."""
    if not NM_SCENES:
        return []
    out = [f"results/neural_modes/{s}/neural_modes.pt" for s in NM_SCENES]
    out += ["results/neural_modes/summary.csv", "results/neural_modes/summary.md"]
    last = {
        "sheet": "sheet/tables.md",
        "energy": "energy/table5.md",
        "dynamics": "dynamics/dynamics.md",
        "keyframes": "keyframes/keyframes.png",
        "aspect": "aspect/aspect.md",
    }
    for study, path in last.items():
        out += [f"results/neural_modes/{s}/{path}" for s in nm_study_scenes(study)]
    return out


def nm_modes_params(wildcards):
    """Input function: what the linear modes depend on (model, material, modes, boundary, normalization)."""
    return rule_params.nm_modes_params(config, wildcards.scene)


def nm_train_params(wildcards):
    """Input function: the scene's model, material and whole neural_modes block."""
    return rule_params.nm_train_params(config, wildcards.scene)


def nm_ground_truth_params(wildcards):
    """Input function: what a study's ground truth depends on (its sample sets, the modes, the box)."""
    return rule_params.nm_ground_truth_params(config, wildcards.scene, wildcards.study)


def nm_study_params(study):
    """Input function: a study's nm_study block, the seed and what else it reads of the scene."""

    def get(wildcards):
        seed = int(wildcards.seed) if "seed" in wildcards.keys() else None
        return rule_params.nm_study_params(config, wildcards.scene, study, seed)

    return get
