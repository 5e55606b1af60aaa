"""Image codecs of the views table: RGB as PNG (or JPEG, read only), label maps as lossless 16-bit PNG.
"""

from __future__ import annotations

import numpy as np

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.shards.layout import ShardError


def encode_label_map(labels: np.ndarray) -> bytes:
    """``[H, W]`` ids (0..65535, IGNORE_LABEL included) -> 16-bit PNG bytes (lossless)."""
    import cv2

    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"label map has shape {labels.shape}, expected (H, W)")
    if labels.size and (labels.min() < 0 or labels.max() > IGNORE_LABEL):
        raise ValueError(f"label map holds ids outside 0..{IGNORE_LABEL} (min {labels.min()}, max {labels.max()})")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(labels.astype(np.uint16)))
    if not ok:
        raise ValueError("cv2.imencode failed on a label map")
    return buf.tobytes()


def decode_label_map(data: bytes, what: str = "label map") -> np.ndarray:
    """16-bit PNG bytes -> ``[H, W]`` int32."""
    import cv2

    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.ndim != 2 or arr.dtype != np.uint16:
        raise ShardError(f"{what}: not a single-channel 16-bit PNG")
    return arr.astype(np.int32)


def encode_rgb(rgb: np.ndarray) -> bytes:
    """``[H, W, 3]`` uint8 RGB -> PNG bytes."""
    import cv2

    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb has shape {rgb.shape} dtype {rgb.dtype}, expected (H, W, 3) uint8")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise ValueError("cv2.imencode failed on an RGB image")
    return buf.tobytes()


def decode_rgb(data: bytes, what: str = "rgb") -> np.ndarray:
    """PNG/JPEG bytes -> ``[H, W, 3]`` uint8 RGB."""
    import cv2

    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if arr is None:
        raise ShardError(f"{what}: image bytes do not decode")
    return np.ascontiguousarray(arr[:, :, ::-1])


def image_format(data: bytes) -> str:
    """``png`` or ``jpeg`` from the magic bytes; ShardError otherwise."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    raise ShardError("rgb bytes are neither PNG nor JPEG")
