"""What a fresh ``ovgaussian view`` page of a dataset room shows: the share of the canvas's central region covered by
splats (not background), and how the first frame correlates with our rasterizer's render of the camera it opens at.

    .venv/bin/python benchmarks/view_first_frame.py --data out/demo/dataset --out benchmarks/results/view_cameras.md

Per room of the splits (val and xval by default): the viewer serves the dataset scene (RGB), headless Debian
chromium with software WebGL (as tests/ovgaussian/test_view_browser.py) opens a fresh page of ``--viewport``, waits
for the camera the viewer opens at, switches the frustums off, and takes the canvas alone. Central region: the middle
half of each side. Background: viser's white (every channel within 6 of 255). The reference is
``seggaussian.render.render_gaussians`` (DC colour, white background) of the same camera at the canvas size (the
view's vertical field of view, principal point centred, as the browser draws it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "ovgaussian"))  # the browser tests' chromium set-up and helpers

#: A pixel is background when every channel is within this of 255 (viser's white).
BACKGROUND_TOLERANCE = 6


def central(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    return image[h // 4:h - h // 4, w // 4:w - w // 4]


def measure_room(browser, data: Path, scene_id: str, viewport) -> dict:
    import torch

    from ovgaussian.view.app import QueryViewer, wait_for_clients
    from ovgaussian.view.scene import load_view_scene
    from ovgaussian.view.state import ViewerState
    from seggaussian.core.cameras import Camera, intrinsics
    from seggaussian.render import render_gaussians
    from test_view_browser import _hide_overlays, _settle, _wait
    from test_view_cameras_browser import _stable_screenshot

    scene = load_view_scene(dataset=data, scene_id=scene_id)
    viewer = QueryViewer(ViewerState(scene), port=0, mode="rgb")
    page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]}, device_scale_factor=1)
    try:
        start = time.perf_counter()
        page.goto(viewer.url + "/?fixedDpr=1")
        (client,) = wait_for_clients(viewer)
        camera = scene.cameras[viewer.start_camera].camera
        _wait(lambda: np.allclose(client.camera.position, camera.center, atol=1e-4), "the initial camera")
        _settle(client)
        viewer.show_cameras.value = False
        _hide_overlays(page)
        image = _stable_screenshot(page)  # gives up after 60 s
        seconds = time.perf_counter() - start
        background = (np.abs(image.astype(np.int32) - 255) <= BACKGROUND_TOLERANCE).all(axis=2)
        focal = camera.K[1, 1] * viewport[1] / camera.height  # the view's vertical fov, square pixels, centred
        shown = Camera(intrinsics(focal, focal, 0.5 * viewport[0], 0.5 * viewport[1]), camera.viewmat, viewport[0],
                       viewport[1])
        reference = render_gaussians(scene.gaussians, shown, sh_degree=0, background=torch.ones(3)).image.numpy()
        reference = np.clip(np.round(reference * 255.0), 0, 255)
        a = central(image).astype(np.float64).mean(axis=2).reshape(-1)
        b = central(reference).mean(axis=2).reshape(-1)
        return {"scene": scene_id, "gaussians": len(scene.gaussians), "cameras": len(scene.cameras),
                "camera": scene.cameras[viewer.start_camera].name, "filled": 1.0 - float(central(background).mean()),
                "correlation": float(np.corrcoef(a, b)[0, 1]), "seconds": seconds}
    finally:
        page.close()
        viewer.stop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (seggaussian build + split)")
    parser.add_argument("--splits", default="val,xval", help="comma-separated splits whose rooms are opened")
    parser.add_argument("--viewport", default="800x600", help="browser viewport WIDTHxHEIGHT (CSS pixels)")
    parser.add_argument("--out", type=Path, default=None, help="write the table as Markdown here")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    from seggaussian import shards
    from seggaussian.util.atomic import atomic_path
    from test_view_browser import CHROMIUM, CHROMIUM_ARGS

    viewport = tuple(int(v) for v in args.viewport.lower().split("x"))
    splits = [s.strip() for s in args.splits.split(",") if s.strip()]
    rows = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        try:
            for split in splits:
                for scene_id in shards.list_scenes(args.data, split):
                    rows.append(measure_room(browser, args.data, scene_id, viewport) | {"split": split})
                    print(f"{split} {scene_id}: {rows[-1]['filled']:.3f} filled", file=sys.stderr, flush=True)
        finally:
            browser.close()
    lines = ["| split | room | Gaussians | cameras | opens at | central region filled | correlation with the "
             "rasterizer | seconds to the first stable frame |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['split']} | {r['scene']} | {r['gaussians']:,} | {r['cameras']} | {r['camera']} | "
                     f"{100 * r['filled']:.1f} % | {r['correlation']:.3f} | {r['seconds']:.1f} |")
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        doc = (f"# `ovgaussian view`: the first frame of a dataset room\n\n"
               f"`benchmarks/view_first_frame.py --data DATA --splits {','.join(splits)} --viewport {args.viewport}`"
               f" (headless chromium, software WebGL).\n\n{text}\n")
        with atomic_path(args.out, suffix=".md") as tmp:
            tmp.write_text(doc)
    print(f"view first frame: {len(rows)} rooms, central region filled {100 * min(r['filled'] for r in rows):.1f} "
          f"to {100 * max(r['filled'] for r in rows):.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
