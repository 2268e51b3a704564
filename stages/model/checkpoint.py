"""The trained field on disk (``field.pt``): its weights, the optimisation settings that built it,
the prompt and the origin record (which guidance and weights trained it)."""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from ..config.sections import OptimizeSettings
from ..core.errors import ConfigError, StageInputError
from ..core.provenance import ORIGIN_KEY, atomic_path, checked_origin
from ..core.safefiles import DATA_LIMIT, open_read
from ..render.sg import sg_integral
from .field import StyleField

#: version of the ``field.pt`` layout (2: the light's sharpness and energy as logarithms; 3: the
#: light a sum of components, the SG lobes' parameters under ``light.sg.``, which a format-2 state
#: moves there when loaded, :meth:`~stages.model.lights.sg.SGLightModule.match_state`)
FIELD_FORMAT = 3
#: settings a ``field.pt`` written before they existed was trained with (their defaults changed
#: when they came: it must be rebuilt as it was trained, not with today's defaults)
SETTINGS_BEFORE_THEY_EXISTED = {
    "specular_lobe": "isotropic",
    "shading_normals": "flat",
    "light_init": "broad",
    "brdf": "tango",
    "shadows": False,
}
#: format 1's light: sharpness ``0.01 + softplus(sharpness_raw)``, amplitude ``softplus(amplitude_raw)``
_FORMAT1_MIN_SHARPNESS = 0.01


def _light_from_format1(state: dict) -> dict:
    """A format-1 state dict with its light in format 2's terms (the same lobes: log sharpness,
    log energy per channel, the energy being the lobe's sphere integral)."""
    state = dict(state)
    lam = _FORMAT1_MIN_SHARPNESS + torch.nn.functional.softplus(state.pop("light.sharpness_raw"))
    amp = torch.nn.functional.softplus(state.pop("light.amplitude_raw"))
    state["light.log_sharpness"] = torch.log(lam)
    state["light.log_energy"] = torch.log(sg_integral(lam, amp).clamp(min=1e-30))
    return state


def save_field(path: str | Path, field: StyleField, settings: OptimizeSettings, prompt: str, origin: dict[str, Any]) -> None:
    """Write ``field.pt`` atomically."""
    with atomic_path(path) as tmp:
        torch.save(
            {
                "format": FIELD_FORMAT,
                "settings": settings.to_dict(),
                "prompt": prompt,
                ORIGIN_KEY: origin,
                "state_dict": field.state_dict(),
            },
            tmp,
        )


def read_torch_file(path: str | Path, device="cpu", *, remedy: str) -> dict:
    """A ``.pt`` file this tool wrote (``field.pt``, ``checkpoint.pt``): a dict of tensors and plain
    containers, read by torch's restricted unpickler (``weights_only=True``), so that a file from
    someone else's results folder can never run code when it is read. Anything else (a pickle
    that names a class or a function, a truncated or foreign file) is a
    :class:`~stages.core.errors.StageInputError` naming the file, what is wrong and ``remedy``."""
    try:
        with open_read(path, DATA_LIMIT, remedy=remedy) as fh:  # a link, FIFO or device there: one line, not a hang
            if not zipfile.is_zipfile(fh):  # torch writes zip archives; older pickles are refused too
                raise StageInputError(path, "not a readable torch file (not the zip archive torch writes)", remedy)
            try:
                with zipfile.ZipFile(fh) as z:
                    entries = z.infolist()
            except (zipfile.BadZipFile, OSError) as err:
                raise StageInputError(path, f"not a readable torch file ({err})", remedy) from None
            _check_archive(entries, Path(path), remedy)
            fh.seek(0)
            data = torch.load(fh, map_location=device, weights_only=True)
    except pickle.UnpicklingError as err:
        lines = str(err).splitlines()
        detail = next((line.strip().rstrip(".") for line in lines if "unsupported global" in line.lower()), "")
        raise StageInputError(
            path,
            "refused: it holds objects other than tensors and plain containers, which are never unpickled "
            f"(it was not written by this tool){f' ({detail})' if detail else ''}",
            remedy,
        ) from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError) as err:
        first = (str(err).splitlines() or [""])[0] or type(err).__name__
        raise StageInputError(path, f"not a readable torch file ({first})", remedy) from None
    if not isinstance(data, dict):
        raise StageInputError(path, f"holds a {type(data).__name__}, not the dict this tool writes", remedy)
    if nesting(data) > MAX_NESTING:
        raise StageInputError(
            path, f"refused: its containers nest deeper than {MAX_NESTING} levels (this tool's files nest a few)", remedy
        )
    return data


