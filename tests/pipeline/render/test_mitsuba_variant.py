import subprocess
import sys

import pytest

from pipeline.core.errors import PipelineError
from pipeline.render import mitsuba_variant


@pytest.fixture
def fake_probe(monkeypatch):
    """Replace the subprocess render with a table of which variants work."""
    working: dict[str, tuple[bool, str]] = {}
    monkeypatch.setattr(mitsuba_variant, "probe", lambda v: working.get(v, (False, "broken")))
    monkeypatch.delenv(mitsuba_variant.ENV_VAR, raising=False)
    mitsuba_variant.choose.cache_clear()
    yield working
    mitsuba_variant.choose.cache_clear()


def test_auto_prefers_cuda_when_it_works(fake_probe):
    fake_probe.update({"cuda_ad_rgb": (True, ""), "llvm_ad_rgb": (True, "")})
    assert mitsuba_variant.choose("auto") == "cuda_ad_rgb"


def test_auto_falls_back_to_llvm(fake_probe):
    fake_probe["llvm_ad_rgb"] = (True, "")
    assert mitsuba_variant.choose("auto") == "llvm_ad_rgb"


def test_environment_overrides_config(fake_probe, monkeypatch):
    fake_probe.update({"cuda_ad_rgb": (True, ""), "llvm_ad_rgb": (True, "")})
    monkeypatch.setenv(mitsuba_variant.ENV_VAR, "llvm_ad_rgb")
    assert mitsuba_variant.choose("cuda_ad_rgb") == "llvm_ad_rgb"


def test_no_working_variant_names_every_failure(fake_probe):
    fake_probe["llvm_ad_rgb"] = (False, "Dr.Jit's LLVM backend aborted; fix: install libllvm19")
    with pytest.raises(PipelineError, match="(?s)mitsuba.variant = 'auto'.*cuda_ad_rgb: broken.*libllvm19"):
        mitsuba_variant.choose("auto")


@pytest.mark.slow
def test_real_probe_of_llvm_backend():
    works, why = mitsuba_variant.probe("llvm_ad_rgb")
    assert works, why


@pytest.mark.slow
def test_probe_detects_the_llvm_15_abort(monkeypatch):
    import glob

    llvm15 = glob.glob("/usr/lib/*/libLLVM-15.so*")
    if not llvm15:
        pytest.skip("no libLLVM 15 on this machine to reproduce the abort with")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", llvm15[0])
    works, why = mitsuba_variant.probe("llvm_ad_rgb")
    assert not works and "apt-get install -y libllvm19" in why


ONE_CORE_EXR = """
import os, sys
os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
import numpy as np
from pipeline.render.mitsuba_variant import activate
activate("llvm_ad_rgb")
import mitsuba as mi
mi.Bitmap(np.zeros((64, 64, 3), np.float32)).write(sys.argv[1])
"""


@pytest.mark.slow
def test_a_process_on_one_core_writes_exr_files(tmp_path):
    """On one core Dr.Jit's pool has one thread, and Mitsuba's EXR writer then waited
    forever (a one-core container ran the pipeline until it was killed)."""
    target = tmp_path / "written.exr"
    done = subprocess.run([sys.executable, "-c", ONE_CORE_EXR, str(target)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert target.stat().st_size > 0
