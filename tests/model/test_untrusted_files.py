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
from stages.config.guidance_modes import guidance_mode
from stages.config.sections import OptimizeSettings
from stages.core.errors import StageInputError
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
    origin = guidance_mode("image").origin_record("image targets: a test", test_only=False, prompt="p")
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
    origin = guidance_mode("image").origin_record("image targets: a test", test_only=False, prompt="p")
    torch.save({"settings": {"width": 10**9}, "state_dict": {}, "origin": origin}, tmp_path / "field.pt")
    with pytest.raises(
        StageInputError, match=r"its stored settings are not valid .*optimize.width must be in \[1, 4096\], got 1000000000"
    ):
        load_field(tmp_path / "field.pt")


def _crafted(path, **changes) -> None:
    """``field.pt`` as the tool writes it, with ``changes`` to its top-level entries (None: removed)."""
    written_field(path)
    data = torch.load(path, weights_only=True)
    for key, value in changes.items():
        if value is None:
            data.pop(key)
        else:
            data[key] = value
    torch.save(data, path)


@pytest.mark.parametrize(
    "changes, problem",
    [
        ({"settings": "width=16"}, "its settings are a str, not a mapping of names"),
        ({"settings": torch.zeros(3)}, "its settings are a Tensor, not a mapping of names"),
        ({"state_dict": [torch.zeros(2)]}, "its state_dict is a list, not a mapping of names to tensors"),
        ({"state_dict": {"material.net.0.weight": "x"}}, "its state_dict is a dict, not a mapping of names to tensors"),
        ({"state_dict": {"material.net.0.weight": torch.zeros(3, 3)}}, "its weights do not fit the network its settings"),
        ({"format": "2"}, "its format is '2', not a number"),
    ],
)
def test_a_crafted_field_of_the_right_container_is_one_line(tmp_path, changes, problem):
    path = tmp_path / "field.pt"
    _crafted(path, **changes)
    with pytest.raises(StageInputError, match=problem) as err:
        load_field(path)
    assert "\n" not in str(err.value) and str(err.value).startswith(str(path))


def test_a_wrongly_shaped_weight_is_one_line(tmp_path):
    path = tmp_path / "field.pt"
    written_field(path)
    data = torch.load(path, weights_only=True)
    name = next(iter(data["state_dict"]))
    data["state_dict"][name] = torch.zeros(7, 5)
    torch.save(data, path)
    with pytest.raises(StageInputError, match=f"its weights do not fit .*{name}") as err:
        load_field(path)
    assert "\n" not in str(err.value)


def test_a_compressed_archive_is_refused_from_its_directory(tmp_path):
    """torch writes stored (uncompressed) zip entries: a deflated entry, which lets a small file
    expand to gigabytes, is refused before anything is read; so is an archive past the size limit."""
    import zipfile

    from stages.model import checkpoint

    plain = tmp_path / "plain.pt"
    torch.save({"format": 2, "state_dict": {"w": torch.zeros(1 << 20)}}, plain)  # 4 MiB of zeros
    packed = tmp_path / "field.pt"
    with zipfile.ZipFile(plain) as src, zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as dst:
        for entry in src.infolist():
            dst.writestr(entry.filename, src.read(entry.filename))
    assert packed.stat().st_size < 100_000
    with pytest.raises(StageInputError, match=r"refused: \d+ compressed entries .*which torch never writes"):
        read_torch_file(packed, remedy="Do the thing.")
    assert read_torch_file(plain, remedy="-")["format"] == 2
    original = checkpoint.MAX_TORCH_BYTES
    try:
        checkpoint.MAX_TORCH_BYTES = 2**20
        with pytest.raises(StageInputError, match="refused: it expands to 4,19[0-9],[0-9]+ bytes, more than 1,048,576"):
            read_torch_file(plain, remedy="-")
    finally:
        checkpoint.MAX_TORCH_BYTES = original


