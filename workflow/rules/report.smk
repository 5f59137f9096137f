# HTML pages of the tables, for `snakemake --report`: the report shows HTML inline, where it offers a CSV
# only for download. Each job renders tables another job wrote (latentsim.report.tables.write_table_html),
# so editing a page never reruns a computation.
from latentsim import labels


# The evaluation's tables: the glance (and the grid the landing page shows), Li et al. Tables 1-2,
# stability, model sizes, and the whole summary on one page.
rule report_summary_pages:
    input:
        glance="results/evaluation/glance.csv",
        table1="results/evaluation/table1.csv",
        table2="results/evaluation/table2.csv",
        stability="results/evaluation/stability.csv",
        divergence="results/evaluation/divergence.csv",
        sizes="results/evaluation/sizes.csv",
        summary="results/evaluation/summary.md",
    output:
        glance=report(
            "results/evaluation/glance.html",
            caption="../report/glance.rst",
            category="Summary",
            labels={"title": "At a glance"},
        ),
        glance_grid="results/evaluation/glance_grid.html",
        table1=report(
            "results/evaluation/table1.html",
            caption="../report/table1.rst",
            category="Summary",
            labels={"title": "Li et al. Table 1: timings"},
        ),
        table2=report(
            "results/evaluation/table2.html",
            caption="../report/table2.rst",
            category="Summary",
            labels={"title": "Li et al. Table 2: Jvp, latent step"},
        ),
        stability=report(
            "results/evaluation/stability.html",
            caption="../report/stability.rst",
            category="Summary",
            labels={"title": "Stability: frames survived"},
        ),
        divergence=report(
            "results/evaluation/divergence.html",
            caption="../report/divergence.rst",
            category="Summary",
            labels={"title": "Divergence over seeds"},
        ),
        sizes=report(
            "results/evaluation/sizes.html",
            caption="../report/sizes.rst",
            category="Summary",
            labels={"title": "Model sizes"},
        ),
        summary=report(
            "results/evaluation/summary.html",
            caption="../report/summary.rst",
            category="Summary",
            labels={"title": "Summary: every table"},
        ),
    log:
        "logs/report/summary_pages.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={
            "glance": "At a glance: every method on every scene",
            "table1": "Li et al. Table 1: full space against the latent integrator",
            "table2": "Li et al. Table 2: single-vertex Jvp and one latent step",
            "stability": "Stability: frames survived per method, seed and test sequence",
            "divergence": "Divergence over seeds (Li et al. Fig. 8): how often each method diverged",
            "sizes": "Model size per scene: ours, the paper's, the sizing sweep",
            "summary": "Summary: every table of the evaluation",
        },
    script:
        "../scripts/report_pages.py"


rule report_mesh_quality_page:
    input:
        table="results/mesh/quality.csv",
    output:
        table=report(
            "results/mesh/quality.html",
            caption="../report/mesh_quality.rst",
            category="Meshes",
        ),
    log:
        "logs/report/mesh_quality_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={"table": "Mesh quality: one row per scene"},
    script:
        "../scripts/report_pages.py"


rule report_sweep_page:
    input:
        choice="results/sweep/{scene}/choice.csv",
    output:
        choice=report(
            "results/sweep/{scene}/choice.html",
            caption="../report/sweep.rst",
            category="Sizing",
            subcategory="{scene}",
        ),
    log:
        "logs/report/{scene}_sweep_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles=lambda w: {"choice": f"Sizing sweep of {w.scene}: every point trained"},
    script:
        "../scripts/report_pages.py"


rule report_nm_summary_page:
    input:
        summary="results/neural_modes/summary.md",
    output:
        summary=report(
            "results/neural_modes/summary.html",
            caption="../report/nm_summary.rst",
            category="Neural Modes",
        ),
    log:
        "logs/report/nm_summary_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={"summary": "Neural Modes (Wang et al. 2024): one row per scene"},
        energy=labels.scene_energies(config, NM_SCENES),
    script:
        "../scripts/report_pages.py"


