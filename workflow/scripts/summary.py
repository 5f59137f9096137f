"""Stage: summary tables and charts across scenes (see latentsim.stages.evaluate.summarise), and the record of the
scenes they hold (so that another config's run in the same folder is refused instead of replacing them)."""
import json

from latentsim.io import atomic_path
from latentsim.stages.evaluate import summarise
from latentsim.utils import run_stage


def main(smk):
    out = smk.output
    summarise(
        list(smk.input.metrics),
        out.csv,
        out.markdown,
        out.figure,
        table1_path=out.table1,
        table2_path=out.table2,
        stability_path=out.stability,
        reconstruction=list(smk.input.reconstruction),
        stress=list(smk.input.stress),
        stress_paths=(out.stress, out.stress_map),
        sizes=dict(smk.params.sizes),
        sweep_choices=dict(smk.params.sweep_choices),
        sizes_path=out.sizes,
        glance_path=out.glance,
        divergence_path=out.divergence,
        claims_path=out.claims,
    )
    with atomic_path(out.owner) as tmp:
        tmp.write_text(json.dumps({"scenes": list(smk.params.scenes)}, indent=1) + "\n")


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
