"""Which cells may be compared, and how: like with like.

A comparison is drawn only between cells of the same mesh and prompt, whose quality is the same
measure (held-out target PSNR, or the same evaluation CLIP) and whose weights are of the same
kind (test-only or real). Within such a group the variants are sorted by what they change
against the reference variant (``report.reference``, default the first variant):

- **configurations**: variants whose resolved per-cell settings are equal once the seed is set
  aside are replicates of one configuration (their spread is the seed's); a variant equal to an
  earlier one seed included is the same run twice (a duplicate) and is left out;
- **factor**: the settings in which a configuration differs from the reference (a sweep factor,
  e.g. ``iterations, milestones``);
- **ablations**: configurations that differ from the reference only by switching components off
  (:data:`~stages.config.sections.ABLATION_SWITCHES`), or the variants ``report.ablations`` names.
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Iterable
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from ..config.sections import ABLATION_SWITCHES, BakeSettings, LodSettings, OptimizeSettings, RelightSettings
from ..core.safefiles import read_json

log = logging.getLogger(__name__)

#: per-cell stages whose settings a variant may override, read from their meta.json
SETTINGS_STAGES = ("optimize", "bake", "relight", "lod")
#: settings that change neither the result nor its cost as compared (a replicate differs only here)
NEUTRAL_KEYS = ("optimize.seed", "optimize.checkpoint_every")
#: the setting replicates differ in
SEED_KEY = "optimize.seed"


def cell_settings(cell_dir: Path) -> dict[str, Any]:
    """The cell's resolved per-cell settings, flattened to ``stage.key`` (from each stage's
    meta.json; a stage that did not run is left out)."""
    flat: dict[str, Any] = {}
    for stage in SETTINGS_STAGES:
        path = Path(cell_dir) / stage / "meta.json"
        if path.exists() or path.is_symlink():
            record = read_json(path)
            settings = record.get("settings") if isinstance(record, dict) else None
            for key, value in (settings if isinstance(settings, dict) else {}).items():
                flat[f"{stage}.{key}"] = value
    return flat


def _canonical(value: Any) -> str:
    return json.dumps(value, sort_keys=True)


#: settings whose default changed after they were added: what a cell made before the setting
#: existed ran under (its value then), where today's default would say otherwise
BEFORE_IT_EXISTED = {"optimize.normal_tilt": 0.0}


@functools.cache
def setting_defaults() -> dict[str, Any]:
    """The value of every per-cell setting in a cell made before the setting existed, flattened to
    ``stage.key``: its default (a setting is added with the default that keeps what ran before),
    or, where that default changed later, the value it was added with (:data:`BEFORE_IT_EXISTED`)."""
    classes = {"optimize": OptimizeSettings, "bake": BakeSettings, "relight": RelightSettings, "lod": LodSettings}
    assert set(classes) == set(SETTINGS_STAGES)
    out = {}
    for stage, cls in classes.items():
        for f in fields(cls):
            if f.default is not MISSING:
                out[f"{stage}.{f.name}"] = f.default
            elif f.default_factory is not MISSING:
                out[f"{stage}.{f.name}"] = f.default_factory()
    return {**out, **BEFORE_IT_EXISTED}


def differing_keys(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """Keys whose values differ between two flat settings dicts, without the result-neutral
    ones, sorted. A key missing on one side (a cell made before the setting existed) stands for
    the setting's default (:func:`setting_defaults`); a key no settings class knows differs when
    missing on one side."""
    keys = (set(a) | set(b)) - set(NEUTRAL_KEYS)
    defaults = setting_defaults()
    absent = object()

    def value(d: dict[str, Any], k: str) -> str:
        v = d.get(k, defaults.get(k, absent))
        return "<absent>" if v is absent else _canonical(v)

    return sorted(k for k in keys if value(a, k) != value(b, k))


def is_ablation(diff: list[str], settings: dict[str, Any]) -> bool:
    """True when every differing key is a component switch set to its "off" value."""
    if not diff:
        return False
    for key in diff:
        stage, _, name = key.partition(".")
        if stage != "optimize" or name not in ABLATION_SWITCHES or settings.get(key) != ABLATION_SWITCHES[name]:
            return False
    return True


def factor_label(diff: list[str], limit: int = 3) -> str:
    """A short name for what a configuration changes: its differing keys (optimize's without the
    stage prefix), the first ``limit`` of them and a count of the rest."""
    names = [k.removeprefix("optimize.") for k in diff]
    if len(names) > limit:
        return ", ".join(names[:limit]) + f" +{len(names) - limit} more"
    return ", ".join(names)


@dataclass
class Group:
    """The cells of one mesh x prompt that may be compared with one another."""

    mesh: str
    prompt: str
    quality_name: str
    test_only: bool
    #: variant -> its row (summary row with ``quality``), in the experiment's variant order
    rows: dict[str, dict] = field(default_factory=dict)
    #: variant -> the configuration it replicates (the first variant with its settings)
    configuration: dict[str, str] = field(default_factory=dict)
    #: configuration -> label of what it changes against the reference ("" for the reference)
    factor: dict[str, str] = field(default_factory=dict)
    #: configurations that are ablations of the reference
    ablations: list[str] = field(default_factory=list)
    #: variant -> an earlier variant with the same settings, seed included (the same run made
    #: twice, e.g. a variant that switches off what the prompt's preset already switched off):
    #: left out of every comparison rather than counted as a seed replicate
    duplicates: dict[str, str] = field(default_factory=dict)
    reference: str | None = None

    @property
    def label(self) -> str:
        return f"{self.mesh} / {self.prompt}"

    def configurations(self) -> dict[str, list[str]]:
        """configuration -> its variants (replicates), in variant order."""
        out: dict[str, list[str]] = {}
        for variant, conf in self.configuration.items():
            out.setdefault(conf, []).append(variant)
        return out

    def stats(self, key: str) -> dict[str, tuple[float, float, int]]:
        """configuration -> (mean, standard deviation, count) of ``key`` over its replicates."""
        out = {}
        for conf, variants in self.configurations().items():
            values = [float(self.rows[v][key]) for v in variants if self.rows[v].get(key) is not None]
            if values:
                out[conf] = (float(np.mean(values)), float(np.std(values, ddof=1)) if len(values) > 1 else 0.0, len(values))
        return out


def comparison_groups(
    rows: Iterable[dict],
    settings: dict[tuple[str, str, str], dict[str, Any]],
    variants: list[str],
    reference: str | None = None,
    ablations: Iterable[str] | None = None,
) -> list[Group]:
    """Group summary rows (with ``quality``, ``quality_name`` and ``test_only``; rows without a
    quality are left out) into like-with-like groups and sort each group's variants into
    configurations, factors and ablations. ``settings``: cell -> :func:`cell_settings`.
    ``variants``: the experiment's variant order; ``reference`` defaults to its first."""
    reference = reference if reference is not None else (variants[0] if variants else None)
    named = None if ablations is None else set(ablations)
    groups: dict[tuple, Group] = {}
    order = {v: i for i, v in enumerate(variants)}
    for row in sorted(rows, key=lambda r: order.get(r["variant"], len(order))):
        if row.get("quality") is None:
            continue
        key = (row["mesh"], row["prompt"], row["quality_name"], bool(row["test_only"]))
        g = groups.setdefault(key, Group(*key))
        g.rows[row["variant"]] = row
    for g in groups.values():
        confs: list[str] = []
        for variant in g.rows:
            s = settings[(g.mesh, g.prompt, variant)]
            twin = next((v for v in g.configuration if _same_run(settings[(g.mesh, g.prompt, v)], s)), None)
            if twin is not None:  # the same settings, seed included: the same run twice, not a replicate
                g.duplicates[variant] = twin
                continue
            same = next((c for c in confs if not differing_keys(settings[(g.mesh, g.prompt, c)], s)), None)
            if same is None:
                confs.append(variant)
                same = variant
            g.configuration[variant] = same
        if reference in g.rows:
            g.reference = g.configuration[reference]
            ref = settings[(g.mesh, g.prompt, g.reference)]
            for conf in confs:
                s = settings[(g.mesh, g.prompt, conf)]
                diff = differing_keys(ref, s)
                g.factor[conf] = factor_label(diff)
                members = [v for v, c in g.configuration.items() if c == conf]
                if conf != g.reference and (is_ablation(diff, s) if named is None else any(v in named for v in members)):
                    g.ablations.append(conf)
        else:
            g.factor = {c: "" for c in confs}
    return list(groups.values())


