"""Guidance: CLIP through open_clip (real weights from a pretrained tag or a local checkpoint, or
a tiny randomly initialised model that is for tests only), and image targets for verification.

Loading never hangs on an unreachable model hub: cached or local weights load directly; weights
that would have to be downloaded are only fetched when the hub answers a 3-second probe (logged
before it is sent; none with ``HF_HUB_OFFLINE=1``), and otherwise :class:`ClipWeightsUnavailable`
explains how to supply a checkpoint. A local checkpoint is read by torch's restricted unpickler
(open_clip's ``weights_only=True``): one that holds anything but tensors and plain containers is
refused in one line naming the file.
"""

from __future__ import annotations

import logging
import os
import pickle
import re
import socket
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor
from torch.nn import functional as F

from ..config.sections import CLIP_ROLES, TINY_CLIP, ClipSpec
from ..core.device import bf16_choice
from ..core.errors import StageInputError
from .compat import import_open_clip
from .vit import CLIP_TOWERS, use_fast_tower

log = logging.getLogger(__name__)

#: the weights id recorded for the tiny random model; anything carrying it is not a real result
TEST_ONLY_WEIGHTS = "tiny-random-clip (TEST ONLY: random weights, not a real stylization)"
HUB_HOST = ("huggingface.co", 443)


#: CLIP's input normalisation (the OpenAI models and open_clip's defaults)
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class ClipWeightsUnavailable(StageInputError):
    """CLIP weights are neither local nor downloadable from here (bad input of a run: a stage
    exits with status 2 and this message)."""

    def __init__(self, message: str) -> None:
        super().__init__(None, message.rstrip("."))


def clip_normalize(images: Tensor, mean=CLIP_MEAN, std=CLIP_STD) -> Tensor:
    """``(B, 3, S, S)`` in [0, 1] -> CLIP's normalised input."""
    m = torch.tensor(mean, device=images.device, dtype=images.dtype)[:, None, None]
    s = torch.tensor(std, device=images.device, dtype=images.dtype)[:, None, None]
    return (images - m) / s


def hub_offline() -> bool:
    """Whether ``HF_HUB_OFFLINE`` (Hugging Face's own switch) says not to contact the model hub."""
    return os.environ.get("HF_HUB_OFFLINE", "") not in ("", "0")


def _hub_reachable(timeout: float = 3.0) -> bool:
    """Whether the model hub answers a connection within ``timeout`` seconds; said in the log before
    it is asked, and never asked under ``HF_HUB_OFFLINE``."""
    if hub_offline():
        return False
    log.info(
        "asking the model hub %s (port %d) whether it answers, for CLIP weights not cached here "
        "(HF_HUB_OFFLINE=1 keeps this machine from asking)",
        *HUB_HOST,
    )
    try:
        with socket.create_connection(HUB_HOST, timeout=timeout):
            return True
    except OSError:
        return False


def _cached_hub_file(hf_hub: str) -> str | None:
    from huggingface_hub import try_to_load_from_cache

    repo, filename = os.path.split(hf_hub)
    names = [filename] if filename else ["open_clip_model.safetensors", "open_clip_pytorch_model.bin"]
    for name in names:
        path = try_to_load_from_cache(repo_id=repo, filename=name)
        if isinstance(path, str):
            return path
    return None


def _hub_cache() -> str:
    from huggingface_hub import constants

    return str(constants.HF_HUB_CACHE)


