rule normalize:
    input:
        mesh=mesh_input,
    output:
        mesh=f"{RESULTS}/{{mesh}}/normalize/mesh.ply",
        transform=f"{RESULTS}/{{mesh}}/normalize/transform.json",
        meta=f"{RESULTS}/{{mesh}}/normalize/meta.json",
    log:
        f"{RESULTS}/{{mesh}}/logs/normalize.log",
    benchmark:
        f"{RESULTS}/{{mesh}}/benchmarks/normalize.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.normalize"),
        source=mesh_source,
        settings=stage_settings_json("normalize"),
    shell:
        "python -m stages.normalize --input {params.source:q} --mesh {output.mesh:q} "
        "--transform {output.transform:q} --meta {output.meta:q} --settings {params.settings:q} "
        "2> {log:q}"
