# Autoencoder on the training frames (Li et al. sec. 3.2), PCA-initialised outer layers; one job per seed.
rule train_autoencoder:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
    output:
        model="results/autoencoder/{scene}/seed{seed}/autoencoder.pt",
        latents="results/autoencoder/{scene}/seed{seed}/latents.h5",
    log:
        "logs/autoencoder/{scene}/seed{seed}.log",
    benchmark:
        "results/benchmarks/autoencoder/{scene}/seed{seed}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=120,
        gpu=gpu_count,
    params:
        train=autoencoder_params,
    script:
        "../scripts/train_autoencoder.py"


# A variant that is a whole model of another size (integrator_variants.<name>.autoencoder) trains its own.
use rule train_autoencoder as train_variant_autoencoder with:
    output:
        model="results/autoencoder/{scene}/{method}/seed{seed}/autoencoder.pt",
        latents="results/autoencoder/{scene}/{method}/seed{seed}/latents.h5",
    log:
        "logs/autoencoder/{scene}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/autoencoder/{scene}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method="|".join(SIZED_METHODS) if SIZED_METHODS else "NO_METHOD",
