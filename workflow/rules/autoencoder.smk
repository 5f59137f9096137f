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
        train=training_params("autoencoder"),
    script:
        "../scripts/train_autoencoder.py"
