"""Stage: the scene's full-space Newton frame timed once (see latentsim.stages.evaluate.write_full_space_time)."""
from latentsim.stages.evaluate import write_full_space_time
from latentsim.utils import run_stage


def main(smk):
    write_full_space_time(smk.input.trajectories, smk.output.table, int(smk.params.frames))


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