#: the deepest nesting of containers read from a ``.pt`` file (a field nests 3 levels, a
#: checkpoint's optimiser state 5): deeper settings would overflow the stack of the code that reads them
MAX_NESTING = 64


def nesting(data: Any, limit: int = MAX_NESTING) -> int:
    """How deep the dicts, lists and tuples of ``data`` nest (a container holding itself counts as
    endless), counted without recursion and stopping past ``limit``: ``limit + 1`` means deeper."""
    stack = [(data, 1)]
    reached: dict[int, int] = {}  # each container's deepest place so far: walked again only from deeper
    deepest = 0
    while stack:
        item, depth = stack.pop()
        if not isinstance(item, (dict, list, tuple)):
            continue
        if depth > limit:
            return limit + 1
        if reached.get(id(item), 0) >= depth:
            continue
        reached[id(item)] = depth
        deepest = max(deepest, depth)
        children = list(item.keys()) + list(item.values()) if isinstance(item, dict) else item
        stack.extend((child, depth + 1) for child in children)
    return deepest


#: the largest ``.pt`` file read, written or expanded: a field at the config's largest networks
#: and its optimiser's moments stay far below it
MAX_TORCH_BYTES = 4 * 2**30


def _check_archive(entries: list[zipfile.ZipInfo], path: Path, remedy: str) -> None:
    """Refuse, from the zip directory's ``entries`` alone, what torch never writes: compressed
    entries (a small file that expands to gigabytes) and archives larger than
    :data:`MAX_TORCH_BYTES`."""
    packed = [e.filename for e in entries if e.compress_type != zipfile.ZIP_STORED]
    if packed:
        raise StageInputError(path, f"refused: {len(packed)} compressed entries ({packed[0]}), which torch never writes", remedy)
    size = sum(e.file_size for e in entries)
    if size > MAX_TORCH_BYTES:
        raise StageInputError(path, f"refused: it expands to {size:,} bytes, more than {MAX_TORCH_BYTES:,}", remedy)


def _field_parts(data: dict, path: str | Path, remedy: str) -> tuple[dict, dict]:
    """The stored settings and state dict of a ``field.pt``'s contents, checked for their types."""
    missing = [key for key in ("settings", "state_dict") if key not in data]
    if missing:
        raise StageInputError(path, f"has no {' or '.join(missing)}: not a field this tool wrote", remedy)
    settings, state = data["settings"], data["state_dict"]
    if not isinstance(settings, dict) or not all(isinstance(k, str) for k in settings):
        raise StageInputError(path, f"its settings are a {type(settings).__name__}, not a mapping of names", remedy)
    if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        raise StageInputError(path, f"its state_dict is a {type(state).__name__}, not a mapping of names to tensors", remedy)
    if not isinstance(data.get("format", 1), int):
        raise StageInputError(path, f"its format is {data.get('format')!r}, not a number", remedy)
    return settings, state


def load_field(path: str | Path, device="cpu") -> tuple[StyleField, OptimizeSettings]:
    """Rebuild a trained :class:`StyleField` from ``field.pt``; ``field.origin`` is the record of
    the guidance and weights that trained it (:func:`~stages.core.provenance.origin_record`), which
    every stage that uses the field copies into its own outputs."""
    remedy = "Run this cell's optimize stage again to rebuild it."
    data = read_torch_file(path, device, remedy=remedy)
    stored_settings, state = _field_parts(data, path, remedy)
    origin = checked_origin(data.get(ORIGIN_KEY), path, "the optimize stage")
    stored = {**SETTINGS_BEFORE_THEY_EXISTED, **stored_settings}
    try:  # held to the config's limits: a foreign file may ask for networks no machine can hold
        settings = OptimizeSettings.from_dict(stored)
    except ConfigError as err:
        raise StageInputError(path, f"its stored settings are not valid ({err})", remedy) from None
    f = StyleField(settings.field_settings()).to(device)
    if int(data.get("format", 1)) < 2 and "light.sharpness_raw" in state:
        state = _light_from_format1(state)
    try:
        f.load_state_dict(state)
    except RuntimeError as err:  # missing, unexpected or misshapen weights
        first = " ".join(str(err).split())[:200]
        raise StageInputError(path, f"its weights do not fit the network its settings describe ({first})", remedy) from None
    f.origin = origin
    return f.eval(), settings
