# Latent integrator trained on the incremental potential (Li et al. sec. 3.3, Eqs. 4-6).
rule train_integrator:
    input:
        trajectories="results/sim/{scene}/trajectories.h5",
        autoencoder="results/autoencoder/{scene}/autoencoder.pt",
        latents="results/autoencoder/{scene}/latents.h5",
    output:
        model="results/integrator/{scene}/integrator.pt",
        history="results/integrator/{scene}/history.h5",
    log:
        "logs/integrator/{scene}.log",
    benchmark:
        "results/benchmarks/integrator/{scene}.tsv"
    conda:
        "../../envs/latentsim.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=240,
        gpu=gpu_count,
    params:
        train=training_params("integrator"),
        progress=progress(),
        checkpoint="results/integrator/{scene}/checkpoint.pt",
    script:
        "../scripts/train_integrator.py"
