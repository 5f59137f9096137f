"""Stage: keyframing in modal coordinates, Fig. 6 (see latentsim.stages.neural_modes.keyframes_stage)."""
from latentsim.stages.neural_modes import keyframes_stage
from latentsim.utils import run_stage


def main(smk):
    out = smk.output
    keyframes_stage(smk.input.mesh, smk.input.model, smk.params.nm, out.motion, out.figure, out.paraview)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
