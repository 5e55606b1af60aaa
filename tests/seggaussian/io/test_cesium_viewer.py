"""Our glTF splats (``KHR_gaussian_splatting``) drawn by CesiumJS, the extension's authors' renderer, in headless
Chromium, against our CPU rasterizer from the same camera.

CesiumJS 1.145.0 (npm ``cesium``, installed into ``.node/cesium`` by ``make setup``) draws Gaussian splats only as 3D
Tiles content, and only when the tileset's ``3DTILES_content_gltf`` requires both ``KHR_gaussian_splatting`` and
``KHR_gaussian_splatting_compression_spz_2`` (``GaussianSplat3DTileContent.tilesetRequiresGaussianSplattingExt``);
other glTF content goes to its mesh/point-cloud path, which leaves the splat attributes unread. So the file checked
here is our ``.glb`` with the SPZ compression extension (``seggaussian.io.gltf``, ``compression="spz"``); the
uncompressed base extension shares every convention with it except the attribute storage (its attributes are
checked against the extension's text in ``test_gltf.py``).

The tileset is one tile whose content is the ``.glb``, with no root transform. Cesium turns glTF's y-up into the
tileset's z-up (3D Tiles' "y-up to z-up": ``(x, y, z) -> (x, -z, y)``), so a point of our RDF scene lands in
Cesium's world at ``Y_UP_TO_Z_UP @ LUF_FROM_RDF @ p``; our camera (OpenCV axes, world-to-camera) is handed to the
page as Cesium's position, view direction and up vector in that world (``cesium_camera``). The page
(``cesium_viewer.html``) has no globe, imagery, terrain, sky or Ion token and reads nothing but the local server.

Checks as ``test_web_viewer.py`` (whose scenes, camera, reference images and measures it shares): the correlation of
the blurred images and their mean colour difference, in natural colours and coloured by label with the labels kept
as ``_SEMANTIC`` / ``_INSTANCE`` attributes (which Cesium must ignore), and a negative control, the scene mirrored
in x, written by the same writer and shown from the same camera, which must fail the structural check.
"""

from __future__ import annotations

import json
import urllib.parse
from pathlib import Path

import numpy as np
import pytest

from seggaussian.core.cameras import Camera
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.gltf import GLTF_FRAME, SPZ_EXTENSION, EXTENSION, write_gltf
from seggaussian.frames.axes import axes_to_rdf
from test_web_viewer import (PART_LABELS, _letter_f_scene, agreement, browser, browser_skip_reason,  # noqa: F401
                             label_scene, mean_abs_difference, mirrored_in_x, page_image, reference_image, rgb_scene,
                             static_server, view_camera)

ROOT = Path(__file__).resolve().parents[3]
PAGE = Path(__file__).resolve().with_name("cesium_viewer.html")
CESIUM_BUILD = ROOT / ".node" / "cesium" / "node_modules" / "cesium" / "Build" / "Cesium"
#: Seconds a page may take to load the tile, decode the SPZ data, sort and settle.
PAGE_TIMEOUT_S = 60.0
#: 3D Tiles' glTF y-up to the tileset's z-up: a rotation by +90 degrees about x.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: Our RDF coordinates to Cesium's world (the tileset's frame): RDF -> glTF's LUF -> z-up.
CESIUM_FROM_RDF = Y_UP_TO_Z_UP @ np.linalg.inv(axes_to_rdf(GLTF_FRAME))
#: Structural check, as for Spark. Measured here (Chromium, SwiftShader, CesiumJS 1.145.0; 1341 Gaussians, 320x240):
#: our files 0.9995 (natural colours) and 0.9996 (coloured by label); the scene mirrored in x 0.45, turned by 180
#: degrees about x 0.61; the SPZ blob written in SPZ's own RUB instead of glTF's frame (the scene turned about y in
#: Cesium) 0.47.
AGREEMENT_MIN = 0.99
#: Colour check, 8-bit levels. Measured: 0.53 and 0.59; the controls 8.6-11.9.
COLOUR_MAD_MAX = 1.0


_SKIP_REASON = browser_skip_reason("CesiumJS", (CESIUM_BUILD / "Cesium.js",))
pytestmark = pytest.mark.skipif(_SKIP_REASON is not None, reason=_SKIP_REASON or "")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """(base URL, folder served at the root): a static server on 127.0.0.1 at a free port, in a thread."""
    root = tmp_path_factory.mktemp("cesium_viewer")
    with static_server(root, PAGE, {"/cesium/": CESIUM_BUILD}) as url:
        yield url, root


