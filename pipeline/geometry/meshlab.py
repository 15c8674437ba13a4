"""pymeshlab's filters, run in a child process of their own.

pymeshlab and pycolmap each bundle native libraries. A process that loads pycolmap
first and pymeshlab second corrupts its heap when it exits: a Dask worker of
``pipeline batch`` aborted in ``malloc_consolidate()`` at every shutdown. So pymeshlab
is never loaded where the pipeline runs: each call starts ``python -m
pipeline.geometry.meshlab``, which loads nothing but pymeshlab, and hands it meshes as
PLY files.

Run as a module: ``python -m pipeline.geometry.meshlab TASK.json``, where TASK.json holds
"operation" (``clean`` or ``decimate``), "input", "output" (PLY paths) and "settings";
the child writes its measures into TASK.json's "result".
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from pipeline.core.errors import PipelineError


def _measure(meshset) -> dict:
    topology = meshset.get_topological_measures()
    mesh = meshset.current_mesh()
    return {
        "faces": mesh.face_number(),
        "vertices": mesh.vertex_number(),
        "watertight": topology["boundary_edges"] == 0 and topology["non_two_manifold_edges"] == 0,
        "genus": topology["genus"],
        "boundary_edges": topology["boundary_edges"],
        "components": topology["connected_components_number"],
    }


def _clean(meshset, pymeshlab, settings: dict) -> dict:
    """Repair, remesh, decimate and smooth (the cleanup stage's settings)."""
    before = _measure(meshset)
    meshset.meshing_remove_duplicate_vertices()
    meshset.meshing_remove_unreferenced_vertices()
    meshset.meshing_repair_non_manifold_edges()
    _remove_small_components(meshset, pymeshlab, settings["min_component_fraction"])
    meshset.meshing_close_holes(maxholesize=settings["max_hole_edges"])
    if settings["remesh_edge_fraction"] > 0:
        meshset.meshing_isotropic_explicit_remeshing(
            iterations=settings["remesh_iterations"],
            targetlen=pymeshlab.PercentageValue(100 * settings["remesh_edge_fraction"]),
        )
    if meshset.current_mesh().face_number() > settings["target_faces"]:
        meshset.meshing_decimation_quadric_edge_collapse(
            targetfacenum=settings["target_faces"], preservenormal=True, preservetopology=True, qualitythr=0.5
        )
    if settings["smoothing_steps"]:
        meshset.apply_coord_taubin_smoothing(stepsmoothnum=settings["smoothing_steps"])
    meshset.meshing_remove_unreferenced_vertices()
    return {"before": before, "after": _measure(meshset)}


def _remove_small_components(meshset, pymeshlab, fraction: float) -> None:
    """Remove the components whose bounding-box diagonal is below ``fraction`` of the
    whole mesh's, always keeping the largest (by faces): at a fraction near 1 the
    filter alone removes every component whose box is smaller than the whole's, which
    leaves no mesh when none spans it."""
    whole = meshset.current_mesh_id()
    meshset.generate_copy_of_current_mesh()
    meshset.meshing_remove_connected_component_by_diameter(mincomponentdiag=pymeshlab.PercentageValue(100 * fraction))
    if meshset.current_mesh().face_number() > 0:
        return
    emptied = meshset.current_mesh_id()
    meshset.set_current_mesh(whole)
    meshset.generate_splitting_by_connected_components()
    numbers, number = [], 0
    while len(numbers) < meshset.number_meshes():  # the ids in use (pymeshlab lists no ids)
        numbers += [number] if meshset.mesh_id_exists(number) else []
        number += 1
    parts = [n for n in numbers if n not in (whole, emptied)]
    meshset.set_current_mesh(max(parts, key=lambda n: meshset.mesh(n).face_number()))


def _decimate(meshset, pymeshlab, settings: dict) -> dict:
    """Quadric edge collapse to ``settings["faces"]``, keeping normals and topology."""
    meshset.meshing_decimation_quadric_edge_collapse(
        targetfacenum=settings["faces"], preservenormal=True, preservetopology=True, planarquadric=True
    )
    return _measure(meshset)


def _run_task(task_path: Path) -> None:
    import pymeshlab

    task = json.loads(task_path.read_text())
    meshset = pymeshlab.MeshSet()
    meshset.load_new_mesh(task["input"])
    operation = {"clean": _clean, "decimate": _decimate}[task["operation"]]
    task["result"] = operation(meshset, pymeshlab, task["settings"])
    meshset.save_current_mesh(task["output"], save_vertex_color=False, save_vertex_quality=False)
    task_path.write_text(json.dumps(task))


def run(operation: str, input_ply: Path, output_ply: Path, settings: dict[str, Any]) -> dict:
    """Apply ``operation`` to the mesh in ``input_ply``, write ``output_ply``; its measures."""
    task_path = output_ply.with_name(output_ply.name + ".task.json")
    task = {"operation": operation, "input": str(input_ply), "output": str(output_ply), "settings": settings}
    task_path.write_text(json.dumps(task))
    try:
        child = subprocess.run(
            [sys.executable, "-m", "pipeline.geometry.meshlab", str(task_path)], capture_output=True, text=True
        )
        if child.returncode != 0:
            raise PipelineError(f"pymeshlab could not {operation} {input_ply}: {child.stderr.strip()[-2000:]}")
        return json.loads(task_path.read_text())["result"]
    finally:
        task_path.unlink(missing_ok=True)


if __name__ == "__main__":
    _run_task(Path(sys.argv[1]))