def _same_run(a: dict[str, Any], b: dict[str, Any]) -> bool:
    return not differing_keys(a, b) and _canonical(a.get(SEED_KEY)) == _canonical(b.get(SEED_KEY))


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points not dominated in (lower time, higher quality), by time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -float("inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def knee_point(points: list[tuple[float, float]], front: list[int]) -> int | None:
    """The front point farthest from the straight line joining the front's ends (normalised
    axes): where more time stops buying much quality."""
    if len(front) < 3:  # a front of one or two points has no bend
        return None
    xs = np.array([points[i][0] for i in front])
    ys = np.array([points[i][1] for i in front])
    x = (xs - xs.min()) / max(np.ptp(xs), 1e-12)
    y = (ys - ys.min()) / max(np.ptp(ys), 1e-12)
    d = np.abs((y[-1] - y[0]) * x - (x[-1] - x[0]) * y + x[-1] * y[0] - y[-1] * x[0])
    return front[int(np.argmax(d))]


def trade_off(group: Group) -> list[dict]:
    """One row per configuration of a group: mean (and spread over its seeds) of the
    optimisation's wall time and of the quality, the mean peak memory (when measured), whether
    it is on the group's Pareto front, and whether it is the front's knee."""
    time, quality, peak = group.stats("seconds"), group.stats("quality"), group.stats("peak_mb")
    confs = [c for c in group.configurations() if c in time and c in quality]
    points = [(time[c][0], quality[c][0]) for c in confs]
    front = pareto_front(points)
    knee = knee_point(points, front)
    out = []
    for i, c in enumerate(confs):
        out.append(
            {
                "group": group.label,
                "configuration": c,
                "variants": "/".join(group.configurations()[c]),
                "seeds": quality[c][2],
                "factor": group.factor.get(c, ""),
                "reference": c == group.reference,
                "ablation": c in group.ablations,
                "seconds": time[c][0],
                "seconds_std": time[c][1],
                "peak_mb": peak[c][0] if c in peak else None,
                "quality": quality[c][0],
                "quality_std": quality[c][1],
                "quality_name": group.quality_name,
                "test_only": group.test_only,
                "pareto": i in front,
                "knee": i == knee,
            }
        )
    return out
