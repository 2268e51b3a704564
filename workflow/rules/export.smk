rule export:
    input:
        unpack(export_inputs),
    output:
        **export_outputs(),
    log:
        f"{CELL}/logs/export.log",
    benchmark:
        f"{CELL}/benchmarks/export.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.export"),
        bake_dir=cell_dir("bake"),
        out_dir=cell_dir("export"),
        name=asset_name,
        settings=cell_settings_json("export"),
        source=mesh_source,
    shell:
        "python -m stages.export --mesh {input.mesh:q} --transform {input.transform:q} "
        "--bake-dir {params.bake_dir:q} --preview {input.preview:q} --out-dir {params.out_dir:q} "
        "--name {params.name:q} --settings {params.settings:q} --source={params.source:q} 2> {log:q}"
