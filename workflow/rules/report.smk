rule report:
    input:
        cell_metas("optimize/meta.json"),
        cell_metas("bake/meta.json"),
        cell_metas("export/meta.json"),
        cell_metas("relight/meta.json"),
        cell_metas("metrics/metrics.json"),
        roundtrip_metas(),
        lod_metas(),
    output:
        summary=report(
            f"{RESULTS}/report/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
        ),
        summary_json=f"{RESULTS}/report/summary.json",
        overview=report(
            f"{RESULTS}/report/overview.png",
            caption="../report/overview.rst",
            category="Summary",
        ),
        speed_accuracy=f"{RESULTS}/report/speed_accuracy.csv",
        plots=report(
            directory(f"{RESULTS}/report/figures"),
            patterns=["{name}.png"],
            caption="../report/figures.rst",
            category="Figures",
        ),
        figures=f"{RESULTS}/report/figures.json",
    log:
        f"{RESULTS}/report/logs/report.log",
    benchmark:
        f"{RESULTS}/report/benchmarks/report.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.report"),
        cells=cell_ids(),
        results=results_root,
        out_dir=output_folder,
        decimated=decimation_pairs_json,
        mesh_dirs=mesh_work_json,
        lod_cells=lod_cells_option(),
        settings=REPORT_SETTINGS_JSON,
    shell:
        "python -m stages.report --results {params.results:q} --out-dir {params.out_dir:q} "
        "--cells {params.cells} --decimated {params.decimated:q} --mesh-dirs {params.mesh_dirs:q} "
        "--settings {params.settings:q} {params.lod_cells} 2> {log:q}"


rule pack:
    input:
        cell_metas("export/meta.json"),
        lod_metas(),
    output:
        zip=f"{RESULTS}/report/asset_pack.zip",
        index=f"{RESULTS}/report/asset_index.csv",
    log:
        f"{RESULTS}/report/logs/pack.log",
    benchmark:
        f"{RESULTS}/report/benchmarks/pack.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.pack"),
        cells=cell_ids(),
        lod_cells=lod_cells_option(),
        results=results_root,
    shell:
        "python -m stages.pack --results {params.results:q} --zip {output.zip:q} "
        "--index {output.index:q} --cells {params.cells} {params.lod_cells} 2> {log:q}"


rule html_report:
    input:
        summary=f"{RESULTS}/report/summary.json",
        figures=f"{RESULTS}/report/figures.json",
        plots=f"{RESULTS}/report/figures",
        assets=cell_metas("export/meta.json"),
        pack=f"{RESULTS}/report/asset_pack.zip",  # each page links it
    output:
        html=f"{RESULTS}/report/index.html",
        site=REPORT_SITE,
    log:
        f"{RESULTS}/report/logs/html_report.log",
    benchmark:
        f"{RESULTS}/report/benchmarks/html_report.tsv"
    conda:
        CONDA_ENV
    params:
        code=code_digest("stages.html_report"),
        cells=cell_ids(),
        results=results_root_from_assets,
        report_dir=output_folder,
        settings=REPORT_SETTINGS_JSON,
    shell:
        "python -m stages.html_report --results {params.results:q} --report-dir {params.report_dir:q} "
        "--cells {params.cells} --settings {params.settings:q} 2> {log:q}"
