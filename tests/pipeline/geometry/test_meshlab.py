"""pymeshlab runs in a process of its own: never loaded beside pycolmap."""

import json

from tests.support.toy_stages import run_python

CLEAN_BESIDE_PYCOLMAP = """
import json, sys, tempfile
from pathlib import Path
import pycolmap, trimesh
import stages  # every stage, as a batch worker loads them
from pipeline.geometry import meshlab
folder = Path(tempfile.mkdtemp())
trimesh.creation.icosphere(subdivisions=4).export(folder / "in.ply")
settings = dict(min_component_fraction=0.1, max_hole_edges=100, remesh_edge_fraction=0.0,
                remesh_iterations=1, target_faces=500, smoothing_steps=1)
measures = meshlab.run("clean", folder / "in.ply", folder / "out.ply", settings)
faces = len(trimesh.load(folder / "out.ply", force="mesh").faces)
print(json.dumps({"measures": measures, "faces": faces, "loaded": "pymeshlab" in sys.modules}))
"""


def test_cleaning_runs_pymeshlab_in_a_child_and_leaves_this_process_without_it():
    done = run_python(CLEAN_BESIDE_PYCOLMAP, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["loaded"] is False
    assert result["measures"]["before"]["faces"] == 5120
    assert result["faces"] == result["measures"]["after"]["faces"] <= 500
    assert result["measures"]["after"]["watertight"] and "Abort" not in done.stderr
