"""The figures each stage records for the summary: every record gives exactly its columns, each
declared once on its field with what it means, reads back what it wrote, and reads the layout the
stages wrote before the records existed; lists stay lists, and the summary's CSV writes them as the
texts it always did."""

from __future__ import annotations

import dataclasses

import pytest

from stages.config import records as r

#: one filled example of each record (the figures a stage writes)
EXAMPLES = {
    r.NormalizeRecord: r.NormalizeRecord(faces=5000),
    r.DecimateRecord: r.DecimateRecord(faces_after=2000, target_faces=2000, target_reached=True),
    r.RaycacheRecord: r.RaycacheRecord(self_occlusion={"median": 0.1, "p95": 0.4}),
    r.OptimizeRecord: r.OptimizeRecord(
        prompt="a vase",
        guidance="image",
        weights="w",
        test_only_weights=False,
        settings={"iterations": 9, "target_material": "wood"},
        light_components=[
            {"kind": "sg", "lobes": 4},
            {
                "kind": "sun",
                "suns": [{"elevation_deg": 35.0, "azimuth_rad": 2.2, "radius_deg": 1.5, "irradiance": [2.8, 2.6, 2.4]}],
            },
        ],
    ),
    r.BakeRecord: r.BakeRecord(texture_size=512, bake_psnr_db=31.5),
    r.ExportRecord: r.ExportRecord(["usdchecker"], 0, 1, 0, 2),
    r.MetricsRecord: r.MetricsRecord(evaluation={"clip_score": 0.3, "weights": "e"}),
    r.RelightRecord: r.RelightRecord(ground_truth=[{"environment": "builtin:sunset", "psnr_db": 24.126}]),
    r.RoundtripRecord: r.RoundtripRecord(problems=0, transport="direct_unshadowed", glb_psnr_db=33.0),
    r.LodRecord: r.LodRecord(levels=[{"faces": 100, "file_bytes": {"model.glb": 2048}, "fidelity_psnr_db": 30.0}]),
}


def test_every_stage_of_the_summary_has_one_record():
    assert set(EXAMPLES) == {*r.MESH_RECORDS, *r.CELL_RECORDS}
    assert len({rec.stage for rec in EXAMPLES}) == len(EXAMPLES)


@pytest.mark.parametrize("cls", list(EXAMPLES), ids=lambda c: c.__name__)
def test_a_record_gives_its_columns_and_reads_back_what_it_wrote(cls):
    record = EXAMPLES[cls]
    names = tuple(c.name for c in cls.columns())
    assert tuple(record.row()) == names and tuple(cls.empty_row()) == names
    assert all(v is None for v in cls.empty_row().values())
    written = record.stats()
    assert all(k not in written for k in cls.OPTIONAL if getattr(record, k) is None)  # left out, not null
    kept = {f.name for f in dataclasses.fields(cls)} - set(cls.OPTIONAL) - ({"settings"} if cls is r.OptimizeRecord else set())
    assert kept <= set(written)  # every other figure is written, null where the stage has none
    meta = {"stats": written} if cls.place == "stats" else dict(written)
    if cls is r.OptimizeRecord:
        meta["settings"] = record.settings  # the metadata's settings, which the record reads
    assert cls.from_meta(meta) == record


