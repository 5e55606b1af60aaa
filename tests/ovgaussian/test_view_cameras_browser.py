"""``ovgaussian view`` opens inside a dataset room at one of its cameras, in a real browser (Debian's chromium,
headless, software WebGL), and a click on a camera's frustum moves the view there.

The room is ``test_view``'s synthetic room closed by three more walls and a ceiling, written as a one-scene dataset
with three view cameras inside (OpenCV world-to-camera, as every dataset stores them). The browser's first frame is
compared with our CPU rasterizer's render of the same camera (``seggaussian.render``): the conversion of the shards'
OpenCV camera into viser's (and three.js's RUB) camera is checked against a reference outside the viewer, and a
camera turned 180 degrees about its x axis (the classic OpenCV / OpenGL mix-up) must match far worse.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from test_view import synthetic_room
from test_view_browser import CHROMIUM, CHROMIUM_ARGS, _hide_overlays, _screenshot, _settle, _wait

#: Viewport (CSS pixels, device scale 1 and ?fixedDpr=1): the cameras' aspect, 4:3.
VIEWPORT = (320, 240)
#: The cameras' image size and focal length (pixels): 4:3, a vertical field of view of about 62 degrees.
IMAGE = (160, 120, 100.0)
#: Share of the central region (the middle half of each side) that must show splats, not background.
MIN_FILLED = 0.95
#: A screenshot pixel is background when every channel is within this of viser's white background.
BACKGROUND_TOLERANCE = 6
#: Lowest correlation accepted between the browser's first frame and our rasterizer's image of the same camera
#: (grey levels, centre region). Measured: 0.9995 (mean absolute difference 0.6 grey levels); the flipped camera
#: -0.03.
MIN_CORRELATION = 0.9
#: The flipped camera's correlation must be this much lower.
FLIP_MARGIN = 0.3


def closed_room():
    """``synthetic_room`` (floor, back wall, chairs, table, sofa in [-2, 2]^2, z up) with the front, left and right
    walls and a ceiling at 2.5 m added (class wall / ceiling), so no camera inside sees out."""
    from seggaussian.core.constants import SH_C0, read_class_names
    from seggaussian.core.gaussians import Gaussians

    names = read_class_names()
    room = synthetic_room()
    step = 0.1
    u = np.arange(-2.0, 2.0 + 1e-9, step)
    h = np.arange(0.0, 2.5 + 1e-9, step)
    parts = []  # means, flat axis, class, rgb
    for fixed, (a, b) in (((1, -2.0), np.meshgrid(u, h, indexing="ij")), ((0, -2.0), np.meshgrid(u, h, indexing="ij")),
                          ((0, 2.0), np.meshgrid(u, h, indexing="ij"))):
        axis, value = fixed
        means = np.zeros((a.size, 3))
        means[:, axis] = value
        means[:, 1 - axis] = a.reshape(-1)
        means[:, 2] = b.reshape(-1)
        parts.append((means, axis, "wall", (0.6 + 0.1 * axis, 0.7, 0.55 + 0.2 * (value > 0))))
    a, b = np.meshgrid(u, u, indexing="ij")
    parts.append((np.stack([a.reshape(-1), b.reshape(-1), np.full(a.size, 2.5)], 1), 2, "ceiling", (0.9, 0.9, 0.85)))
    means = [room.means]
    log_scales = [room.log_scales]
    dc = [room.sh[:, :1]]
    semantic = [room.extras["semantic"]]
    for pts, axis, name, rgb in parts:
        scales = np.full((len(pts), 3), 0.07)
        scales[:, axis] = 0.01
        means.append(pts)
        log_scales.append(np.log(scales))
        dc.append(np.tile(((np.asarray(rgb) - 0.5) / SH_C0)[None, None], (len(pts), 1, 1)))
        semantic.append(np.full(len(pts), names.index(name), np.int32))
    means = np.concatenate(means)
    n = len(means)
    return Gaussians.from_arrays(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.concatenate(log_scales),
                                 np.full(n, 4.0), np.concatenate(dc).astype(np.float32),
                                 extras={"semantic": np.concatenate(semantic).astype(np.int32),
                                         "instance": np.zeros(n, np.int32),
                                         "transfer_distance": np.zeros(n, np.float32)})


def room_cameras():
    """Three cameras inside the room at eye height: towards the sofa (back wall), the chairs, the table."""
    from seggaussian.core.cameras import Camera, intrinsics, look_at

    width, height, focal = IMAGE
    K = intrinsics(focal, focal, 0.5 * width, 0.5 * height)
    poses = (((0.2, -1.6, 1.5), (-0.2, 1.5, 0.4)), ((1.5, 1.2, 1.4), (-0.9, -0.4, 0.5)),
             ((-1.5, 1.0, 1.6), (1.0, -0.4, 0.7)))
    return [Camera(K, look_at(eye, target), width, height) for eye, target in poses]


def write_room_dataset(root):
    from seggaussian import shards
    from seggaussian.core.constants import read_class_names
    from seggaussian.shards.config import ShardConfig

    room = closed_room()
    config = ShardConfig(row_group_bytes=1 << 16)
    width, height, _ = IMAGE
    blank = np.zeros((height, width), np.int32)
    rows = [shards.ViewRow(f"frame{i:06d}.jpg", "train", camera, shards.encode_rgb(np.zeros((height, width, 3),
                                                                                              np.uint8)),
                           shards.encode_label_map(blank), shards.encode_label_map(blank), 1.0)
            for i, camera in enumerate(room_cameras())]
    fragments = {}
    for table_name, table in (("gaussians", shards.gaussians_table("room", room)),
                              ("views", shards.views_table("room", rows))):
        fragments[table_name] = root / "cache" / f"{table_name}.parquet"
        shards.write_parquet_atomic(fragments[table_name], table_name, [table], config)
    dataset = root / "dataset"
    shards.write_dataset(dataset, {"room": "val"}, {"room": {"fragments": fragments, "source": "synthetic"}}, config,
                         read_class_names(), "h")
    return dataset, room


@pytest.fixture(scope="module")
def room_viewer(tmp_path_factory):
    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} absent (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright (pip install playwright) is absent")
    pytest.importorskip("viser", reason="viser (extra 'view') is absent")
    from ovgaussian.view.app import QueryViewer
    from ovgaussian.view.scene import load_view_scene
    from ovgaussian.view.state import ViewerState

    dataset, room = write_room_dataset(tmp_path_factory.mktemp("room"))
    viewer = QueryViewer(ViewerState(load_view_scene(dataset=dataset, scene_id="room")), port=0, mode="rgb")
    playwright = sync_api.sync_playwright().start()
    browser = playwright.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
    page = browser.new_page(viewport={"width": VIEWPORT[0], "height": VIEWPORT[1]}, device_scale_factor=1)
    try:
        page.goto(viewer.url + "/?fixedDpr=1")
        from ovgaussian.view.app import wait_for_clients

        (client,) = wait_for_clients(viewer)
        _settle(client)
        yield viewer, page, client, room
    finally:
        browser.close()
        playwright.stop()
        viewer.stop()


def _assert_at(client, camera) -> None:
    from ovgaussian.view.cameras import camera_pose, frustum_wxyz

    pose = camera_pose(camera)
    np.testing.assert_allclose(client.camera.position, pose.position, atol=1e-4)
    wxyz = np.asarray(client.camera.wxyz)
    expected = frustum_wxyz(camera)
    assert min(np.abs(wxyz - expected).max(), np.abs(wxyz + expected).max()) < 1e-4, (wxyz, expected)
    assert abs(client.camera.fov - pose.fov) < 1e-6


def _stable_screenshot(page) -> np.ndarray:
    previous = None
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        image = _screenshot(page)
        if previous is not None and np.array_equal(image, previous):
            return image
        previous = image
        time.sleep(0.5)
    raise AssertionError("the browser never showed a stable frame")


def _centre(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    return image[h // 4:h - h // 4, w // 4:w - w // 4]


def _grey_correlation(a: np.ndarray, b: np.ndarray) -> float:
    a = _centre(a).astype(np.float64).mean(axis=2).reshape(-1)
    b = _centre(b).astype(np.float64).mean(axis=2).reshape(-1)
    return float(np.corrcoef(a, b)[0, 1])


def _render(room, camera) -> np.ndarray:
    import torch

    from seggaussian.render import render_gaussians

    out = render_gaussians(room, camera, sh_degree=0, background=torch.ones(3))
    return np.clip(np.round(out.image.numpy() * 255.0), 0, 255).astype(np.uint8)


def test_fresh_page_opens_inside_the_room_at_a_scene_camera(room_viewer):
    from seggaussian.core.cameras import Camera

    viewer, page, client, room = room_viewer
    cameras = viewer.state.scene.cameras
    assert len(cameras) == 3 and viewer.start_camera is not None
    start = cameras[viewer.start_camera].camera
    _wait(lambda: np.allclose(client.camera.position, start.center, atol=1e-4), "the page's initial camera")
    _settle(client)
    _assert_at(client, start)  # the pose the browser reports is the dataset camera's
    viewer.show_cameras.value = False  # "Show cameras" off: measure the splats alone
    assert viewer.frustums and not any(handle.visible for handle in viewer.frustums.values())
    _hide_overlays(page)
    image = _stable_screenshot(page)
    assert image.shape[:2] == (VIEWPORT[1], VIEWPORT[0])
    background = (np.abs(image.astype(np.int32) - 255) <= BACKGROUND_TOLERANCE).all(axis=2)
    filled = 1.0 - float(_centre(background).mean())
    # our rasterizer's image of the dataset camera as the canvas shows it (same pose and vertical fov)
    scale = VIEWPORT[1] / start.height
    shown = Camera(np.diag([scale, scale, 1.0]) @ start.K, start.viewmat, VIEWPORT[0], VIEWPORT[1])
    flip = np.diag([1.0, -1.0, -1.0, 1.0]) @ start.viewmat  # 180 degrees about the camera's x axis
    right = _grey_correlation(image, _render(room, shown))
    wrong = _grey_correlation(image, _render(room, Camera(shown.K, flip, shown.width, shown.height)))
    print(f"filled {filled:.3f}, correlation with the rasterizer {right:.3f}, with the flipped camera {wrong:.3f}")
    assert filled >= MIN_FILLED
    assert right >= MIN_CORRELATION and right >= wrong + FLIP_MARGIN
    viewer.show_cameras.value = True
    assert [i for i, handle in viewer.frustums.items() if not handle.visible] == [viewer.start_camera]


def test_click_on_a_frustum_moves_the_camera_there(room_viewer):
    from ovgaussian.view.app import FRUSTUM_RGB
    from ovgaussian.view.cameras import browser_camera

    viewer, page, client, room = room_viewer
    cameras = viewer.state.scene.cameras
    target = next(i for i in range(len(cameras)) if i != viewer.start_camera)
    centre = cameras[target].camera.center
    with client.atomic():  # look at the target camera from where the page opened
        client.camera.look_at = tuple(centre)
    _settle(client)
    _hide_overlays(page)
    image = _stable_screenshot(page)
    orange = (np.abs(image.astype(np.int32) - np.asarray(FRUSTUM_RGB)) <= 60).all(axis=2)
    view = browser_camera(client.camera.position, client.camera.wxyz, client.camera.fov, VIEWPORT[0], VIEWPORT[1])
    (uv,), _ = view.project(centre[None])
    rows, cols = np.nonzero(orange)
    assert rows.size, "no frustum drawn in view"
    k = int(np.argmin((cols + 0.5 - uv[0]) ** 2 + (rows + 0.5 - uv[1]) ** 2))
    viewer.last_camera = None
    page.mouse.click(int(cols[k]), int(rows[k]))
    _wait(lambda: viewer.last_camera is not None, "the click on the frustum")
    assert viewer.last_camera == target
    _wait(lambda: np.allclose(client.camera.position, centre, atol=1e-4), "the camera to move")
    _settle(client)
    _assert_at(client, cameras[target].camera)
