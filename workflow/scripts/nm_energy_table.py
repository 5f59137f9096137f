"""Stage: Table 5, PCA+AE against Neural Modes on a solid (see latentsim.nm_pipeline.energy_table_stage)."""
from latentsim.nm_pipeline import energy_table_stage
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
