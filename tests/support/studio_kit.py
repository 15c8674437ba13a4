"""A tiny scene to fit in the studio: a principled sphere on a grey floor under an
area light and a constant environment, two sensors of 32x32 px, and references
rendered from known values."""

from pathlib import Path

import numpy as np

SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
{sensors}
  <bsdf type="principled" id="mat">
    <rgb name="base_color" value="{colour}"/>
    <float name="roughness" value="{rough}"/>
  </bsdf>
  <shape type="sphere" id="ball"><float name="radius" value="0.1"/><ref id="mat"/></shape>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><scale value="0.5"/><translate z="-0.1"/></transform>
    <bsdf type="diffuse" id="floor_bsdf"><rgb name="reflectance" value="0.5"/></bsdf>
  </shape>
  <emitter type="constant" id="sky"><rgb name="radiance" value="0.3"/></emitter>
  <shape type="rectangle" id="lamp">
    <transform name="to_world">
      <scale value="0.15"/><lookat origin="0.3, 0.3, 0.5" target="0, 0, 0" up="0, 0, 1"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="10"/></emitter>
  </shape>
</scene>
"""
SENSOR = """  <sensor type="perspective" id="{name}">
    <float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="{x}, {y}, 0.25" target="0, 0, 0" up="0, 0, 1"/></transform>
    <sampler type="independent"><integer name="sample_count" value="8"/></sampler>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
  </sensor>"""
TRUTH = {"colour": (0.7, 0.3, 0.2), "rough": 0.3}
START = {"colour": (0.4, 0.4, 0.4), "rough": 0.6}


def write_scene(path: Path, colour, rough: float) -> Path:
    eyes = {"front": (0.5, -0.1), "side": (-0.2, 0.5)}
    sensors = "\n".join(SENSOR.format(name=name, x=x, y=y) for name, (x, y) in eyes.items())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(SCENE.format(sensors=sensors, colour=", ".join(map(str, colour)), rough=rough))
    return path


def write_kit(folder: Path) -> tuple[Path, Path]:
    """The scene at its start values, and its references rendered from the truth."""
    import mitsuba as mi

    from pipeline.imaging.photo_io import write_image

    truth = mi.load_file(str(write_scene(folder / "truth" / "scene.xml", **TRUTH)))
    references = folder / "references"
    references.mkdir(parents=True, exist_ok=True)
    for index, sensor in enumerate(truth.sensors()):
        image = np.asarray(mi.render(truth, sensor=sensor, spp=512, seed=index), np.float32)
        write_image(references / f"{index}_{sensor.id()}.exr", image)
    return write_scene(folder / "scene" / "scene.xml", **START), references
