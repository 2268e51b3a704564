rule optimize:
    input:
        unpack(cell_targets("train")),
        unpack(light_map_input),
        train=mesh_work_input("raycache", "train.npz"),
        eval=mesh_work_input("raycache", "eval.npz"),
    output:
        **optimize_outputs(),
    log:
        f"{RESULTS}/{{mesh}}/{{prompt}}/{{variant}}/logs/optimize.log",
    benchmark:
        f"{RESULTS}/{{mesh}}/{{prompt}}/{{variant}}/benchmarks/optimize.tsv"
    conda:
        CONDA_ENV
    threads: optimize_threads
    resources:
        gpu=GPU_JOBS,
    params:
        code=code_digest("stages.optimize"),
        device=DEVICE,
        prompt=prompt_text,
        out_dir=cell_dir("optimize"),
        settings=optimize_settings_json,
        targets=targets_option,
    shell:
        "python -m stages.optimize --train {input.train:q} --eval {input.eval:q} "
        "--prompt={params.prompt:q} --out-dir {params.out_dir:q} --settings {params.settings:q} "
        "{params.targets} --threads {threads} --device {params.device} 2> {log:q}"
