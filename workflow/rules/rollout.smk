# Autoregressive rollout of one method on every test sequence from its first two frames and the BC history.
rule rollout:
    input:
        unpack(method_autoencoder("autoencoder")),
        trajectories="results/sim/{scene}/trajectories.h5",
        integrator="results/integrator/{scene}/{method}/seed{seed}/integrator.pt",
    output:
        rollout="results/rollout/{scene}/{method}/seed{seed}/rollout.h5",
        runtime="results/rollout/{scene}/{method}/seed{seed}/runtime.npz",
        torch_export="results/rollout/{scene}/{method}/seed{seed}/runtime.pt",
    log:
        "logs/rollout/{scene}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/rollout/{scene}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method="|".join(INTEGRATOR_METHODS),
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        rollout=scene_cfg("rollout"),
        method="{method}",
        seed="{seed}",
    script:
        "../scripts/rollout.py"
