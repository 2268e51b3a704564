rule decimate:
    input:
        mesh=f"{RESULTS}/{{mesh}}/normalize/mesh.ply",
    output:
        mesh=f"{RESULTS}/{{mesh}}/decimate/mesh.ply",
        meta=f"{RESULTS}/{{mesh}}/decimate/meta.json",
    log:
        f"{RESULTS}/{{mesh}}/logs/decimate.log",
    benchmark:
        f"{RESULTS}/{{mesh}}/benchmarks/decimate.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.decimate"),
        settings=stage_settings_json("decimate"),
        raycache=budget_raycache_json,
    shell:
        "python -m stages.decimate --input {input.mesh:q} --mesh {output.mesh:q} "
        "--meta {output.meta:q} --settings {params.settings:q} {params.raycache} 2> {log:q}"
