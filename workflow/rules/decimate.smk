rule decimate:
    input:
        mesh=mesh_work_input("normalize", "mesh.ply"),
    output:
        mesh=f"{MESH_WORK_DIR}/decimate/mesh.ply",
        meta=f"{MESH_WORK_DIR}/decimate/meta.json",
    log:
        f"{MESH_WORK_DIR}/logs/decimate.log",
    benchmark:
        f"{MESH_WORK_DIR}/benchmarks/decimate.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.decimate"),
        settings=stage_settings_json("decimate"),
        raycache=budget_raycache_json,
    shell:
        "python -m stages.decimate --input {input.mesh:q} --mesh {output.mesh:q} "
        "--meta {output.meta:q} --settings {params.settings:q} {params.raycache} 2> {log:q}"
