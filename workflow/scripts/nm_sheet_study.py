"""Stage: the Neural Modes sheet study, every method along its training (see latentsim.stages.neural_modes.sheet_study_stage)."""
from latentsim.stages.neural_modes import sheet_study_stage
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    sheet_study_stage(
        smk.input.mesh,
        smk.input.modes,
        smk.input.ground_truth,
        smk.params.nm,
        smk.output.study,
        progress=progress_enabled(smk.config.get("progress", True)),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
