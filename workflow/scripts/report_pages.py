"""Stage: HTML pages of the report's tables (see latentsim.report.tables.write_table_html).

Every output but ``glance_grid`` is the page of the input of the same name; ``glance`` is the glance
page, which also writes ``glance_grid``, the grid on the report's landing page."""
from latentsim.report.tables import write_glance_html, write_table_html
from latentsim.utils import run_stage


def main(smk):
    titles = dict(smk.params.titles)
    for name, page in smk.output.items():
        if name == "glance":
            write_glance_html(smk.input.glance, page, smk.output.glance_grid, title=titles[name])
        elif name != "glance_grid":
            write_table_html(getattr(smk.input, name), page, title=titles.get(name))


run_stage(snakemake, main)  # noqa: F821 (injected by Snakemake)
