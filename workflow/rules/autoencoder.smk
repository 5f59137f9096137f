# Autoencoder on the training frames (Li et al. sec. 3.2), PCA-initialised outer layers.
rule train_autoencoder:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
    output:
        model="results/autoencoder/{scene}/autoencoder.pt",
        latents="results/autoencoder/{scene}/latents.h5",
    log:
        "logs/autoencoder/{scene}.log",
    benchmark:
        "results/benchmarks/autoencoder/{scene}.tsv"
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
        model="results/autoencoder/{scene}/{method}/autoencoder.pt",
        latents="results/autoencoder/{scene}/{method}/latents.h5",
    log:
        "logs/autoencoder/{scene}/{method}.log",
    benchmark:
        "results/benchmarks/autoencoder/{scene}/{method}.tsv"
    wildcard_constraints:
        method="|".join(SIZED_METHODS) if SIZED_METHODS else "NO_METHOD",
