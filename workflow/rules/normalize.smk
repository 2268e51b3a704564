rule normalize:
    input:
        mesh=mesh_input,
    output:
        mesh=f"{MESH_WORK_DIR}/normalize/mesh.ply",
        transform=f"{MESH_WORK_DIR}/normalize/transform.json",
        meta=f"{MESH_WORK_DIR}/normalize/meta.json",
    log:
        f"{MESH_WORK_DIR}/logs/normalize.log",
    benchmark:
        f"{MESH_WORK_DIR}/benchmarks/normalize.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.normalize"),
        source=mesh_source,
        settings=stage_settings_json("normalize"),
    shell:
        "python -m stages.normalize --input={params.source:q} --mesh {output.mesh:q} "
        "--transform {output.transform:q} --meta {output.meta:q} --settings {params.settings:q} "
        "2> {log:q}"
