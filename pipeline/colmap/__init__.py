"""COLMAP through pycolmap, one module per concern: features (extraction, matching,
the database's verified matches), mapping (incremental mapping, self-calibration,
registered poses), model_io (models to and from the pipeline's cameras) and meshing
(screened Poisson).

pycolmap 4.2's CPU wheel: no dense stereo, no Delaunay meshing. Every call is
made deterministic: photos are imported in sorted order, RANSAC and the mapper
are seeded, and bundle adjustment and Poisson run on one thread (with COLMAP's
threaded defaults, reruns on the same photos gave different poses). COLMAP puts
the first pixel's centre at (0.5, 0.5), OpenCV and this package at (0, 0):
``COLMAP_PIXEL_OFFSET`` converts.
"""

from __future__ import annotations

import os

import pycolmap

from pipeline.core.interrupts import after_native_import

after_native_import()  # glog's handlers, installed as pycolmap loads, print stack dumps
# COLMAP logs every step of every photo at INFO, hundreds of lines a run: only its
# warnings are shown, unless GLOG_minloglevel says otherwise (`pipeline -v` sets it to 0).
pycolmap.logging.minloglevel = int(os.environ.get("GLOG_minloglevel", pycolmap.logging.WARNING.value))

COLMAP_PIXEL_OFFSET = 0.5
"""COLMAP puts the first pixel's centre at (0.5, 0.5), OpenCV and this package at (0, 0)."""
