"""Importing open_clip next to a torchvision whose compiled ops cannot load.

On a CPU-only machine pip pairs ``torch==2.13.0+cpu`` with torchvision 0.28.0, a CUDA build
whose ``_C`` library needs ``libtorch_cuda``. torchvision then fails at import with ``operator
torchvision::nms does not exist`` (its fake-tensor registrations assume the ops exist), which
also breaks ``import open_clip``. :func:`import_open_clip` checks first whether torchvision's
compiled library loads; only when it does not, it defines the two operator *schemas* that the
import needs (``torchvision::nms`` and ``torchvision::qnms``) so the import succeeds. CLIP uses
torchvision only for image transforms and a frozen batch-norm class; detection ops (and image
decoding) stay unavailable, and calling them raises. A working torchvision (GPU users, or a
matching CPU build) is left untouched.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
from pathlib import Path

log = logging.getLogger(__name__)


@functools.cache
def _patch_torchvision_ops() -> bool:
    """Define the missing op schemas when torchvision's compiled ops fail to load.

    Returns True when a patch was applied. Must run before the first ``import torchvision``.
    """
    import torch

    spec = importlib.util.find_spec("torchvision")
    if spec is None or spec.origin is None:
        return False
    libs = sorted(Path(spec.origin).parent.glob("_C*.so")) + sorted(Path(spec.origin).parent.glob("_C*.pyd"))
    if not libs:
        return False
    try:
        torch.ops.load_library(str(libs[0]))
        return False  # the real ops are there
    except (OSError, RuntimeError) as exc:
        reason = str(exc).splitlines()[0]
    lib = torch.library.Library("torchvision", "FRAGMENT")
    for name in ("nms", "qnms"):
        if not _has_schema(name):
            lib.define(f"{name}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    _LIBS.append(lib)  # keep the fragment alive for the life of the process
    log.debug(
        "torchvision's compiled ops did not load (%s); defined nms/qnms schemas so its transforms "
        "import (detection ops unavailable; not needed by CLIP)",
        reason,
    )
    return True


_LIBS: list = []


def _has_schema(name: str) -> bool:
    import torch

    try:
        torch._C._get_schema(f"torchvision::{name}", "")
        return True
    except RuntimeError:
        return False


def import_open_clip():
    """``import open_clip`` (lazily, with the torchvision workaround when needed)."""
    try:
        _patch_torchvision_ops()
        import open_clip
    except ImportError as exc:
        raise ImportError("CLIP guidance needs open_clip_torch (and torchvision): pip install open_clip_torch") from exc
    return open_clip
