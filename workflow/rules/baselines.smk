# Reduced-order baselines (PCA subspace, Fulton-style autoencoder latent space) by reduced implicit Euler.
rule reduced_rollout:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        autoencoder="results/autoencoder/{scene}/autoencoder.pt",
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
