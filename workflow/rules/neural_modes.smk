# Neural Modes (Wang et al. 2024): linear modes, self-supervised training, summary, for wang2024 scenes.
from functools import partial

from latentsim import nm_pipeline

NM_SCENES = sorted(s for s in SCENES if config["scenes"][s].get("paper") == "wang2024")


# Every Neural Modes artefact of the configured wang2024 scenes (rule all's input).
neural_modes_targets = partial(nm_pipeline.targets, NM_SCENES)


# Lowest vibration modes of the rest state (sparse shift-invert), Dirichlet or rigid-free.
rule nm_linear_modes:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
    output:
        modes="results/neural_modes/{scene}/linear_modes.h5",
    log:
        "logs/neural_modes/{scene}_linear_modes.log",
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        nm=lambda wildcards: nm_pipeline.scene_params(config, wildcards.scene),
    script:
        "../scripts/nm_linear_modes.py"


# Self-supervised Neural Modes (Eq. 13): energy + orthogonality + origin, L-BFGS.
rule nm_train:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
        modes="results/neural_modes/{scene}/linear_modes.h5",
    output:
        model="results/neural_modes/{scene}/neural_modes.pt",
        history="results/neural_modes/{scene}/history.h5",
    log:
        "logs/neural_modes/{scene}_train.log",
    benchmark:
        "results/benchmarks/neural_modes/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=8000,
        runtime=240,
    params:
        nm=lambda wildcards: nm_pipeline.scene_params(config, wildcards.scene),
        seed=config["seed"],
    script:
        "../scripts/nm_train.py"


# One row per scene: energy against linear modes, constraint, origin, latent-direction correlation.
rule nm_summary:
    input:
        histories=expand("results/neural_modes/{scene}/history.h5", scene=NM_SCENES),
    output:
        csv=report(
            "results/neural_modes/summary.csv",
            caption="../report/nm_summary.rst",
            category="Neural Modes",
        ),
        markdown="results/neural_modes/summary.md",
    log:
        "logs/neural_modes/summary.log",
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        scenes=NM_SCENES,
    script:
        "../scripts/nm_summary.py"
