"""Stage: Tables 2, 3, 4, A1 and Figs. 2, 3, 4 of the sheet study (see latentsim.stages.neural_modes.sheet_tables_stage)."""
from latentsim.stages.neural_modes import sheet_tables_stage
from latentsim.utils import run_stage


def main(smk):
    sheet_tables_stage(list(smk.input.study), dict(smk.output.items()))


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
