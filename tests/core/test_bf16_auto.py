"""The bfloat16 levers decided at run time (``optimize.bf16``, ``optimize.bf16_networks``: auto, on,
off): auto is bfloat16 exactly where the device has it natively and float32 elsewhere, on both
kinds of machine (the other kind simulated), and what ran reaches the metadata, the plan and the
doctor."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import pytest
import torch
from conftest import REPO, TINY_OPTIMIZE

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core import device as policy
from stages.core.errors import ConfigError

CPU = torch.device("cpu")
NATIVE = (True, "CPU with native bfloat16 (simulated)")
EMULATED = (False, "this CPU has no native bfloat16 (simulated)")


@pytest.mark.parametrize(
    ("setting", "support", "runs", "label"),
    [
        ("auto", NATIVE, True, "bfloat16 autocast (auto: CPU with native bfloat16 (simulated))"),
        ("auto", EMULATED, False, "float32 (auto: this CPU has no native bfloat16 (simulated))"),
        ("on", NATIVE, True, "bfloat16 autocast (CPU with native bfloat16 (simulated))"),
        ("on", EMULATED, False, "float32 (this CPU has no native bfloat16 (simulated))"),
        ("off", NATIVE, False, "float32"),
        ("off", EMULATED, False, "float32"),
        (True, NATIVE, True, "bfloat16 autocast (CPU with native bfloat16 (simulated))"),
        (False, NATIVE, False, "float32"),
    ],
)
def test_each_setting_on_each_kind_of_machine(monkeypatch, caplog, setting, support, runs, label):
    monkeypatch.setattr(policy, "bf16_support", lambda device: support)
    with caplog.at_level(logging.WARNING, logger="stages.core.device"):
        assert policy.bf16_choice(setting, CPU, "bf16") == (runs, label)
    # only an explicit "on" that cannot be honoured warns: auto's float32 is the decision, not a fallback
    warned = [r.getMessage() for r in caplog.records]
    assert bool(warned) == (setting in ("on", True) and not support[0]), warned
    if warned:
        assert warned[0].startswith("bf16 asked for, but this CPU has no native bfloat16")


def test_a_bad_setting_is_refused_by_name():
    with pytest.raises(ValueError, match=r"bf16_networks must be one of auto, on, off, got 'yes'"):
        policy.bf16_choice("yes", CPU, "bf16_networks")
    with pytest.raises(ConfigError, match=r"bf16 must be one of auto, on, off, got 'fast'"):
        OptimizeSettings(bf16="fast")
    # YAML 1.1's bare on/off arrive as booleans and mean on and off
    assert (OptimizeSettings(bf16=True).bf16, OptimizeSettings(bf16_networks=False).bf16_networks) == ("on", "off")
    assert (OptimizeSettings().bf16, OptimizeSettings().bf16_networks) == ("auto", "auto")


def test_the_real_answer_on_this_machine_matches_onednn():
    """Not simulated: auto follows what oneDNN reports for this CPU (AVX-512 BF16 or AMX)."""
    native = torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    runs, label = policy.bf16_choice("auto", CPU, "bf16")
    assert runs == native and label.startswith("bfloat16 autocast (auto:" if native else "float32 (auto:")


#: the conftest's tiny optimisation under the test CLIP, without crops or normal network
TINY = {**TINY_OPTIMIZE, "clip_tiny_test": True, "crops": 0, "normal_network": False}


@pytest.mark.parametrize("support", [NATIVE, EMULATED], ids=["native", "no-native-bf16"])
def test_auto_decides_a_real_run_and_its_metadata_says_so(monkeypatch, cache, tmp_path, support):
    """A real optimisation under the defaults on both kinds of machine: the networks and CLIP run
    what auto decided (the autocast actually taken), and meta.json records it."""
    monkeypatch.setattr(policy, "bf16_support", lambda device: support)
    seen = []
    real = torch.autocast

    def spy(device_type, dtype=None, enabled=True, **kw):
        if dtype == torch.bfloat16:
            seen.append(enabled)
        return real(device_type, dtype=dtype, enabled=enabled, **kw)

    monkeypatch.setattr(torch, "autocast", spy)
    optimize.run(cache / "train.npz", cache / "eval.npz", "a vase made of wood", tmp_path, OptimizeSettings(**TINY), "cpu")
    meta = json.loads((tmp_path / "meta.json").read_text())
    expect = "bfloat16 autocast (auto: " if support[0] else "float32 (auto: "
    assert meta["clip_precision"].startswith(expect) and meta["network_precision"].startswith(expect), meta
    assert meta["settings"]["bf16"] == "auto" and meta["settings"]["bf16_networks"] == "auto"
    assert seen and any(seen) == support[0]


@pytest.mark.slow(minutes=0.3)
def test_a_cpu_without_native_bfloat16_taken_for_real(cache, tmp_path):
    """Not simulated: a real optimisation in a process where torch is held to AVX2
    (``AVX2_ONLY_ENV``: oneDNN without AVX-512, so without bfloat16 kernels), as on a CPU that has
    only AVX2: auto runs CLIP and the networks in float32, and meta.json says why and names the CPU."""
    if torch.backends.cpu.get_cpu_capability() != "AVX512":
        pytest.skip("this CPU has no AVX-512 to hold back (test_the_real_answer_on_this_machine_matches_onednn takes it)")
    settings = json.dumps(OptimizeSettings(**TINY).to_dict())
    cmd = [sys.executable, "-m", "stages.optimize", "--train", str(cache / "train.npz"), "--eval", str(cache / "eval.npz")]
    cmd += ["--prompt", "a vase made of wood", "--out-dir", str(tmp_path), "--settings", settings, "--device", "cpu"]
    env = {**os.environ, **policy.AVX2_ONLY_ENV}
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    meta = json.loads((tmp_path / "meta.json").read_text())
    expect = "float32 (auto: this CPU has no native bfloat16 (no AVX-512 BF16 or AMX for oneDNN))"
    assert meta["clip_precision"] == expect and meta["network_precision"] == expect, meta
    assert meta["cpu"].startswith(f"{policy.cpu_isa().split('-')[0]}-avx2-"), meta["cpu"]


def test_the_plan_and_the_doctor_show_what_will_run(monkeypatch):
    from stages.config.workflow import WorkflowConfig

    monkeypatch.setattr(policy, "bf16_support", lambda device: EMULATED)
    line = policy.precision_summary("auto", "on", CPU)
    assert line == (
        "CLIP float32 (bf16: auto), networks float32 (bf16_networks: on): this CPU has no native bfloat16 (simulated)"
    )
    monkeypatch.setattr(policy, "bf16_support", lambda device: NATIVE)
    cfg = WorkflowConfig(
        {
            "meshes": {"vase": {"builtin": "vase"}},
            "prompts": {"wood": {"text": "a {object} made of wood"}},
            "variants": {"full": {}, "plain": {"optimize": {"bf16_networks": "off"}}},
            "optimize": {"clip_tiny_test": True},
        }
    )
    from stages import doctor, plan

    text = plan.plan_text(plan.make_plan(cfg, "main", calibrate=False))
    assert "precision: CLIP bfloat16 (bf16: auto), networks bfloat16 (bf16_networks: auto): CPU with native" in text
    assert "precision: CLIP bfloat16 (bf16: auto), networks float32 (bf16_networks: off)" in text
    check = doctor.check_torch(cfg)
    assert "training runs CLIP bfloat16 (bf16: auto), networks bfloat16 (bf16_networks: auto); CLIP bfloat16" in check.detail
