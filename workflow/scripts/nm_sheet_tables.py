"""Stage: Tables 2, 3, 4, A1 and Figs. 2, 3, 4 of the sheet study (see latentsim.nm_pipeline.sheet_tables_stage)."""
from latentsim.nm_pipeline import sheet_tables_stage
from latentsim.utils import run_stage


def main(smk):
    sheet_tables_stage(smk.input.study, dict(smk.output.items()))


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
