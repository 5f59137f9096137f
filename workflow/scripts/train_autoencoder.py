"""Stage: autoencoder training (see latentsim.stages.autoencoder.train_autoencoder)."""
from latentsim.stages.autoencoder import train_autoencoder
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    p = smk.params.train
    method = getattr(smk.wildcards, "method", None)
    train_autoencoder(
        smk.input.trajectories,
        p["settings"],
        p["seed"],
        p["device"],
        smk.output.model,
        smk.output.latents,
        progress=progress_enabled(smk.config.get("progress", True)),
        label=f"scene {smk.wildcards.scene}" + (f", method {method}" if method else ""),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
