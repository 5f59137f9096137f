"""Stage: latent integrator training (see latentsim.stages.integrator.train_integrator)."""
from latentsim.stages.integrator import train_integrator
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    p = smk.params.train
    train_integrator(
        smk.input.trajectories,
        smk.input.autoencoder,
        p["settings"],
        p["seed"],
        p["device"],
        smk.output.model,
        smk.output.history,
        checkpoint=smk.params.checkpoint,
        progress=progress_enabled(smk.config.get("progress", True)),
        label=f"scene {smk.wildcards.scene}, method {smk.wildcards.method}",
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
