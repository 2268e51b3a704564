"""Files read back from a results folder are data, never code: ``field.pt`` and ``checkpoint.pt``
load through torch's restricted unpickler. A pickle that would run code when unpickled (here: create
a folder) is refused with one clear error naming the file, and the code does not run; a truncated or
foreign file gets the same kind of error; the files the tool writes load as before."""

from __future__ import annotations

import os
import pickle

import pytest
import torch

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core.errors import StageInputError
from stages.core.provenance import origin_record
from stages.model.checkpoint import load_field, read_torch_file, save_field
from stages.model.field import StyleField

SMALL = dict(width=16, light_lobes=4, material_frequencies=2, normal_frequencies=2)


class RunsCode:
    """Unpickling it calls ``os.mkdir(marker)``: what a hostile ``.pt`` file would do."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def hostile(path, marker) -> None:
    with open(path, "wb") as fh:
        torch.save({"format": 2, "state_dict": {}, "payload": RunsCode(str(marker))}, fh)


def written_field(path) -> None:
    s = OptimizeSettings(**SMALL)
    origin = origin_record(guidance="image", weights="image targets: a test", test_only=False, prompt="p")
    save_field(path, StyleField(s.field_settings()), s, "p", origin)


def test_the_hostile_file_would_run_code_if_it_were_unpickled(tmp_path):
    """The payload is real: plain ``pickle`` (what ``weights_only=True`` amounts to) runs it."""
    marker = tmp_path / "ran"
    pickle.loads(pickle.dumps(RunsCode(str(marker))))
    assert marker.is_dir()


def test_a_field_that_would_run_code_is_refused_and_nothing_runs(tmp_path):
    marker = tmp_path / "ran"
    hostile(tmp_path / "field.pt", marker)
    with pytest.raises(StageInputError) as err:
        load_field(tmp_path / "field.pt")
    message = str(err.value)
    assert str(tmp_path / "field.pt") in message and "refused" in message and "posix.mkdir" in message
    assert "optimize stage again" in message and "\n" not in message
    assert not marker.exists()


def test_a_checkpoint_that_would_run_code_stops_the_resume_and_nothing_runs(cache, tmp_path):
    out = tmp_path / "cell"
    out.mkdir()
    marker = tmp_path / "ran"
    hostile(out / "checkpoint.pt", marker)
    s = OptimizeSettings(iterations=2, clip_tiny_test=True, image_size=64, eval_width=16, **SMALL)
    with pytest.raises(StageInputError, match=r"checkpoint\.pt: refused: .*Delete it to start this optimisation afresh"):
        optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", out, s, "cpu")
    assert not marker.exists() and not (out / "meta.json").exists()
    assert (out / "checkpoint.pt").is_file()  # the user's file is left for them to inspect


@pytest.mark.parametrize(
    "content, problem",
    [
        (b"", "not a readable torch file"),
        (b"PK\x03\x04 cut short", "not a readable torch file"),
        (b"\x80\x02garbage, not a pickle of anything" * 8, r"not a readable torch file \(not the zip archive"),
        (None, "holds a list, not the dict"),
    ],
)
def test_truncated_and_foreign_files_get_one_clear_error(tmp_path, content, problem):
    path = tmp_path / "field.pt"
    if content is None:
        torch.save([torch.zeros(2)], path)
    else:
        path.write_bytes(content)
    with pytest.raises(StageInputError, match=problem) as err:
        read_torch_file(path, remedy="Do the thing.")
    assert str(err.value).startswith(str(path)) and str(err.value).endswith("Do the thing.")


def test_a_dict_that_is_not_a_field_gets_one_clear_error(tmp_path):
    torch.save({"weights": torch.zeros(2)}, tmp_path / "field.pt")
    with pytest.raises(StageInputError, match="has no settings or state_dict: not a field this tool wrote"):
        load_field(tmp_path / "field.pt")


def test_a_field_the_tool_wrote_loads_through_the_restricted_reader(tmp_path):
    written_field(tmp_path / "field.pt")
    field, settings = load_field(tmp_path / "field.pt")
    assert settings.width == 16 and field.origin["guidance"] == "image"


def test_a_field_asking_for_networks_past_the_limits_is_refused_before_they_are_built(tmp_path):
    """The stored settings are held to the config's limits: a foreign field.pt asking for a
    width of a billion is one clear error, not an out-of-memory kill."""
    origin = origin_record(guidance="image", weights="image targets: a test", test_only=False, prompt="p")
    torch.save({"settings": {"width": 10**9}, "state_dict": {}, "origin": origin}, tmp_path / "field.pt")
    with pytest.raises(StageInputError, match=r"its stored settings are not valid .*width: 1000000000, past this tool's limit"):
        load_field(tmp_path / "field.pt")
