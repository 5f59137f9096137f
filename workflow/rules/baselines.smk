# Reduced-order baselines (PCA, linear modes, Fulton-style autoencoder latent space, Neural Modes) by reduced implicit Euler.
# One rollout per baseline, with the autoencoder of the scene's first seed (its coordinates and latent size;
# no seed changes these baselines' rollouts) ...
rule reduced_rollout:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        autoencoder=lambda w: f"{autoencoder_dir(config, w.scene)}/autoencoder.pt",
        neural_modes=lambda w: (
            [f"results/neural_modes/{w.scene}/neural_modes.pt"]
            if w.method == "neural_modes_reduced"
            else []
        ),
    output:
        rollout="results/rollout/{scene}/{method}/rollout.h5",
    log:
        "logs/rollout/{scene}/{method}.log",
    benchmark:
        "results/benchmarks/rollout/{scene}/{method}.tsv"
    wildcard_constraints:
        method="|".join(m for m in BASELINES if m not in SEEDED_BASELINES),
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
    params:
        reduced=scene_cfg("reduced"),
        method="{method}",
        seed=-1,
    script:
        "../scripts/reduced_rollout.py"


# ... and one per seed of those that reduce with a network trained per seed (the autoencoder's decoder).
use rule reduced_rollout as reduced_rollout_seeded with:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        autoencoder="results/autoencoder/{scene}/seed{seed}/autoencoder.pt",
    output:
        rollout="results/rollout/{scene}/{method}/seed{seed}/rollout.h5",
    log:
        "logs/rollout/{scene}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/rollout/{scene}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method="|".join(SEEDED_BASELINES),
    params:
        reduced=scene_cfg("reduced"),
        method="{method}",
        seed="{seed}",