def weights_help(
    spec: ClipSpec, problem: str, looked: list[str], quick_gelu: bool = False, repo: str | None = None, known: bool = True
) -> str:
    """What to do when the CLIP of ``spec`` cannot be had: which model (guidance or evaluation,
    name and weights tag), why (``problem``), where it was looked for, the config keys that point
    at a local file (with the architecture name that matches those weights: OpenAI's weights use
    QuickGELU, ``<model>-quickgelu``), how to get that file (``known``: open_clip knows the tag),
    and how to run without it."""
    section = spec.section
    arch = spec.model if not quick_gelu or spec.model.endswith("-quickgelu") else f"{spec.model}-quickgelu"
    role = CLIP_ROLES.get(section, "CLIP")
    lines = [f"The {role}, {spec.model} with the weights {spec.pretrained!r}, is not available: {problem}."]
    if looked:
        lines.append("Looked for it in: " + "; ".join(looked) + ".")
    lines += [
        "To use a local copy of these weights, set in the config:",
        f"  {section}:",
        "    clip_checkpoint: /path/to/open_clip_pytorch_model.bin",
        f"    clip_model: {arch}" + ("  # these weights need QuickGELU, which this name selects" if arch != spec.model else ""),
    ]
    if known and spec.pretrained:
        source = f"<Hugging Face cache>/models--{repo.replace('/', '--')}/snapshots/<hash>/" if repo else "open_clip's cache"
        copy = f", or copy that models--... folder into this machine's Hugging Face cache, {_hub_cache()} (HF_HOME)"
        lines.append(
            "To get that file, on a machine with internet run\n"
            f"  python -c \"import open_clip; open_clip.create_model('{spec.model}', pretrained='{spec.pretrained}')\"\n"
            f"and copy the file it downloads (from {source}) here{copy if repo else ''}."
        )
    elif not known:
        lines.append(f"Or set {section}.clip_pretrained to one of the model's tags above.")
    if section == "metrics":
        lines.append(
            "Or switch the evaluation off: metrics: {clip: false} (no CLIP score or R-precision; the image-target "
            "metrics still run)."
        )
    else:
        lines.append(
            "Or run without CLIP weights: --configfile config/demo.yaml (image-guided), or add "
            "config/overlays/offline.yaml (the tiny random test CLIP; every result is marked TEST ONLY)."
        )
    return "\n".join(lines)


def resolve_weights(spec: ClipSpec, *, download: bool = True, online: bool = True) -> tuple[str, str, bool]:
    """Return ``(path, weights_id, quick_gelu)`` for ``spec``, downloading only when the hub
    answers. Raises :class:`ClipWeightsUnavailable` (fast) when the weights cannot be had, with
    :func:`weights_help`'s message. ``download=False`` (the doctor: a check, not a fetch of
    hundreds of megabytes): weights that are not cached but that the hub would give come back
    with the path ``""``. ``online=False`` (the doctor's ``--offline``): the hub is not asked, and
    weights that are not here are unavailable, as under ``HF_HUB_OFFLINE``."""
    open_clip = import_open_clip()
    cfg = open_clip.get_pretrained_cfg(spec.model, spec.pretrained) if spec.pretrained else {}
    quick_gelu = bool(cfg.get("quick_gelu", False))
    repo = cfg["hf_hub"].rstrip("/") if cfg.get("hf_hub") else None
    if spec.checkpoint:
        path = Path(spec.checkpoint)
        if not path.is_file():
            problem = f"the file {path} set as {spec.section}.clip_checkpoint does not exist"
            raise ClipWeightsUnavailable(weights_help(spec, problem, [str(path)], quick_gelu, repo, bool(cfg)))
        return str(path), f"{spec.model}:{path.name}", False
    if not cfg:
        tags = ", ".join(repr(t) for t in open_clip.list_pretrained_tags_by_model(spec.model)) or "none"
        problem = f"open_clip knows no weights {spec.pretrained!r} for the model {spec.model!r} (its tags: {tags})"
        raise ClipWeightsUnavailable(weights_help(spec, problem, [], known=False))
    weights_id = f"{spec.model}/{spec.pretrained}"
    if repo:
        cached = _cached_hub_file(cfg["hf_hub"])
        if cached:
            return cached, weights_id, quick_gelu
    looked = [f"the Hugging Face cache ({_hub_cache()}/models--{repo.replace('/', '--')})"] if repo else []
    if not online or not _hub_reachable():
        why = "not asked: offline" if not online else "HF_HUB_OFFLINE is set" if hub_offline() else "unreachable from here"
        looked.append(f"the model hub {HUB_HOST[0]} ({why})")
        problem = (
            "they are not cached on this machine and cannot be downloaded (offline)"
            if online
            else "they are not cached on this machine (the model hub was not asked)"
        )
        raise ClipWeightsUnavailable(weights_help(spec, problem, looked, quick_gelu, repo))
    if not download:
        return "", weights_id, quick_gelu
    from open_clip.pretrained import download_pretrained

    path = download_pretrained(cfg)
    if not path:
        looked.append(f"the model hub {HUB_HOST[0]} (the download failed)")
        raise ClipWeightsUnavailable(weights_help(spec, "downloading them failed", looked, quick_gelu, repo))
    return path, weights_id, quick_gelu