def cesium_camera(camera: Camera) -> dict:
    """Our camera (OpenCV axes, RDF world) as the page takes it: position, view direction and up in Cesium's world,
    the horizontal field of view (square pixels, principal point at the centre required)."""
    K = camera.K
    assert K[0, 0] == K[1, 1] and K[0, 2] == camera.width / 2 and K[1, 2] == camera.height / 2
    rotation, translation = camera.viewmat[:3, :3], camera.viewmat[:3, 3]
    centre = -rotation.T @ translation
    return {"position": (CESIUM_FROM_RDF @ centre).tolist(), "direction": (CESIUM_FROM_RDF @ rotation[2]).tolist(),
            "up": (CESIUM_FROM_RDF @ -rotation[1]).tolist(), "fovx": float(2 * np.arctan(camera.width / (2 * K[0, 0]))),
            "width": camera.width, "height": camera.height}


def write_tileset(folder: Path, stem: str, gaussians: Gaussians) -> Path:
    """``stem.glb`` (SPZ-compressed) and a one-tile ``stem.tileset.json`` pointing at it."""
    write_gltf(folder / f"{stem}.glb", gaussians, compression="spz")
    centre = CESIUM_FROM_RDF @ ((gaussians.means.min(0) + gaussians.means.max(0)) / 2)
    radius = float(np.linalg.norm(gaussians.means.max(0) - gaussians.means.min(0))) + 1.0
    tileset = {
        "asset": {"version": "1.1"},
        "extensionsUsed": ["3DTILES_content_gltf"],
        "extensions": {"3DTILES_content_gltf": {"extensionsUsed": [EXTENSION, SPZ_EXTENSION],
                                                "extensionsRequired": [EXTENSION, SPZ_EXTENSION]}},
        "geometricError": 1.0,
        "root": {"boundingVolume": {"sphere": [*centre.tolist(), radius]}, "geometricError": 0.0, "refine": "ADD",
                 "content": {"uri": f"{stem}.glb"}},
    }
    path = folder / f"{stem}.tileset.json"
    path.write_text(json.dumps(tileset))
    return path


def render_in_cesium(browser, server, tileset: Path, camera: Camera) -> tuple[np.ndarray, dict]:
    """Cesium's image (uint8 RGB) of the tileset from ``camera``, and the page's result record."""
    base, root = server
    query = urllib.parse.urlencode({"tileset": f"/{tileset.relative_to(root).as_posix()}",
                                    "camera": json.dumps(cesium_camera(camera))})
    return page_image(browser, f"{base}/viewer.html?{query}", camera.width, camera.height, PAGE_TIMEOUT_S)


def _save(folder: Path, image: np.ndarray, reference: np.ndarray) -> str:
    import cv2

    for name, rgb in (("cesium", image), ("ours", reference)):
        cv2.imwrite(str(folder / f"{name}.png"), np.ascontiguousarray(rgb[..., ::-1]))
    return f"images in {folder}"


def labelled_scene() -> Gaussians:
    """The "F" coloured by label, its labels kept as ``_SEMANTIC`` and ``_INSTANCE`` attributes (Cesium must ignore
    them)."""
    _, parts = _letter_f_scene()
    labels = np.asarray(PART_LABELS)[parts]
    return label_scene().with_extras(semantic=labels.astype(np.int32), instance=parts.astype(np.int32))


CASES = {"rgb": rgb_scene, "labelled": labelled_scene}


@pytest.mark.parametrize("case", list(CASES))
def test_cesium_draws_our_glb_as_we_render_it(browser, server, tmp_path, case):
    """Cesium's image of our ``.glb`` equals our rasterizer's image of the same Gaussians: structure (correlation) and
    colour (mean absolute difference), with every Gaussian drawn."""
    scene = CASES[case]()
    camera = view_camera()
    reference = reference_image(scene, camera, dc_only=False)
    image, result = render_in_cesium(browser, server, write_tileset(server[1], case, scene), camera)
    score, mad = agreement(image, reference), mean_abs_difference(image, reference)
    assert result["count"] == len(scene) and score >= AGREEMENT_MIN and mad <= COLOUR_MAD_MAX, (
        f"{case}: Cesium drew {result['count']} of {len(scene)} Gaussians; correlation {score:.4f} (needs >= "
        f"{AGREEMENT_MIN}), colour difference {mad:.2f} levels (needs <= {COLOUR_MAD_MAX}); "
        f"{_save(tmp_path, image, reference)}")


def test_mirrored_glb_fails_the_check(browser, server, tmp_path):
    """Negative control: the scene mirrored in x, written by the same writer and shown from the same camera, is told
    apart from our image of the scene (the check above can fail)."""
    scene = rgb_scene()
    camera = view_camera()
    reference = reference_image(scene, camera, dc_only=False)
    image, _ = render_in_cesium(browser, server, write_tileset(server[1], "mirrored", mirrored_in_x(scene)), camera)
    score = agreement(image, reference)
    assert score < AGREEMENT_MIN, (f"the mirrored scene passes (correlation {score:.4f}); "
                                   f"{_save(tmp_path, image, reference)}")
