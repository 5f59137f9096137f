"""Stage: Table 5, PCA+AE against Neural Modes on a solid (see latentsim.stages.neural_modes.energy_table_stage)."""
from latentsim.stages.neural_modes import energy_table_stage
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    energy_table_stage(
        smk.input.mesh,
        smk.input.ground_truth,
        smk.input.model,
        smk.params.nm,
        smk.output.csv,
        smk.output.markdown,
        smk.output.history,
        progress=progress_enabled(smk.config.get("progress", True)),
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
