"""Stage: summary table and speed-accuracy chart across scenes (see latentsim.evaluate)."""
from latentsim.evaluate import summarise
from latentsim.utils import run_stage


def main(smk):
    summarise(list(smk.input.metrics), smk.output.csv, smk.output.markdown, smk.output.figure)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
