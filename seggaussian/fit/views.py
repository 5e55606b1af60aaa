"""Views of a scene ready for fitting: validated, images read (and downscaled) into float tensors,
anonymized pixels masked.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Sequence

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.core.scene import Scene
from seggaussian.sources._common import read_valid_mask
from seggaussian.sources.raycast import MeshRaycaster

if TYPE_CHECKING:
    import torch

class FitInputError(ValueError):
    """A scene that cannot be fitted; the message names the scene, the file or view, and the field."""


class ViewData(NamedTuple):
    """A view ready for fitting: camera at the processed size and its image."""

    name: str
    camera: Camera
    image: "torch.Tensor"  # [H, W, 3] float32 in [0, 1]
    viewmat: "torch.Tensor"  # [4, 4] float32
    K: "torch.Tensor"  # [3, 3] float32
    valid: "torch.Tensor | None" = None  # [H, W] bool, False on anonymized pixels; None = all valid
    depth: "torch.Tensor | None" = None  # [H, W] float32 camera z of the scene's mesh, 0 = no hit; None = no mesh


def masked_render(image: "torch.Tensor", view: ViewData) -> "torch.Tensor":
    """The render ``[H, W, 3]`` with its anonymized pixels replaced by the target's: those pixels add
    nothing to L1, D-SSIM or PSNR and pass no gradient (the anonymization masks' pixels are ignored)."""
    import torch

    if view.valid is None:
        return image
    return torch.where(view.valid[..., None], image, view.image)


def validate_scene(scene: Scene) -> None:
    """Raise ``FitInputError`` for a scene that cannot be fitted (no views, no points, bad poses)."""
    sid = scene.scene_id
    if not scene.views_with_role("train"):
        raise FitInputError(f"scene {sid}: no train views to fit (views: {len(scene.views)})")
    if scene.points.shape[0] == 0:
        raise FitInputError(f"scene {sid}: no initial points (Scene.points is empty)")
    if not np.isfinite(scene.points).all():
        bad = int((~np.isfinite(scene.points).all(axis=1)).sum())
        raise FitInputError(f"scene {sid}: Scene.points has {bad} non-finite rows")
    for view in scene.views:
        cam = view.camera
        if not (np.isfinite(cam.viewmat).all() and np.isfinite(cam.K).all()):
            raise FitInputError(f"scene {sid}, view {view.name}: camera viewmat or K is not finite")
        if abs(np.linalg.det(cam.viewmat[:3, :3]) - 1.0) > 1e-3:
            raise FitInputError(f"scene {sid}, view {view.name}: camera viewmat rotation is not a rotation "
                                f"(det {np.linalg.det(cam.viewmat[:3, :3]):.4f})")
        if view.image_path is None:
            raise FitInputError(f"scene {sid}, view {view.name}: no image (View.image_path is None)")


def read_image(path: Path, camera: Camera) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB; the size must match the camera's."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FitInputError(f"{path}: image file not found")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FitInputError(f"{path}: not a readable image")
    h, w = bgr.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise FitInputError(f"{path}: image is {w}x{h} but the camera width/height is "
                            f"{camera.width}x{camera.height}")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def load_views(views: Sequence, downscale: float) -> list[ViewData]:
    """Read and (optionally) downscale the images of ``views`` (``scene.View``)."""
    import cv2
    import torch

    out = []
    for view in views:
        rgb = read_image(view.image_path, view.camera)
        camera = view.camera
        if downscale != 1.0:
            camera = camera.scaled(1.0 / downscale)
            rgb = cv2.resize(rgb, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        image = torch.from_numpy(rgb.astype(np.float32) / 255.0)
        valid = None
        if view.mask_path is not None:
            mask = read_valid_mask(view.mask_path, camera.width, camera.height)
            valid = None if mask.all() else torch.from_numpy(mask)
        out.append(ViewData(view.name, camera, image, torch.from_numpy(camera.viewmat.astype(np.float32)),
                            torch.from_numpy(camera.K.astype(np.float32)), valid))
    return out


def evenly_spaced(items: Sequence, count: int) -> list:
    if count >= len(items):
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def with_mesh_depth(views: Sequence[ViewData], points: np.ndarray, faces: np.ndarray | None) -> list[ViewData]:
    """``views`` with ``depth`` set to the camera z of the mesh ``(points, faces)`` per pixel centre (raycast,
    0 where a ray misses); unchanged when there is no mesh (``faces`` None or empty)."""
    import torch

    if faces is None or len(faces) == 0 or not views:
        return list(views)
    caster = MeshRaycaster(points, faces)
    return [view._replace(depth=torch.from_numpy(caster.cast(view.camera).depth.astype(np.float32)))
            for view in views]
