"""Stage: the conditioned integrator over the seeds (see latentsim.stages.conditioning.summarise_conditioned)."""
from latentsim.stages.conditioning import summarise_conditioned
from latentsim.utils import run_stage


def main(smk):
    summarise_conditioned(
        smk.wildcards.scene,
        list(smk.input.metrics),
        list(smk.input.frame_rate),
        float(smk.params.tolerance),
        dict(smk.params.train),
        smk.output.table,
        smk.output.markdown,
        smk.output.figure,
    )


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
