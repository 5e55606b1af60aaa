"""views stage: per selected view, the RGB image and the label maps rendered through the blend weights -> ``views.parquet``.

Label maps come from the one rasterizer (``seggaussian.render``): per-pixel blend weights of the labelled
Gaussians, voted on inside the walk (``render_label_images``), the ignore label counted as a label of its own;
anonymized pixels (ScanNet++ masks) are ignore.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from seggaussian.pipeline.config import BuildConfig, ViewConfig

from seggaussian.shards.config import ShardConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.gaussians import Gaussians
from seggaussian.render import render_gaussians
from seggaussian.render.label_images import prepare_label_scene, render_label_scene
from seggaussian.render.rasterize import camera_tensors
from seggaussian.core.scene import Scene
from seggaussian.shards.files import write_parquet_atomic
from seggaussian.shards.images import encode_label_map, encode_rgb, image_format
from seggaussian.shards.records import ViewRow
from seggaussian.shards.tables import views_table
from seggaussian.sources._common import read_valid_mask

#: Files the stage writes into the scene's cache folder.
OUTPUTS = ("views.parquet",)


def select_views(views, stride: int) -> list:
    """Every ``stride``-th train view plus every novel view, in source order."""
    out, k = [], 0
    for v in views:
        if v.role == "novel":
            out.append(v)
        else:
            if k % max(1, stride) == 0:
                out.append(v)
            k += 1
    return out


def view_scale(width: int, height: int, config: ViewConfig) -> float:
    """Image scale of a view: ``image_scale``, reduced so that the longer side stays within ``max_image_side``."""
    scale = float(config.image_scale)
    if config.max_image_side and max(width, height) * scale > config.max_image_side:
        scale = config.max_image_side / max(width, height)
    return scale


def run_views(scene: Scene, gaussians: Gaussians, config: BuildConfig, num_classes: int) -> tuple[list, dict]:
    """One ViewRow per selected view: camera, RGB bytes, label maps rendered through the blend weights."""
    t = gaussians.to_torch()
    semantic = torch.from_numpy(gaussians.extras["semantic"].astype(np.int64))
    instance = torch.from_numpy(gaussians.extras["instance"].astype(np.int64))
    rows, label_scene = [], None
    for view in select_views(scene.views, config.views.view_stride):
        cam = view.camera
        scale = view_scale(cam.width, cam.height, config.views)
        if scale != 1.0:
            cam = cam.scaled(scale)
        what = f"scene {scene.scene_id} view {view.name}"
        if view.image_path is not None:
            data = Path(view.image_path).read_bytes()
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if image is None:
                raise ValueError(f"{view.image_path}: image does not decode ({what})")
            if scale == 1.0 and image.shape[:2] == (cam.height, cam.width) and _is_png_or_jpeg(data):
                rgb_bytes = data  # stored as is (exact, no re-encoding)
            else:
                resized = cv2.resize(image, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
                rgb_bytes = encode_rgb(np.ascontiguousarray(resized[:, :, ::-1]))
        else:
            out = render_gaussians(gaussians, cam)
            rgb = (out.image.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
            rgb_bytes = encode_rgb(rgb)
        image_format(rgb_bytes)
        if len(gaussians):
            viewmat, K = camera_tensors(cam)
            if label_scene is None:  # checked and prepared once, for every view
                label_scene = prepare_label_scene(t["means"], t["quats"], t["log_scales"], t["opacity_logits"],
                                                  semantic, instance, num_classes)
            maps = render_label_scene(label_scene, viewmat, K, cam.width, cam.height, top_k=config.views.top_k,
                                      min_alpha=config.views.min_alpha)
            sem_map = maps.semantic.numpy()
            inst_map = maps.instance.numpy()
        else:
            sem_map = np.full((cam.height, cam.width), IGNORE_LABEL, np.int64)
            inst_map = sem_map.copy()
        if view.mask_path is not None:  # anonymized pixels carry no label
            valid = read_valid_mask(view.mask_path, cam.width, cam.height)
            sem_map[~valid] = IGNORE_LABEL
            inst_map[~valid] = IGNORE_LABEL
        rows.append(ViewRow(view.name, view.role, cam, rgb_bytes, encode_label_map(sem_map), encode_label_map(inst_map),
                            float((sem_map != IGNORE_LABEL).mean())))
    coverage = [r.label_coverage for r in rows]
    return rows, {"num_views": len(rows), "novel_views": sum(r.role == "novel" for r in rows),
                  "label_coverage_mean": float(np.mean(coverage)) if coverage else 0.0}


def _is_png_or_jpeg(data: bytes) -> bool:
    return data[:8] == b"\x89PNG\r\n\x1a\n" or data[:3] == b"\xff\xd8\xff"


def write_views(scene_dir: Path, scene_id: str, rows: list, shards: ShardConfig) -> None:
    """The per-scene ``views`` table."""
    write_parquet_atomic(Path(scene_dir) / OUTPUTS[0], "views", [views_table(scene_id, rows)], shards)