def missing_weights(specs) -> list[str]:
    """One :func:`weights_help` message per CLIP of ``specs`` whose weights cannot be had (the
    guidance and the evaluation model each name their own config keys); [] when all are there."""
    problems = []
    for spec in specs:
        try:
            resolve_weights(spec)
        except ClipWeightsUnavailable as exc:
            problems.append(str(exc))
    return problems


class ClipGuide:
    """A frozen CLIP that embeds prompts and images (images in [0, 1], ``(B, 3, S, S)``).

    ``bf16`` (``auto``, ``on``, ``off``; booleans mean on and off): the image tower under bfloat16
    autocast where the device supports it natively (:func:`bf16_choice`); elsewhere float32, and
    :attr:`precision`, which the optimisation's metadata records, says why (``on`` also warns).

    ``tower`` (:data:`~stages.config.sections.CLIP_TOWERS`): ``"batched"`` runs the image tower's
    attention and patch embedding as contiguous matrix products, with the frozen weights cast to
    bfloat16 once under ``bf16`` (the same function, faster on a CPU: :mod:`stages.guidance.vit`);
    ``"open_clip"`` leaves open_clip's own modules."""

    def __init__(
        self,
        model,
        tokenizer,
        *,
        image_size: int,
        weights_id: str,
        test_only: bool,
        device,
        bf16: str | bool,
        tower: str = "batched",
    ):
        if tower not in CLIP_TOWERS:
            raise ValueError(f"CLIP tower must be one of {', '.join(CLIP_TOWERS)}, got {tower!r}")
        self.model = model.eval().requires_grad_(False).to(device)
        self.tokenizer = tokenizer
        self.image_size = image_size
        self.weights_id = weights_id
        self.test_only = test_only
        self.device = torch.device(device)
        #: whether the tower runs under bfloat16 autocast, and what ran, for the metadata
        #: (:func:`bf16_choice`: "bfloat16 autocast (<why>)", "float32" or "float32 (<why not>)")
        self.bf16, self.precision = bf16_choice(bf16, self.device, "bf16 (CLIP's image tower)")
        #: the image tower's path, and how many of its modules the fast path changed
        self.tower = tower
        self.tower_changes = use_fast_tower(self.model.visual, self.bf16) if tower == "batched" else 0

    def text_tokens(self, text: str) -> tuple[int, int]:
        """``(tokens the text makes with its start and end markers, tokens CLIP reads)``."""
        limit = int(getattr(self.tokenizer, "context_length", None) or 77)
        encode = getattr(self.tokenizer, "encode", None)
        if encode is None:  # a tokenizer without BPE access: count what it kept (at most the limit)
            return int((self.tokenizer([text]) != 0).sum()), limit
        return len(encode(text)) + 2, limit

    def embed_text(self, text: str) -> Tensor:
        """The unit text embedding; a text longer than CLIP's context is cut by the tokenizer, and
        that is logged as a warning naming the prompt (CLIP never sees the rest)."""
        used, limit = self.text_tokens(text)
        if used > limit:
            shown = text if len(text) <= 80 else text[:79] + "…"
            log.warning(
                "prompt %r makes %d tokens; CLIP reads the first %d, so the rest of it has no effect: shorten it",
                shown,
                used,
                limit,
            )
        with torch.no_grad():
            tokens = self.tokenizer([text]).to(self.device)
            emb = self.model.encode_text(tokens).float()
        return F.normalize(emb, dim=-1)[0]

    def embed_images(self, images: Tensor) -> Tensor:
        x = clip_normalize(images, CLIP_MEAN, CLIP_STD)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            emb = self.model.encode_image(x)
        return emb.float()

    def similarity(self, images: Tensor, text_embedding: Tensor) -> Tensor:
        """Cosine similarity of the *averaged* image embedding with the text embedding (TANGO)."""
        return self.similarities([images], text_embedding)[0]

    def similarities(self, groups: Sequence[Tensor], text_embedding: Tensor) -> list[Tensor]:
        """:meth:`similarity` of each group of images ``(B_i, 3, S, S)``, all embedded as one
        batch: the values of one call per group (to the rounding of the products) in less time,
        as the tower's products have more rows (docs/measurements/speed.md)."""
        sizes = [len(g) for g in groups]
        embeddings = self.embed_images(torch.cat(list(groups))).split(sizes)
        return [F.cosine_similarity(e.mean(0), text_embedding, dim=0) for e in embeddings]


