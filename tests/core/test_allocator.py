"""The C allocator keeping freed memory while training (``optimize.keep_freed_memory``): on glibc
it spares a loop that frees and takes the same memory again its page faults (measured for real, in
fresh processes); elsewhere, and off, the allocator is left as it is, and what ran reaches the
metadata."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO, TINY_OPTIMIZE

from stages import optimize
from stages.config.sections import OptimizeSettings
from stages.core import allocator

ON_GLIBC = allocator.glibc() is not None

#: a loop shaped like a training step's memory: 12 blocks of 24 MiB taken, written and freed, 6 times;
#: prints the minor page faults of the last 5 rounds (the first one fills the heap)
LOOP = textwrap.dedent(
    """
    import resource, sys
    from stages.core.allocator import keep_freed_memory
    print(keep_freed_memory(sys.argv[1])[0], file=sys.stderr)
    def step():
        blocks = [bytearray(24 * 2**20) for _ in range(12)]  # zeroed: every page written
        del blocks
    step()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        step()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def faults(setting: str) -> int:
    out = subprocess.run([sys.executable, "-c", LOOP, setting], cwd=REPO, capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not ON_GLIBC, reason="glibc's malloc only (this C library is not glibc)")
def test_kept_memory_spares_a_step_its_page_faults():
    """With the allocator as it is, every round of the loop faults its 288 MiB in again (a page
    each, or a huge page each where transparent huge pages are always on); kept, almost none."""
    as_is, kept = faults("off"), faults("on")
    assert as_is > 5 * 100, as_is  # at least 100 faults a round, whatever the page size
    assert kept * 20 < as_is, (kept, as_is)


def test_the_label_names_glibc_and_the_thresholds():
    on, label = allocator.keep_freed_memory("off")
    assert (on, label) == (False, "the C allocator as it is (keep_freed_memory: off)")
    if ON_GLIBC:  # run in a child: this test process keeps its allocator as it is
        code = "from stages.core.allocator import keep_freed_memory as k; print(k('auto'))"
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True).stdout
        assert out.startswith("(True, 'glibc 2.") and "(mmap threshold 32 MiB, trim threshold 2 GiB)" in out, out


class FakeLibc:
    """A glibc whose ``mallopt`` answers ``answer`` (1: done, 0: refused) and records its calls."""

    def __init__(self, answer: int) -> None:
        self.answer, self.calls = answer, []

        class Version:
            restype = None

            def __call__(self) -> bytes:
                return b"2.99"

        self.gnu_get_libc_version = Version()

    def mallopt(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.answer


@pytest.mark.parametrize(
    ("setting", "libc", "runs", "label", "warns"),
    [
        ("auto", None, False, "the C allocator as it is (the C library is not glibc)", False),
        ("on", None, False, "the C allocator as it is (the C library is not glibc)", True),
        (True, None, False, "the C allocator as it is (the C library is not glibc)", True),
        ("auto", 0, False, "the C allocator as it is (glibc 2.99 refused the mmap and trim threshold)", False),
        ("on", 0, False, "the C allocator as it is (glibc 2.99 refused the mmap and trim threshold)", True),
        ("auto", 1, True, "glibc 2.99 malloc keeps freed memory (mmap threshold 32 MiB, trim threshold 2 GiB)", False),
        (False, 1, False, "the C allocator as it is (keep_freed_memory: off)", False),
    ],
)
def test_each_setting_with_each_c_library(monkeypatch, caplog, setting, libc, runs, label, warns):
    """Not glibc (musl, macOS, Windows) and a glibc that refuses the values, simulated: the
    allocator is left as it is, and only an explicit on warns."""
    fake = None if libc is None else FakeLibc(libc)
    monkeypatch.setattr(allocator, "glibc", lambda: fake)
    with caplog.at_level(logging.WARNING, logger="stages.core.allocator"):
        assert allocator.keep_freed_memory(setting) == (runs, label)
    assert bool(caplog.records) == warns, caplog.records
    if fake is not None and setting not in ("off", False):
        assert fake.calls == [(allocator.M_MMAP_THRESHOLD, 32 * 2**20), (allocator.M_TRIM_THRESHOLD, 2**31 - 1)]


def test_a_bad_setting_is_refused_by_name():
    with pytest.raises(ValueError, match=r"keep_freed_memory must be one of auto, on, off, got 'always'"):
        allocator.keep_freed_memory("always")


def test_a_run_records_what_the_allocator_did_and_resumes_across_it(monkeypatch, cache, tmp_path):
    """meta.json's allocator says what ran; the setting does not change what training computes,
    so it is left out of the settings' digest (a run resumes across it)."""
    monkeypatch.setattr(allocator, "glibc", lambda: None)  # this test process's allocator stays as it is
    s = OptimizeSettings(**TINY_OPTIMIZE, clip_tiny_test=True, crops=0, normal_network=False, keep_freed_memory="auto")
    optimize.run(cache / "train.npz", cache / "eval.npz", "a vase made of wood", tmp_path, s, "cpu")
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["allocator"] == "the C allocator as it is (the C library is not glibc)"
    assert meta["settings"]["keep_freed_memory"] == "auto"
    off = OptimizeSettings(**TINY_OPTIMIZE, clip_tiny_test=True, crops=0, normal_network=False, keep_freed_memory="off")
    assert off.digest() == s.digest()


@pytest.mark.parametrize("libc", [None, 1])
def test_the_doctor_says_what_each_run_s_allocator_will_do(monkeypatch, libc):
    """The doctor's torch line names what training's allocator will do under each setting of this
    config's runs (without doing it), on glibc and elsewhere (simulated)."""
    from stages import doctor
    from stages.config.workflow import WorkflowConfig

    fake = None if libc is None else FakeLibc(libc)
    monkeypatch.setattr(allocator, "glibc", lambda: fake)
    cfg = WorkflowConfig(
        {
            "device": "cpu",
            "meshes": {"vase": {"builtin": "vase"}},
            "prompts": {"wood": {"text": "a {object} made of wood"}},
            "variants": {"kept": {}, "as_is": {"optimize": {"keep_freed_memory": "off"}}},
            "optimize": {"clip_tiny_test": True, "iterations": 3},
        }
    )
    detail = doctor.check_torch(cfg).detail
    kept = "keeps freed memory while training (glibc 2.99; keep_freed_memory: auto)"
    expect = f"C allocator: {kept}; " if fake else "C allocator: as it is (the C library is not glibc); "
    assert expect + "as it is (keep_freed_memory: off)" in detail, detail
    assert fake is None or fake.calls == []  # the doctor asks nothing of the allocator
