"""Stage: ground truth (Eq. 9) of a Neural Modes study's sample sets (see latentsim.stages.neural_modes.ground_truth_stage)."""
from latentsim.stages.neural_modes import ground_truth_stage
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    ground_truth_stage(
        smk.input.mesh,
        smk.input.modes,
        smk.params.study,
        smk.params.gt,
        smk.output.ground_truth,
        progress=progress_enabled(smk.config.get("progress", True)),
        checkpoint=smk.params.checkpoint,
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
