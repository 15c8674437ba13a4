"""The pipeline's CLI with Dr.Jit's kernels on one thread, for comparing two versions of
the code: on several threads the fits' gradients are summed by atomic adds in no fixed
order, so two runs of the same code differ (a fit amplifies the last digits).

    PYTHONPATH=CODE .venv/bin/python bench/tools/one_thread.py run CAPTURE [options]

(CODE: the checkout whose pipeline runs; this file may come from another.)

Mitsuba's image I/O waits on Dr.Jit's thread pool and never returns on one thread, so
loading a scene (with its plugins in file order) and writing a bitmap get four threads
for their duration. Limitations: with a bitmap texture in the scene (fit_texture,
fit_geometry) the runs are no longer bit-repeatable: a scene loaded on four threads
renders its first iterations a few float32 units apart from run to run. Up to
fit_material two runs agree to the bit.
"""

from __future__ import annotations

import functools
import sys

import drjit as dr
import mitsuba as mi

IO_THREADS = 4


def with_threads(function, sequential: bool = False):
    """``function`` run with IO_THREADS threads (``sequential``: scene plugins loaded in order)."""

    @functools.wraps(function)
    def wrapped(*args, **kwargs):
        if sequential:
            kwargs.setdefault("parallel", False)
        dr.set_thread_count(IO_THREADS)
        try:
            return function(*args, **kwargs)
        finally:
            dr.set_thread_count(1)

    return wrapped


def main() -> int:
    for name in ("load_file", "load_dict", "load_string"):
        setattr(mi, name, with_threads(getattr(mi, name), sequential=True))
    mi.Bitmap.write = with_threads(mi.Bitmap.write)
    dr.set_thread_count(1)
    from pipeline.cli import main as cli

    return cli(sys.argv[1:])


if __name__ == "__main__":
    sys.exit(main())
