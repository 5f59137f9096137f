# Autoregressive latent rollout of every test sequence from its first two frames and the BC history.
rule rollout:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        autoencoder="results/autoencoder/{scene}/autoencoder.pt",
        integrator="results/integrator/{scene}/integrator.pt",
    output:
        rollout="results/rollout/{scene}/rollout.h5",
    log:
        "logs/rollout/{scene}.log",
    benchmark:
        "results/benchmarks/rollout/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        rollout=scene_cfg("rollout"),
    script:
        "../scripts/rollout.py"
