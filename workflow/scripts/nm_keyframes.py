"""Stage: keyframing in modal coordinates, Fig. 6 (see latentsim.nm_pipeline.keyframes_stage)."""
from latentsim.nm_pipeline import keyframes_stage
from latentsim.utils import run_stage


def main(smk):
    out = smk.output
    keyframes_stage(smk.input.mesh, smk.input.model, smk.params.nm, out.motion, out.figure, out.paraview)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
