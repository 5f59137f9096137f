# Mesh preparation: generate or fetch, tetrahedralise, select Dirichlet vertices, check quality.
rule prepare_mesh:
    input:
        user_mesh,
    output:
        mesh="results/mesh/{scene}/mesh.h5",
        vtu="results/mesh/{scene}/mesh.vtu",
    log:
        "logs/mesh/{scene}.log",
    conda:
        "../../envs/latentsim.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        scene=scene_cfg("model", "mesh", "dirichlet"),
        sources=mesh_sources(),
    script:
        "../scripts/prepare_mesh.py"


# One row per scene of the quality statistics its mesh.h5 records (dihedral angles, radius-edge ratio, ...).
rule mesh_quality_table:
    input:
        meshes=expand("results/mesh/{scene}/mesh.h5", scene=SCENES),
    output:
        table="results/mesh/quality.csv",
    log:
        "logs/mesh/quality_table.log",
    conda:
        "../../envs/latentsim.yaml"
    params:
        scenes=SCENES,
    script:
        "../scripts/mesh_quality_table.py"
