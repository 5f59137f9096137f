# One latent integrator for a range of time steps and moduli (config scenes.<scene>.conditioning; beyond
# Li et al. sec. 5): the scene at each condition, the autoencoder on every training condition, the
# conditioned integrator and a reference at each test condition, their evaluation and the summary.


wildcard_constraints:
    condition="|".join(CONDITION_NAMES) if CONDITION_NAMES else "NO_CONDITION",
    model="|".join(["conditioned", *CONDITION_NAMES]),


# The scene's sequences as the same motions in physical time at one condition's time step and modulus.
rule conditioned_simulate:
    input:
        mesh="results/mesh/{scene}/mesh.h5",
    output:
        trajectories="results/conditioned/{scene}/sim/{condition}.h5",
        paraview=directory("results/conditioned/{scene}/sim/{condition}_paraview"),
    log:
        "logs/conditioned/{scene}/sim/{condition}.log",
    benchmark:
        "results/benchmarks/conditioned/{scene}/sim/{condition}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
    params:
        sim=condition_sim_params,
    script:
        "../scripts/conditioned_simulate.py"


# The scene's autoencoder, trained on the frames of every training condition.
use rule train_autoencoder as conditioned_autoencoder with:
    input:
        trajectories=lambda w: list(condition_files("train")(w).values()),
    output:
        model="results/conditioned/{scene}/seed{seed}/autoencoder.pt",
        latents="results/conditioned/{scene}/seed{seed}/latents.h5",
    log:
        "logs/conditioned/{scene}/seed{seed}/autoencoder.log",
    benchmark:
        "results/benchmarks/conditioned/{scene}/seed{seed}/autoencoder.tsv"
    params:
        train=conditioned_autoencoder_params,


# The conditioned integrator (model "conditioned") or the reference at one test condition (model: its name).
rule conditioned_integrator:
    input:
        trajectories=lambda w: list(condition_files("train")(w).values()),
        autoencoder="results/conditioned/{scene}/seed{seed}/autoencoder.pt",
    output:
        model="results/conditioned/{scene}/seed{seed}/{model}/integrator.pt",
        history="results/conditioned/{scene}/seed{seed}/{model}/history.h5",
    log:
        "logs/conditioned/{scene}/seed{seed}/{model}.log",
    benchmark:
        "results/benchmarks/conditioned/{scene}/seed{seed}/{model}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
        gpu=gpu_count,
    params:
        train=conditioned_integrator_params,
        checkpoint="results/conditioned/{scene}/seed{seed}/{model}/checkpoint.pt",
    script:
        "../scripts/train_integrator.py"


# Every model at every held-out condition: errors, stress conditions, one step timed; the frame-rate pairs.
rule conditioned_evaluate:
    input:
        unpack(
            lambda w: {f"test_{n}": p for n, p in condition_files("test")(w).items()}
        ),
        unpack(lambda w: {f"model_{n}": p for n, p in conditioned_models(w).items()}),
        autoencoder="results/conditioned/{scene}/seed{seed}/autoencoder.pt",
    output:
        metrics="results/conditioned/{scene}/seed{seed}/metrics.csv",
        frame_rate="results/conditioned/{scene}/seed{seed}/frame_rate.csv",
    log:
        "logs/conditioned/{scene}/seed{seed}/evaluate.log",
    benchmark:
        "results/benchmarks/conditioned/{scene}/seed{seed}/evaluate.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=60,
    params:
        rollout=scene_cfg("rollout"),
        seed="{seed}",
    script:
        "../scripts/conditioned_evaluate.py"


# Over the seeds: the table (csv, Markdown) and the figure of error against time step and modulus.
rule conditioned_summary:
    input:
        metrics=lambda w: expand(
            "results/conditioned/{scene}/seed{seed}/metrics.csv",
            scene=w.scene,
            seed=scene_seeds(config, w.scene),
        ),
        frame_rate=lambda w: expand(
            "results/conditioned/{scene}/seed{seed}/frame_rate.csv",
            scene=w.scene,
            seed=scene_seeds(config, w.scene),
        ),
    output:
        table="results/conditioned/{scene}/summary.csv",
        markdown="results/conditioned/{scene}/summary.md",
        figure=report(
            "results/conditioned/{scene}/errors.png",
            category="Conditioned integrator",
            subcategory="{scene}",
            caption="../report/conditioned.rst",
        ),
    log:
        "logs/conditioned/{scene}/summary.log",
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        tolerance=lambda w: config["scenes"][w.scene]["sweep"]["tolerance"],
        train=lambda w: {
            n: c
            for n, c in conditions(config, w.scene).items()
            if c["split"] == "train"
        },
    script:
        "../scripts/conditioned_summary.py"