def test_a_checkpoint_without_its_parts_stops_the_resume_in_one_line(cache, tmp_path):
    out = tmp_path / "cell"
    out.mkdir()
    s = OptimizeSettings(iterations=2, clip_tiny_test=True, image_size=64, eval_width=16, **SMALL)
    torch.save({"digest": s.digest(), "optimizer": {}}, out / "checkpoint.pt")  # no field
    with pytest.raises(StageInputError, match=r"checkpoint\.pt: is not a checkpoint of this optimisation \(KeyError") as err:
        optimize.run(cache / "train.npz", cache / "eval.npz", "a vase", out, s, "cpu")
    assert "\n" not in str(err.value) and not (out / "meta.json").exists()


def test_a_field_that_is_a_link_or_a_fifo_inside_a_results_folder_is_one_line(tmp_path):
    import os

    cell = tmp_path / "results" / "exp" / "vase" / "wood" / "base" / "optimize"
    cell.mkdir(parents=True)
    written_field(tmp_path / "elsewhere.pt")
    (cell / "field.pt").symlink_to(tmp_path / "elsewhere.pt")
    with pytest.raises(StageInputError, match="it is a symbolic link inside"):
        load_field(cell / "field.pt")
    (cell / "field.pt").unlink()
    os.mkfifo(cell / "field.pt")
    with pytest.raises(StageInputError, match="is a FIFO, not a plain file"):
        load_field(cell / "field.pt")


def _deep(levels: int) -> dict:
    value: dict = {}
    for _ in range(levels):
        value = {"a": value}
    return value


def _saved_deep(path, levels: int) -> None:
    """``field.pt`` whose settings nest ``levels`` deep, saved by torch (its pickler recurses once
    per level: here in a thread with a large stack and a raised recursion limit)."""
    import sys
    import threading

    origin = guidance_mode("image").origin_record("image targets: a test", test_only=False, prompt="p")
    data = {"format": 2, "settings": {"width": _deep(levels)}, "state_dict": {}, "origin": origin}
    failed: list[BaseException] = []

    def save() -> None:
        try:
            torch.save(data, path)
        except BaseException as err:  # noqa: BLE001 - reported by the test
            failed.append(err)

    limit, stack = sys.getrecursionlimit(), threading.stack_size()
    sys.setrecursionlimit(max(limit, 4 * levels))
    threading.stack_size(1 << 30)
    try:
        worker = threading.Thread(target=save)
        worker.start()
        worker.join()
    finally:
        threading.stack_size(stack)
        sys.setrecursionlimit(limit)
    assert not failed, failed


def test_a_field_whose_settings_nest_200000_deep_is_one_line(tmp_path):
    """Nesting past any field's is refused as soon as the file is read (the settings' checks and
    their messages walk what they are given, and would overflow Python's stack)."""
    path = tmp_path / "field.pt"
    _saved_deep(path, 200_000)
    with pytest.raises(StageInputError) as err:
        load_field(path)
    message = str(err.value)
    assert message.startswith(f"{path}: refused: its containers nest deeper than 64 levels") and "\n" not in message
    assert "optimize stage again" in message


def test_a_field_whose_settings_hold_themselves_is_one_line(tmp_path):
    looped: dict = {}
    looped["a"] = looped
    _crafted(tmp_path / "field.pt", settings={"width": looped})
    with pytest.raises(StageInputError, match="refused: its containers nest deeper than 64 levels") as err:
        load_field(tmp_path / "field.pt")
    assert "\n" not in str(err.value)


def test_nesting_counts_shared_containers_at_their_deepest_place():
    from stages.model.checkpoint import nesting

    leaf: list = []
    assert nesting({"w": torch.zeros(3), "s": {"x": [1, (2, 3)]}}) == 4
    assert nesting({"a": leaf, "b": {"c": {"d": leaf}}}) == 4  # shared: counted where it is deepest
    assert nesting(_deep(80)) == 65  # past the limit: stops there
