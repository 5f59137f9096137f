"""Stage: Neural Modes conditioned on a sheet's aspect ratio, Sec. 4.3 / Fig. A2 (see latentsim.stages.neural_modes.aspect_stage)."""
from latentsim.stages.neural_modes import aspect_stage
from latentsim.utils import progress_enabled, run_stage


def main(smk):
    out = {k: getattr(smk.output, k) for k in ("model", "family", "csv", "markdown", "figure", "paraview")}
    aspect_stage(smk.input.mesh, smk.params.nm, out, progress=progress_enabled(smk.config.get("progress", True)))


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