# The sheet study's tables (Wang et al. Tables 2, 3, 4, A1, Figs. 3-4), one page each and all on one.
rule report_nm_sheet_pages:
    input:
        tables="results/neural_modes/{scene}/sheet/tables.md",
        table2="results/neural_modes/{scene}/sheet/table2.csv",
        table3="results/neural_modes/{scene}/sheet/table3.csv",
        table4="results/neural_modes/{scene}/sheet/table4.csv",
        tableA1="results/neural_modes/{scene}/sheet/tableA1.csv",
        correlation="results/neural_modes/{scene}/sheet/correlation.csv",
        structure="results/neural_modes/{scene}/sheet/structure.csv",
    output:
        tables=report(
            "results/neural_modes/{scene}/sheet/tables.html",
            caption="../report/nm_tables.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        table2=report(
            "results/neural_modes/{scene}/sheet/table2.html",
            caption="../report/nm_table2.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        table3=report(
            "results/neural_modes/{scene}/sheet/table3.html",
            caption="../report/nm_table3.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        table4=report(
            "results/neural_modes/{scene}/sheet/table4.html",
            caption="../report/nm_table4.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        tableA1=report(
            "results/neural_modes/{scene}/sheet/tableA1.html",
            caption="../report/nm_tableA1.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        correlation=report(
            "results/neural_modes/{scene}/sheet/correlation.html",
            caption="../report/nm_correlation.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
        structure=report(
            "results/neural_modes/{scene}/sheet/structure.html",
            caption="../report/nm_structure.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
    log:
        "logs/report/{scene}_nm_sheet_pages.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={
            "table2": "Wang et al. Table 2: elastic energy error (validation, test)",
            "table3": "Wang et al. Table 3: early stopping of the supervised methods",
            "table4": "Wang et al. Table 4: membrane stress error",
            "tableA1": "Wang et al. Table A1: nodal force error",
            "correlation": "Mode collapse: eigenvalues of the latent directions' correlation",
            "structure": "Latent-space structure: the origin and the half-turn symmetry",
        },
        energy=lambda w: labels.scene_energy_note(config, w.scene),
    script:
        "../scripts/report_pages.py"


rule report_nm_energy_page:
    input:
        table5="results/neural_modes/{scene}/energy/table5.md",
    output:
        table5=report(
            "results/neural_modes/{scene}/energy/table5.html",
            caption="../report/nm_table5.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
    log:
        "logs/report/{scene}_nm_energy_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={},
        energy=lambda w: labels.scene_energy_note(config, w.scene),
    script:
        "../scripts/report_pages.py"


rule report_nm_dynamics_page:
    input:
        dynamics="results/neural_modes/{scene}/dynamics/dynamics.md",
    output:
        dynamics=report(
            "results/neural_modes/{scene}/dynamics/dynamics.html",
            caption="../report/nm_dynamics.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
    log:
        "logs/report/{scene}_nm_dynamics_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={},
    script:
        "../scripts/report_pages.py"


rule report_nm_aspect_page:
    input:
        aspect="results/neural_modes/{scene}/aspect/aspect.md",
    output:
        aspect=report(
            "results/neural_modes/{scene}/aspect/aspect.html",
            caption="../report/nm_aspect.rst",
            category="Neural Modes",
            subcategory="{scene}",
        ),
    log:
        "logs/report/{scene}_nm_aspect_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={},
    script:
        "../scripts/report_pages.py"


rule report_conditioned_page:
    input:
        summary="results/conditioned/{scene}/summary.md",
    output:
        summary=report(
            "results/conditioned/{scene}/summary.html",
            caption="../report/conditioned.rst",
            category="Conditioned integrator",
            subcategory="{scene}",
        ),
    log:
        "logs/report/{scene}_conditioned_page.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        titles={},
    script:
        "../scripts/report_pages.py"
