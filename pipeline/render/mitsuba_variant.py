"""Chooses the Mitsuba variant once, centrally.

Order: the environment variable ``PIPELINE_MITSUBA_VARIANT``, else the config's
``mitsuba.variant``; ``auto`` tries ``cuda_ad_rgb`` and then ``llvm_ad_rgb``.
Each candidate is proven by a tiny render in a subprocess, because a broken
backend does not raise: Dr.Jit 1.5 on Debian's libLLVM 15 aborts the whole
process (``LLVM ERROR: Cannot select ... fminimum``).
"""

from __future__ import annotations

import ctypes.util
import functools
import glob
import os
import subprocess
import sys

from pipeline import logger
from pipeline.core.errors import PipelineError

ENV_VAR = "PIPELINE_MITSUBA_VARIANT"
LLVM_FIX = (
    "install LLVM 19 and point Dr.Jit at it: `apt-get update && apt-get install -y libllvm19` "
    "and `export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so` "
    "(bin/bootstrap does both)"
)

_PROBE = """
import sys
import drjit as dr
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
    "light": {"type": "constant"},
    "ball": {"type": "sphere", "center": [0, 0, 5], "bsdf": {"type": "roughdielectric"}},
})
image = mi.render(scene, spp=2)
dr.sync_thread()
print("mean", float(image.numpy().mean()))
"""


def ensure_llvm_path() -> None:
    """Point Dr.Jit at libLLVM 19 when the user has not chosen a library."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    candidates = sorted(glob.glob("/usr/lib/*/libLLVM-19.so*") + glob.glob("/usr/lib/llvm-19/lib/libLLVM*.so*"))
    if candidates:
        os.environ["DRJIT_LIBLLVM_PATH"] = candidates[0]


def probe(variant: str) -> tuple[bool, str]:
    """Render a tiny scene with ``variant`` in a subprocess; (works, why not)."""
    if variant.startswith("cuda") and ctypes.util.find_library("cuda") is None:
        return False, "no CUDA driver (libcuda) on this machine"
    ensure_llvm_path()
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE, variant],
            capture_output=True,
            text=True,
            timeout=300,
        )
    except subprocess.TimeoutExpired:
        return False, "a 8x8 test render did not finish within 300 s"
    if done.returncode == 0 and "mean" in done.stdout:
        return True, ""
    if "LLVM ERROR" in done.stderr or "Cannot select" in done.stderr:
        library = os.environ.get("DRJIT_LIBLLVM_PATH", "the system's default libLLVM")
        return False, f"Dr.Jit's LLVM backend aborted with {library}; fix: {LLVM_FIX}"
    last = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
    return False, last


@functools.cache
def choose(requested: str = "auto") -> str:
    """The variant to use; raises PipelineError naming the fix when none works."""
    requested = os.environ.get(ENV_VAR) or requested
    candidates = ["cuda_ad_rgb", "llvm_ad_rgb"] if requested == "auto" else [requested]
    failures = []
    for variant in candidates:
        works, why = probe(variant)
        if works:
            logger.debug("Mitsuba variant %s", variant)
            return variant
        failures.append(f"{variant}: {why}")
    source = f"${ENV_VAR}" if os.environ.get(ENV_VAR) else "mitsuba.variant"
    raise PipelineError(f"no usable Mitsuba variant ({source} = {requested!r}):\n  " + "\n  ".join(failures))


def activate(requested: str = "auto") -> str:
    """Choose the variant and set it in this process; returns its name."""
    variant = choose(requested)
    ensure_llvm_path()
    import drjit as dr
    import mitsuba as mi

    # Mitsuba 3.9 writes EXR files through OpenEXR's threads, sized from Dr.Jit's pool:
    # with a pool of one (a one-core machine or container: Dr.Jit sizes it by the cores
    # this process may use), Bitmap.write of an EXR waits forever. Two threads on one
    # core write it.
    if dr.thread_count() < 2:
        dr.set_thread_count(2)
    mi.set_variant(variant)
    return variant
