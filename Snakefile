# latentsim: full-space simulation -> autoencoder -> latent integrator -> rollout -> evaluation.
# Table of contents only: the rules live in workflow/rules/, the code in src/latentsim/.
from snakemake.utils import min_version

min_version("8.0")


# The default config holds every paper scene; --configfile replaces it (it is not merged into it),
# and --config key=value overrides either.
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/autoencoder.smk"
include: "workflow/rules/integrator.smk"
include: "workflow/rules/rollout.smk"
include: "workflow/rules/baselines.smk"
include: "workflow/rules/sweep.smk"
include: "workflow/rules/conditioning.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/neural_modes.smk"
include: "workflow/rules/report.smk"


# The commit and machine of every run, in its log (.snakemake/log/), for tools/run_record.py.
onstart:
    for line in run_header():
        logger.info(line)


# The report's landing page: snakemake --report report.html (docs/report.md).
report: "workflow/report/workflow.rst"


# Default target: every stage of every configured scene, the summary tables and their report pages.
rule all:
    default_target: True
    input:
        all_targets(),
        neural_modes_targets(),
        report_pages(),


# The sizing sweeps (``sweep`` of each scene): every point trained over the seeds, each scene's choice and its report
# page.  Not part of ``all`` (unless ``sizing_in_all``), which trains the sizes the config records (``sweep.chosen``).
rule sizing:
    input:
        list(sweep_choices().values()),
        [c.removesuffix(".csv") + ".html" for c in sweep_choices().values()],