def test_rows_read_the_figures_the_stages_wrote_before():
    # a relight stage's stats with two environments, one of them scaled: written by hand
    relit = r.RelightRecord.from_meta(
        {
            "stats": {
                "envmap": "builtin:sunset",
                "ground_truth": [
                    {"environment": "builtin:sunset", "psnr_db": 24.126, "psnr_scaled_db": 27.0, "scale": [1.0, 0.5, 0.25]},
                    {"environment": "envs/a/b.hdr", "psnr_db": 20.0},
                ],
            }
        }
    ).row()
    assert relit == {
        "relit_environments": ["builtin:sunset", "envs/a/b.hdr"],
        "relit_psnr_db": [24.126, 20.0],
        "relit_psnr_scaled_db": [27.0],
        "relit_ceiling_psnr_db": None,
        "relit_scale": [[1.0, 0.5, 0.25]],
    }
    assert r.text_row(relit) == {  # the summary's CSV, as before the lists
        "relit_environments": "builtin:sunset | envs/a/b.hdr",
        "relit_psnr_db": "24.13/20.00",
        "relit_psnr_scaled_db": "27.00",
        "relit_ceiling_psnr_db": None,
        "relit_scale": "1.00,0.50,0.25",
    }
    opt = r.OptimizeRecord.from_meta(
        {
            "prompt": "p",
            "guidance": "clip",
            "weights": "ViT-B-32 openai",
            "test_only_weights": True,
            "settings": {"iterations": 3},
        }
    )
    assert opt.row()["weights"] == "test-only random" and opt.row()["iterations"] == 3 and opt.row()["guidance"] == "CLIP"
    lod = r.LodRecord.from_meta(
        {
            "stats": {
                "levels": [
                    {"faces": 100, "file_bytes": {"model.glb": 10}, "fidelity_psnr_db": 30.0},
                    {"faces": 50, "file_bytes": {"model.glb": 7}, "fidelity_psnr_db": 25.555},
                ]
            }
        }
    ).row()
    assert lod == {"lod_faces": [100, 50], "lod_glb_bytes": [10, 7], "lod_fidelity_psnr_db": [30.0, 25.555]}
    assert r.text_row(lod) == {"lod_faces": "100/50", "lod_glb_bytes": "10/7", "lod_fidelity_psnr_db": "30.00/25.55"}
    # a figure the stage did not have is None in the row, not an error
    want = {"bake_psnr_db": None, "texture_size": None, "uv_layout": None, "uv_why": None}
    assert r.BakeRecord.from_meta({"stats": {}}).row() == want
    assert (
        r.MetricsRecord.from_meta({"image_target": {"psnr_db": 22.0, "material": {"roughness_mae": 0.2}}}).row()[
            "target_roughness_mae"
        ]
        == 0.2
    )


def test_records_are_frozen_dataclasses_with_their_stage_and_place():
    for cls in EXAMPLES:
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
        assert cls.place in ("stats", "top") and cls.file in ("meta.json", "metrics.json")


def test_each_column_is_declared_once_with_what_it_means():
    every = [c for cls in EXAMPLES for c in cls.columns()]
    assert len({c.name for c in every}) == len(every)  # no two records give the same column
    for c in every:
        assert c.description and not c.description.endswith("."), c.name
        assert c.field in {f.name for f in dataclasses.fields(next(cls for cls in EXAMPLES if c in cls.columns()))}
    # the columns of a record follow its fields' order, whatever the constructor's order of arguments
    assert [c.name for c in r.RoundtripRecord.columns()][-2:] == ["roundtrip_problems", "roundtrip_transport"]
    assert r.BakeRecord.columns()[0].title() == "bake (dB)"


def test_the_text_form_is_decided_once_and_leaves_other_values_alone():
    row = {"mesh": "m", "relit_psnr_db": [24.126], "lod_faces": None, "faces_before": 12, "usd_validators": 3}
    assert r.text_row(row) == {"mesh": "m", "relit_psnr_db": "24.13", "lod_faces": None, "faces_before": 12, "usd_validators": 3}
    assert r.text_row({"relit_psnr_db": []})["relit_psnr_db"] is None


def test_the_learned_suns_are_said_in_words():
    """The optimisation's light components (``meta.json``) give the summary's ``learned_suns``: one
    text per sun, its elevation, azimuth, radius and irradiance; none for a light of SG lobes alone."""
    row = EXAMPLES[r.OptimizeRecord].row()
    assert row["learned_suns"] == ["elevation 35.0 deg, azimuth 126.1 deg, radius 1.50 deg, irradiance 2.8, 2.6, 2.4"]
    plain = dataclasses.replace(EXAMPLES[r.OptimizeRecord], light_components=[{"kind": "sg", "lobes": 4}])
    assert plain.row()["learned_suns"] is None
