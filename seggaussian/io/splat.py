"""antimatter15 ``.splat`` files: a headerless array of 32-byte little-endian records.

Record layout (byte offsets)::

    0  float32 x, y, z             position
    12 float32 sx, sy, sz          scales (linear, not logs)
    24 uint8   r, g, b, a          colour and opacity, value / 255
    28 uint8   q0, q1, q2, q3      rotation w, x, y, z; component = (byte - 127.5) / 127.5

Decoding (as @playcanvas/splat-transform): ``log_scales = log(s)``; ``f_dc = (c / 255 - 0.5) / SH_C0``;
``opacity_logit = logit(clamp(a / 255, eps, 1 - eps))`` with ``eps = UNIT_OPACITY_EPS``; the quaternion is
kept as decoded (not normalized; it is normalized on use). The format has no SH bands beyond DC and
no extra properties. Quantisation steps: colour and opacity 1/255, quaternion components 1/127.5
(before normalization); positions and scales are exact float32.

Writing: positions and ``exp(log_scales)`` as float32, ``round(255 * (0.5 + SH_C0 * f_dc))`` and
``round(255 * sigmoid(logit))`` clamped to [0, 255], the normalized quaternion as
``round(127.5 * q + 127.5)``. Higher SH bands and extras are not representable and are dropped.
Records keep the input order (viewers sort by depth themselves).

There is no magic number: a file is taken as ``.splat`` when no other format matches, its size is a
multiple of 32 and at least 3/4 of its first 64 records hold finite positions and non-negative finite
scales (:func:`looks_like_splat`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_atomic
from seggaussian.io.splat_common import (
    SplatFormatError,
    dc_from_rgb,
    logit_from_unit,
    read_file_bytes,
    rgb_from_dc,
    unit_from_logit,
    unorm_to_byte,
)

__all__ = ["SPLAT_RECORD", "RECORD_BYTES", "read_splat", "decode_splat", "encode_splat", "write_splat",
           "looks_like_splat"]

TITLE = "antimatter15 .splat"
#: One record, little endian.
SPLAT_RECORD = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)),
                         ("rot", "u1", (4,))])
RECORD_BYTES = 32
assert SPLAT_RECORD.itemsize == RECORD_BYTES
#: Records checked by ``looks_like_splat``.
SNIFF_RECORDS = 64
#: Share of those records that must hold finite positions and non-negative finite scales.
SNIFF_PLAUSIBLE_SHARE = 0.75
#: Half the byte range of a quaternion component: component = (byte - QUAT_HALF) / QUAT_HALF.
QUAT_HALF = np.float32(127.5)


def looks_like_splat(head: bytes, file_size: int) -> bool:
    """``head`` (the first bytes of a file of ``file_size`` bytes) plausibly starts a ``.splat`` file."""
    if file_size == 0 or file_size % RECORD_BYTES:
        return False
    count = min(len(head), SNIFF_RECORDS * RECORD_BYTES) // RECORD_BYTES
    if count == 0:
        return False
    records = np.frombuffer(head[: count * RECORD_BYTES], dtype=SPLAT_RECORD)
    with np.errstate(invalid="ignore"):
        plausible = (np.isfinite(records["position"]).all(axis=1) & np.isfinite(records["scale"]).all(axis=1)
                     & (records["scale"] >= 0).all(axis=1))
    # most, not all: a broken record is then reported by validation, naming the field
    return bool(plausible.mean() >= SNIFF_PLAUSIBLE_SHARE)


def decode_splat(data: bytes | np.ndarray, source: str | os.PathLike = "<bytes>") -> Gaussians:
    """The bytes of a ``.splat`` file -> ``Gaussians`` (raw decoded values, not validated)."""
    size = len(data)
    if size == 0:
        raise SplatFormatError(f"{source}: empty file (0 bytes), not an {TITLE} file")
    if size % RECORD_BYTES:
        raise SplatFormatError(
            f"{source}: {TITLE}: the size ({size} bytes) is not a multiple of the {RECORD_BYTES}-byte record "
            f"({size // RECORD_BYTES} whole records and {size % RECORD_BYTES} bytes left over: truncated?)"
        )
    records = np.frombuffer(data, dtype=SPLAT_RECORD)
    n = records.shape[0]
    means = np.ascontiguousarray(records["position"], dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):  # zero or negative scales -> -inf / NaN, reported later
        log_scales = np.log(records["scale"]).astype(np.float32)
    rgba = records["rgba"]
    sh = np.empty((n, 1, 3), np.float32)
    sh[:, 0, :] = dc_from_rgb(rgba[:, :3] * np.float32(1.0 / 255.0))
    opacity_logits = logit_from_unit(rgba[:, 3] * np.float32(1.0 / 255.0))
    quats = ((records["rot"].astype(np.float32) - QUAT_HALF) / QUAT_HALF).astype(np.float32)
    return Gaussians(means, quats, log_scales, opacity_logits, sh)


def read_splat(path: str | os.PathLike) -> Gaussians:
    """Read a ``.splat`` file -> ``Gaussians`` (not validated); ``SplatFormatError`` when malformed."""
    path = Path(path)
    return decode_splat(read_file_bytes(path, TITLE), path)


def encode_splat(gaussians: Gaussians) -> np.ndarray:
    """``Gaussians`` -> ``[N]`` records of ``SPLAT_RECORD``; non-finite input is refused."""
    g = gaussians
    for name in ("means", "log_scales", "quats", "opacity_logits"):
        if not np.isfinite(getattr(g, name)).all():
            raise ValueError(f"{TITLE}: Gaussians.{name} holds NaN/Inf; validate (or repair) before writing")
    if not np.isfinite(g.sh[:, 0]).all():
        raise ValueError(f"{TITLE}: Gaussians.sh (DC) holds NaN/Inf; validate (or repair) before writing")
    records = np.zeros(len(g), dtype=SPLAT_RECORD)
    records["position"] = g.means
    with np.errstate(over="ignore"):
        records["scale"] = np.exp(g.log_scales.astype(np.float64)).astype(np.float32)
    records["rgba"][:, :3] = unorm_to_byte(rgb_from_dc(g.sh[:, 0, :]))
    records["rgba"][:, 3] = unorm_to_byte(unit_from_logit(g.opacity_logits))
    unit = g.normalized_quats().astype(np.float64)
    records["rot"] = np.clip(np.round(unit * 127.5 + 127.5), 0, 255).astype(np.uint8)
    return records


def write_splat(path: str | os.PathLike, gaussians: Gaussians) -> None:
    """Write ``gaussians`` as a ``.splat`` file, atomically (DC colour only; extras dropped)."""
    write_atomic(path, [encode_splat(gaussians)])
