# Latent integrator of one method: the scene's self-supervised one (Li et al. sec. 3.3, Eqs. 4-6)
# or a variant (supervised baseline, ablation) from config integrator_variants; one job per seed.
rule train_integrator:
    input:
        unpack(method_autoencoder("autoencoder", "latents")),
        trajectories="results/sim/{scene}/trajectories.h5",
    output:
        model="results/integrator/{scene}/{method}/seed{seed}/integrator.pt",
        history="results/integrator/{scene}/{method}/seed{seed}/history.h5",
    log:
        "logs/integrator/{scene}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/integrator/{scene}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method="|".join(INTEGRATOR_METHODS),
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
        gpu=gpu_count,
    params:
        train=integrator_params,
        checkpoint="results/integrator/{scene}/{method}/seed{seed}/checkpoint.pt",
    script:
        "../scripts/train_integrator.py"
