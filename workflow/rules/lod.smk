rule lod:
    input:
        unpack(lod_inputs),
    output:
        **lod_outputs(),
    log:
        f"{CELL}/logs/lod.log",
    benchmark:
        f"{CELL}/benchmarks/lod.tsv"
    conda:
        CONDA_ENV
    threads: 1
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.lod"),
        device=DEVICE,
        bake_dir=cell_dir("bake"),
        out_dir=cell_dir("lod"),
        name=asset_name,
        settings=lod_settings_json,
    shell:
        "python -m stages.lod --mesh {input.mesh:q} --field {input.field:q} --eval {input.eval:q} "
        "--transform {input.transform:q} --bake-dir {params.bake_dir:q} --export-meta {input.export_meta:q} "
        "--out-dir {params.out_dir:q} --name {params.name:q} --settings {params.settings:q} "
        "--threads {threads} --device {params.device} 2> {log:q}"
