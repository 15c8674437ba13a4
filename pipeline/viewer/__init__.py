"""A glTF viewer for self-contained HTML pages: three.js renders a .glb embedded in
the page, so the page opens offline, mailed or copied alone.

three_bundle.js (three.js r170 with its glTF loader, orbit controls and room
environment, MIT licence) ships with the package; build_bundle.sh rebuilds it. The
model is lit by three.js's neutral room environment (image-based light), shown in
linear-to-sRGB output without tone mapping, so a base colour reads as it was fitted.

Without a camera the view frames the model and orbits with the mouse. With one (a
photo's intrinsics and pose in the pipeline's world, z up) it renders exactly that
photo's view, as the export test compares with Mitsuba's render. When the model is
on screen the host element gets ``data-rendered="1"`` (``data-error`` on failure).
"""

from __future__ import annotations

import base64
import json
from functools import cache
from pathlib import Path

import numpy as np

from pipeline.camera.model import Intrinsics, Pose

BUNDLE = Path(__file__).with_name("three_bundle.js")
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""The pipeline's world (z up) to glTF's (y up), as stages/export.py turns the mesh."""
OPENCV_TO_GL = np.diag([1.0, -1.0, -1.0])
"""An OpenCV camera (x right, y down, looking along +z) to an OpenGL one (y up, along -z)."""

INIT = """
(() => {
  const host = document.getElementById(%(id)s);
  const {THREE, GLTFLoader, OrbitControls, RoomEnvironment} = window.THREE_VIEWER;
  const [width, height] = [%(width)d, %(height)d];
  const renderer = new THREE.WebGLRenderer({antialias: true, preserveDrawingBuffer: true});
  renderer.setPixelRatio(1);
  renderer.setSize(width, height);
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.NoToneMapping;
  host.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(%(background)s);
  scene.environment = new THREE.PMREMGenerator(renderer).fromScene(new RoomEnvironment(), 0.04).texture;
  const camera = new THREE.PerspectiveCamera(40, width / height, 0.001, 1000);
  const fixed = %(camera)s;
  const glb = Uint8Array.from(atob(%(glb)s), c => c.charCodeAt(0));
  new GLTFLoader().parse(glb.buffer, '', gltf => {
    scene.add(gltf.scene);
    if (fixed) {
      camera.matrixAutoUpdate = false;
      camera.matrix.fromArray(fixed.matrix);
      camera.matrixWorld.copy(camera.matrix);
      camera.matrixWorldInverse.copy(camera.matrix).invert();
      camera.projectionMatrix.fromArray(fixed.projection);
      camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
      renderer.render(scene, camera);
    } else {
      const box = new THREE.Box3().setFromObject(gltf.scene);
      const centre = box.getCenter(new THREE.Vector3());
      const size = box.getSize(new THREE.Vector3()).length();
      camera.near = size / 100; camera.far = size * 100; camera.updateProjectionMatrix();
      camera.position.copy(centre).add(new THREE.Vector3(0.6, 0.5, 1.0).multiplyScalar(size));
      const controls = new OrbitControls(camera, renderer.domElement);
      controls.target.copy(centre);
      controls.update();
      renderer.setAnimationLoop(() => { controls.update(); renderer.render(scene, camera); });
    }
    host.dataset.rendered = '1';
  }, error => { host.dataset.error = String(error); });
})();
"""


@cache
def _bundle() -> str:
    return BUNDLE.read_text()


def _fixed_camera(intrinsics: Intrinsics, pose: Pose, near: float, far: float) -> dict[str, list[float]]:
    """three.js's camera matrix and projection (column-major) for a photo's view."""
    to_world = np.eye(4)
    to_world[:3, :3] = Z_UP_TO_Y_UP @ pose.R.T @ OPENCV_TO_GL
    to_world[:3, 3] = Z_UP_TO_Y_UP @ pose.center
    width, height = intrinsics.width, intrinsics.height
    projection = np.array(
        [
            [2 * intrinsics.fx / width, 0.0, 1 - 2 * intrinsics.cx / width, 0.0],
            [0.0, 2 * intrinsics.fy / height, 2 * intrinsics.cy / height - 1, 0.0],
            [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )
    return {"matrix": to_world.T.ravel().tolist(), "projection": projection.T.ravel().tolist()}


def viewer_fragment(
    glb: bytes,
    element_id: str = "viewer",
    size: tuple[int, int] = (640, 480),
    view: tuple[Intrinsics, Pose] | None = None,
    background: str = "#ffffff",
) -> str:
    """HTML for a viewer of ``glb`` in a ``size`` (width, height) box: the model framed
    and orbiting, or, with ``view``, that photo's view at its own size."""
    camera = "null"
    if view is not None:
        intrinsics, _ = view
        size = (intrinsics.width, intrinsics.height)
        camera = json.dumps(_fixed_camera(*view, near=0.01, far=100.0))
    init = INIT % {
        "id": json.dumps(element_id),
        "width": size[0],
        "height": size[1],
        "background": json.dumps(background),
        "camera": camera,
        "glb": json.dumps(base64.b64encode(glb).decode()),
    }
    return (
        f'<div id="{element_id}" class="viewer" style="width:{size[0]}px;height:{size[1]}px"></div>\n'
        f"<script>{_bundle()}</script>\n<script>{init}</script>"
    )


def viewer_page(glb: bytes, title: str = "specimen", **options) -> str:
    """A whole page holding only the viewer (``viewer_fragment``'s options)."""
    return (
        '<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>'
        f"{title}</title><style>body{{margin:0}}</style></head><body>\n"
        f"{viewer_fragment(glb, **options)}\n</body></html>\n"
    )


__all__ = ["viewer_fragment", "viewer_page"]