#: open_clip model name of the tiny test architecture (stages/guidance/data/tango-tiny-test-clip.json)
TINY_MODEL = TINY_CLIP


def register_tiny_model() -> None:
    """Make the tiny test architecture known to open_clip (idempotent)."""
    open_clip = import_open_clip()
    if TINY_MODEL not in open_clip.list_models():
        open_clip.add_model_config(Path(__file__).parent / "data" / f"{TINY_MODEL}.json")


def tiny_test_clip(seed: int = 0):
    """A 2-layer, 64-wide CLIP with random weights (3.6 M parameters, mostly the token
    embedding), built through open_clip like a real model: for tests and CI only. Its outputs
    carry :data:`TEST_ONLY_WEIGHTS`."""
    open_clip = import_open_clip()
    register_tiny_model()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = open_clip.create_model(TINY_MODEL, pretrained=None)
    return model, open_clip.get_tokenizer(TINY_MODEL)


def _image_size(model) -> int:
    size = model.visual.image_size
    return int(size[0] if isinstance(size, tuple | list) else size)


def _unreadable_weights(spec: ClipSpec, err: pickle.UnpicklingError) -> tuple[str, str]:
    """``(problem, remedy)`` of a weights file that torch's restricted unpickler refused (a pickle
    that names a function or a class, which would run code if it were unpickled, or one it cannot
    read), naming what it stopped at."""
    text = " ".join(str(err).split())
    name = re.search(r"GLOBAL (\S+?)\.?(?: |$)", text)
    operand = re.search(r"Unsupported operand (\d+)", text)
    if name:
        what = f" (it names {name.group(1)}, which unpickling would call)"
    elif operand:
        what = f" (pickle operation {operand.group(1)}, which torch's weights-only reader does not take)"
    else:
        what = ""
    key = f"{spec.section}.clip_checkpoint" if spec.checkpoint else f"{spec.section}.clip_pretrained"
    return (
        f"refused: not a weights-only file: it holds more than tensors and plain containers{what}, and is never unpickled",
        f"Give {key} weights saved as tensors (a state dict, as open_clip's files are), from a source you trust.",
    )


def load_clip(spec: ClipSpec, device="cpu", bf16: str | bool = "off", tower: str = "batched") -> ClipGuide:
    """Load the CLIP of ``spec`` on ``device``; fails fast when weights are unavailable.
    ``bf16`` and ``tower``: see :class:`ClipGuide`."""
    if spec.tiny_test:
        model, tok = tiny_test_clip()
        log.warning("using %s", TEST_ONLY_WEIGHTS)
        return ClipGuide(
            model,
            tok,
            image_size=_image_size(model),
            weights_id=TEST_ONLY_WEIGHTS,
            test_only=True,
            device=device,
            bf16=bf16,
            tower=tower,
        )
    path, weights_id, quick_gelu = resolve_weights(spec)
    open_clip = import_open_clip()
    if spec.model == TINY_MODEL:
        register_tiny_model()
    try:
        model = open_clip.create_model(spec.model, pretrained=path, force_quick_gelu=quick_gelu, device=device)
    except pickle.UnpicklingError as err:
        raise StageInputError(path, *_unreadable_weights(spec, err)) from None
    size = _image_size(model)
    log.info("loaded CLIP %s from %s", weights_id, path)
    return ClipGuide(
        model,
        open_clip.get_tokenizer(spec.model),
        image_size=size,
        weights_id=weights_id,
        test_only=False,
        device=device,
        bf16=bf16,
    )
