"""Stage: latent integrator training (see latentsim.stages.integrator.train_integrator): a scene's
method (rule train_integrator), or a conditioned scene's conditioned integrator or reference (rule
conditioned_integrator, whose params carry the box of conditions)."""
from latentsim.stages.integrator import train_integrator
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    p = smk.params.train
    conditioned = "conditioning" in p
    what = f"conditioned model {smk.wildcards.model}" if conditioned else f"method {smk.wildcards.method}"
    train_integrator(
        list(smk.input.trajectories) if conditioned else smk.input.trajectories,
        smk.input.autoencoder,
        p["settings"],
        p["seed"],
        p["device"],
        smk.output.model,
        smk.output.history,
        checkpoint=smk.params.checkpoint,
        progress=progress_enabled(smk.config.get("progress", True)),
        label=f"scene {smk.wildcards.scene}, {what}",
        conditioning=p.get("conditioning"),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
