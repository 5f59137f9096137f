"""Stage: subspace dynamics of Neural Modes and linear modes (see latentsim.nm_pipeline.dynamics_stage)."""
from latentsim.nm_pipeline import dynamics_stage
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    dynamics_stage(
        smk.input.trajectories,
        smk.input.model,
        smk.params.nm,
        dict(smk.output.items()),
        progress=progress_enabled(smk.config.get("progress", True)),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
