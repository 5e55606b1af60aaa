"""Render one view of a 3DGS PLY to a PNG (``seggaussian render``): explicit camera or an orbit camera."""

from __future__ import annotations

import errno
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seggaussian.util.atomic import atomic_path
from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.frames.frame_config import FrameConfig, frame_record, to_scene_frame
from seggaussian.io.formats import read_gaussians
from seggaussian.render.rasterize import render_gaussians

#: The orbit camera stands this many times the scene's robust radius away from its centre.
ORBIT_DISTANCE_FACTOR = 2.2
#: Robust scene radius: this quantile of the distances of the means to their median.
ORBIT_RADIUS_QUANTILE = 0.9


@dataclass(frozen=True)
class QuicklookConfig:
    """What ``render_ply_view`` renders.

    Fields:
        ply: the 3DGS PLY to read.
        out: the PNG to write (8-bit RGB; written to a temporary name, then renamed).
        camera_json: a JSON file with ``K`` (3x3), ``viewmat`` (4x4 world-to-camera, OpenCV axes), ``width``,
            ``height``; when None, an orbit camera looks at the scene centre.
        width, height: image size of the orbit camera.
        azimuth_deg, elevation_deg: direction of the orbit camera around the world z axis (z up).
        fov_deg: horizontal field of view of the orbit camera.
        sh_degree: SH bands used (None: all stored).
        background: RGB background in [0, 1].
        backend: rasterizer backend (``auto``, ``fast``, ``reference``).
        frame: the splat's frame (``--transform``, ``--from-frame``): the scene is moved into the scene's frame
            before the camera (given in that frame) looks at it.
    """

    ply: Path
    out: Path
    camera_json: Path | None = None
    width: int = 640
    height: int = 480
    azimuth_deg: float = -60.0
    elevation_deg: float = 30.0
    fov_deg: float = 60.0
    sh_degree: int | None = None
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    backend: str = "auto"
    frame: FrameConfig = FrameConfig()


class CameraFileError(ValueError):
    """A camera JSON that cannot be used; the message names the file and the field."""


def read_camera_json(path: Path) -> Camera:
    """``{"K": 3x3, "viewmat": 4x4, "width": int, "height": int}`` -> Camera."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CameraFileError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(data, dict):
        raise CameraFileError(f"{path}: expected a JSON object with K, viewmat, width, height")
    fields = {}
    for name, shape in (("K", (3, 3)), ("viewmat", (4, 4))):
        if name not in data:
            raise CameraFileError(f"{path}: missing field {name!r}")
        try:
            value = np.asarray(data[name], dtype=np.float64)
        except (TypeError, ValueError):
            raise CameraFileError(f"{path}: field {name!r} is not a numeric matrix") from None
        if value.shape != shape or not np.isfinite(value).all():
            raise CameraFileError(f"{path}: field {name!r} must be a finite {shape[0]}x{shape[1]} matrix")
        fields[name] = value
    for name in ("width", "height"):
        value = data.get(name)
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise CameraFileError(f"{path}: field {name!r} must be a positive integer, got {value!r}")
        fields[name] = value
    return Camera(fields["K"], fields["viewmat"], fields["width"], fields["height"])


def orbit_camera(means: np.ndarray, config: QuicklookConfig) -> Camera:
    """A camera at ORBIT_DISTANCE_FACTOR robust radii from the median of ``means``, looking at it (z up)."""
    finite = means[np.isfinite(means).all(1)] if len(means) else means
    centre = np.median(finite, axis=0) if len(finite) else np.zeros(3)
    radius = float(np.quantile(np.linalg.norm(finite - centre, axis=1), ORBIT_RADIUS_QUANTILE)) if len(finite) else 1.0
    radius = max(radius, 1e-3)
    az, el = math.radians(config.azimuth_deg), math.radians(config.elevation_deg)
    direction = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    eye = centre + ORBIT_DISTANCE_FACTOR * radius * direction
    focal = 0.5 * config.width / math.tan(math.radians(config.fov_deg) / 2)
    K = intrinsics(focal, focal, config.width / 2, config.height / 2)
    return Camera(K, look_at(eye, centre), config.width, config.height)


def write_png_atomic(path: Path, rgb: np.ndarray) -> None:
    """uint8 RGB ``[H, W, 3]`` -> PNG, via a temporary file in the same folder and ``os.replace``."""
    import cv2

    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(errno.EIO, "could not write the PNG", str(path))


def render_ply_view(config: QuicklookConfig) -> dict:
    """Read the PLY, render the view, write the PNG; returns a JSON-ready summary."""
    import torch

    start = time.perf_counter()
    gaussians, _report, _format = read_gaussians(config.ply)  # any splat format, detected by content
    gaussians, frame = to_scene_frame(gaussians, config.frame)
    camera = read_camera_json(config.camera_json) if config.camera_json else orbit_camera(gaussians.means, config)
    out = render_gaussians(
        gaussians, camera, sh_degree=config.sh_degree,
        background=torch.tensor(config.background, dtype=torch.float32), backend=config.backend,
    )
    rgb = (out.image.detach().clamp(0.0, 1.0).numpy() * 255.0 + 0.5).astype(np.uint8)
    Path(config.out).parent.mkdir(parents=True, exist_ok=True)
    write_png_atomic(config.out, rgb)
    alpha = out.alpha.detach().numpy()
    return {
        "ply": str(config.ply), "out": str(config.out), "num_gaussians": len(gaussians), "frame": frame_record(frame),
        "sh_degree": gaussians.sh_degree if config.sh_degree is None else config.sh_degree,
        "width": camera.width, "height": camera.height, "covered_fraction": float((alpha > 0.5).mean()),
        "camera": {"K": camera.K, "viewmat": camera.viewmat}, "seconds": time.perf_counter() - start,
    }
