rule lod:
    input:
        unpack(lod_inputs),
    output:
        usda=f"{CELL}/lod/model_lods.usda",
        usdz=f"{CELL}/lod/model_lods.usdz",
        glb=f"{CELL}/lod/model_lods.glb",
        figure=f"{CELL}/lod/levels.png",
        meta=f"{CELL}/lod/meta.json",
    log:
        f"{CELL}/logs/lod.log",
    benchmark:
        f"{CELL}/benchmarks/lod.tsv"
    conda:
        CONDA_ENV
    threads: 2
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.lod"),
        device=DEVICE,
        bake_dir=cell_dir("bake"),
        out_dir=cell_dir("lod"),
        name=asset_name,
        settings=cell_settings_json("lod"),
        bake_settings=cell_settings_json("bake"),
        export_settings=cell_settings_json("export"),
        decimate_settings=stage_settings_json("decimate"),
    shell:
        "python -m stages.lod --mesh {input.mesh:q} --field {input.field:q} --eval {input.eval:q} "
        "--transform {input.transform:q} --bake-dir {params.bake_dir:q} --export-meta {input.export_meta:q} "
        "--out-dir {params.out_dir:q} --name {params.name:q} --settings {params.settings:q} "
        "--bake-settings {params.bake_settings:q} --export-settings {params.export_settings:q} "
        "--decimate-settings {params.decimate_settings:q} "
        "--threads {threads} --device {params.device} 2> {log:q}"
