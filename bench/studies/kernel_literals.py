"""What makes Dr.Jit compile a new kernel, or dr.freeze record anew, between two views:
the measurements behind pipeline.fit.views.mask_windows (one window size, no crop) and
pipeline.fit.loop's one recording per view.

Part 1 renders Mitsuba's Cornell box (path, depth 3, 4 spp) once with a sensor, then
with a sensor differing in one setting, and reports each render's seconds: a render
that compiles takes about as long as the first; one that reuses the kernels takes
milliseconds. Part 2 calls one frozen render function alternately with two sensors
(or one sensor whose parameters are updated between calls) six times and reports how
often dr.freeze recorded and how many recordings it kept.

Usage: ``.venv/bin/python -m bench.studies.kernel_literals [--write]`` (after
bin/bootstrap; seconds); ``--write`` puts the tables into docs/benchmarks.md.
Run it with a Dr.Jit kernel cache that has not seen these kernels (``HOME`` pointing
at an empty folder) for part 1's compile times.
"""

from __future__ import annotations

import sys
import time

from bench.common import machine, write_section
from pipeline.render import mitsuba_variant


def main() -> None:
    mitsuba_variant.activate("auto")
    import drjit as dr
    import mitsuba as mi

    scene = mi.load_dict(mi.cornell_box())
    integrator = mi.load_dict({"type": "path", "max_depth": 3})

    def sensor(width=48, height=40, fov=40.0, principal_x=0.0, z=3.9, crop=None):
        film = {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}}
        if crop:
            film |= dict(zip(("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"), crop))
        eye = mi.ScalarTransform4f().look_at(origin=[0.1, 0, z], target=[0, 0, 0], up=[0, 1, 0])
        return mi.load_dict(
            {"type": "perspective", "fov": fov, "principal_point_offset_x": principal_x, "to_world": eye, "film": film}
        )

    def seconds(camera) -> float:
        started = time.perf_counter()
        image = mi.render(scene, sensor=camera, integrator=integrator, spp=4)
        dr.eval(image)
        dr.sync_thread()
        return time.perf_counter() - started

    lines = ["| render with | seconds |", "|---|---|"]
    for label, camera in (
        ("48x40, the first render", sensor()),
        ("the same settings again (a new sensor)", sensor()),
        ("another film size (50x40)", sensor(width=50)),
        ("another principal point", sensor(principal_x=0.1)),
        ("another field of view", sensor(fov=45.0)),
        ("another pose", sensor(z=3.5)),
        ("a 48x40 crop of a 200x200 film at (10, 10)", sensor(200, 200, crop=(10, 10, 48, 40))),
        ("the same crop at (20, 30)", sensor(200, 200, crop=(20, 30, 48, 40))),
    ):
        lines.append(f"| {label} | {seconds(camera):.3f} |")

    def frozen_calls(cameras, updates=None) -> tuple[int, int]:
        @dr.freeze
        def render(scene, camera, seed):
            return dr.mean(mi.render(scene, sensor=camera, integrator=integrator, spp=2, seed=seed), axis=None)

        for call in range(6):
            camera = cameras[call % len(cameras)]
            if updates:
                parameters = mi.traverse(camera)
                for key, value in updates[call % len(updates)].items():
                    parameters[key] = type(value)(value)
                parameters.update()
            dr.eval(render(scene, camera, dr.opaque(mi.UInt32, call)))
        return render.n_recordings, render.n_cached_recordings

    other = mi.traverse(sensor(z=3.5))
    lines += ["", "| six calls of one frozen function with | recorded | recordings kept |", "|---|---|---|"]
    one = sensor()
    start = {"to_world": type(mi.traverse(one)["to_world"])(mi.traverse(one)["to_world"])}
    for label, cameras, updates in (
        ("one sensor", [one], None),
        ("two sensors of identical settings", [sensor(), sensor()], None),
        ("two sensors, two poses", [sensor(), sensor(z=3.5)], None),
        ("one sensor, its pose updated between calls", [sensor()], [start, {"to_world": other["to_world"]}]),
    ):
        lines.append(f"| {label} | %d | %d |" % frozen_calls(cameras, updates))
    print("\n".join(lines))
    if "--write" in sys.argv[1:]:
        command = "HOME=$(mktemp -d) .venv/bin/python -m bench.studies.kernel_literals --write"
        intro = [
            "## Kernels compiled per view",
            "",
            f"{machine()} Command: `{command}` (an empty kernel cache).",
            "A film's size and a crop's offset are literals in Dr.Jit's kernels, the pose, field of view",
            "and principal point are not (so every view of a fit has one window size and no crop:",
            "pipeline.fit.views.mask_windows); dr.freeze records once per sensor object (so each view",
            "has its own recording: pipeline.fit.loop).",
            "",
        ]
        write_section("kernel-literals", intro + lines)


if __name__ == "__main__":
    main()
