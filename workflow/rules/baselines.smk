# Reduced-order baselines (PCA, linear modes, Fulton-style autoencoder latent space, Neural Modes) by reduced implicit Euler.
rule reduced_rollout:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        autoencoder="results/autoencoder/{scene}/autoencoder.pt",
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
        method="|".join(BASELINES),
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
    params:
        reduced=scene_cfg("reduced"),
        method="{method}",
    script:
        "../scripts/reduced_rollout.py"
