"""Stage: subspace dynamics of Neural Modes and linear modes (see latentsim.stages.neural_modes.dynamics_stage)."""
from latentsim.stages.neural_modes import dynamics_stage
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
