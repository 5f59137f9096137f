"""Stage: the sizing sweep's choice and chart (see latentsim.stages.sweep.choose), and the choice against the config's
record of it (a warning in the log when they differ)."""
import logging

import pandas as pd

from latentsim.io import read_csv
from latentsim.report.tables import write_table
from latentsim.stages.sweep import choose, chosen_label, recorded_choice_note, sweep_chart
from latentsim.utils import run_stage


def main(smk):
    df = pd.concat([read_csv(p) for p in smk.input.points], ignore_index=True)
    table = choose(df, float(smk.params.tolerance), float(smk.params.pass_fraction)).assign(method=smk.params.method)
    write_table(table, smk.output.choice)
    sweep_chart(table, float(smk.params.tolerance), smk.wildcards.scene, smk.output.chart, method=smk.params.method)
    label = chosen_label(table, smk.params.sizes)
    note = recorded_choice_note(label, smk.params.recorded, smk.wildcards.scene)
    log = logging.getLogger("latentsim")
    (log.info if smk.params.recorded and smk.params.recorded["point"] == label else log.warning)(note)


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
