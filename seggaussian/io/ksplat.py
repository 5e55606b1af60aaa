"""mkkellogg ``.ksplat`` files (GaussianSplats3D's ``SplatBuffer``), format version 0.1, compression levels 0-2.

Layout (little endian)::

    main header, 4096 bytes:
        u8 version_major (0), u8 version_minor (>= 1), 2 unused bytes,
        u32 max_sections @4, u32 sections @8, u32 max_splats @12, u32 splats @16,
        u16 compression_level @20 (0, 1, 2), f32 scene_center[3] @24,
        f32 sh_min @36, f32 sh_max @40 (level 2 SH range; 0 means the default -1.5 / 1.5)
    max_sections section headers, 1024 bytes each:
        u32 splats @0, u32 max_splats @4, u32 bucket_capacity @8, u32 buckets @12,
        f32 block_size @16, u16 bucket_storage_bytes @20 (12), u32 quantisation_range @24 (0 = the level's
        default: 1 for level 0, 32767 for levels 1-2), u32 storage_bytes @28, u32 full_buckets @32,
        u32 partial_buckets @36, u16 sh_degree @40
    then per section: u32 partial_bucket_sizes[partial_buckets], buckets x bucket_storage_bytes (f32 centre x, y,
        z each), then max_splats records (``splats`` used, the rest padding)

Records (``sh`` = 0, 9, 24 or 45 values for SH degree 0-3):

=========  ===========================  ===============================================
level      centre / scale / rotation    SH
=========  ===========================  ===============================================
0          f32 x3 / f32 x3 / f32 x4     f32
1          u16 x3 / f16 x3 / f16 x4     f16
2          u16 x3 / f16 x3 / f16 x4     u8: ``sh_min + b / 255 * (sh_max - sh_min)``
=========  ===========================  ===============================================

and after the rotation ``u8 r, g, b, a`` in every level. Decoding follows @playcanvas/splat-transform's reader:

* centre (levels 1-2): ``(u - range) * block_size / 2 / range + centre of the splat's bucket``; splat ``i``
  of a section lies in bucket ``i // bucket_capacity`` while ``i < full_buckets * bucket_capacity``, after
  that in the partial buckets, which follow the full ones and hold ``partial_bucket_sizes`` splats each;
* scale: linear, ``log_scales = log(s)``; a zero scale (a float16 underflow) decodes to ``log(s) =
  ZERO_SCALE_LOG`` (-10, as the reference); a negative or NaN scale is left NaN for validation to report;
* rotation ``w, x, y, z`` as stored (not normalized); colour ``f_dc = (c / 255 - 0.5) / SH_C0``; opacity
  ``logit(clamp(a / 255, eps, 1 - eps))``, ``eps = UNIT_OPACITY_EPS``;
* SH: stored band after band, channel-major inside a band: band 1 as R0 R1 R2 G0 G1 G2 B0 B1 B2, band 2 as
  five coefficients per channel, band 3 as seven.

Quantisation steps: level 0 is float32 except colour and opacity (1/255); levels 1-2 store positions to
``block_size / 2 / range`` (5 m blocks and range 32767 as written here: 7.6e-5 m), scales, rotations and
(level 1) SH as float16 (relative step 2^-11; scales below 2^-24 underflow), level-2 SH to
``(sh_max - sh_min) / 255``.

Writing (:func:`encode_ksplat`): one section; level 0 keeps the input order and has no buckets; levels 1-2
group splats into 5 m cells, cut each cell into buckets of 256 (full buckets first, then one partial bucket
per cell, as GaussianSplats3D does) and store them in that order (:func:`bucket_layout`). Quaternions are
normalized; scales are clamped to float16's range at levels 1-2; level-2 SH use the symmetric range
``+-max|sh|``. GaussianSplats3D reads SH up to degree 2, so band 3 is dropped unless ``max_sh_degree=3``
(which the reference converter reads). Extras (labels) are not representable and are dropped.

There is no magic number: :func:`looks_like_ksplat` checks the header (version 0.1+, two zero bytes,
compression level, section table inside the file); the counts are checked by the decoder.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import NamedTuple

import numpy as np

from seggaussian.util.atomic import write_bytes_atomic
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.splat_common import (
    SplatFormatError,
    dc_from_rgb,
    logit_from_unit,
    read_file_bytes,
    require_finite,
    rgb_from_dc,
    unit_from_logit,
    unorm_to_byte,
)

__all__ = ["KSPLAT_LEVELS", "KSPLAT_MAX_SH_DEGREE", "BucketLayout", "bucket_layout", "decode_ksplat",
           "read_ksplat", "encode_ksplat", "write_ksplat", "looks_like_ksplat"]

TITLE = "mkkellogg .ksplat"
MAIN_HEADER_BYTES = 4096
SECTION_HEADER_BYTES = 1024
MAIN_HEADER = struct.Struct("<BBxxIIIIH2x3fff")                  # the first 44 bytes
SECTION_HEADER = struct.Struct("<IIIIfH2xIIIIH")                  # the first 42 bytes
#: Compression levels read and written.
KSPLAT_LEVELS = (0, 1, 2)
#: Degree written by default: GaussianSplats3D stores SH up to degree 2.
KSPLAT_MAX_SH_DEGREE = 2
#: Stored SH values per degree (all bands above DC, three channels).
SH_VALUES = (0, 9, 24, 45)
#: Position quantisation range of levels 1-2 when the section header holds 0; level 0's is 1 (unused).
DEFAULT_RANGE = {0: 1, 1: 32767, 2: 32767}
#: Level-2 SH range when the main header holds 0 (the reference reads ``value || default``).
DEFAULT_SH_MIN, DEFAULT_SH_MAX = -1.5, 1.5
#: Log scale of a stored zero scale (float16 underflow), as @playcanvas/splat-transform decodes it.
ZERO_SCALE_LOG = -10.0
#: Bucket geometry written (GaussianSplats3D's defaults): cube edge in metres, splats per bucket.
BLOCK_SIZE = 5.0
BUCKET_CAPACITY = 256
#: Bytes per bucket: its centre, three float32.
BUCKET_STORAGE_BYTES = 12
#: Largest finite float16; scales are clamped to [F16_MIN_SUBNORMAL, F16_MAX] at levels 1-2.
F16_MAX = 65504.0
F16_MIN_SUBNORMAL = 2.0 ** -24
#: Largest section count taken from a header (guards the section-table arithmetic; GaussianSplats3D
#: writes one section per scene).
MAX_SECTIONS = 1 << 16


def _record_dtype(level: int, sh_values: int) -> np.dtype:
    pos, flt, sh = ("<f4", "<f4", "<f4") if level == 0 else ("<u2", "<f2", "<f2" if level == 1 else "u1")
    return np.dtype([("center", pos, (3,)), ("scale", flt, (3,)), ("rot", flt, (4,)), ("rgba", "u1", (4,)),
                     ("sh", sh, (sh_values,))])


def _sh_slots(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """For each stored SH value of ``degree``: its coefficient index in ``sh[:, 1:]`` and its channel."""
    coeffs, channels = [], []
    for band in range(1, degree + 1):
        first, width = band * band - 1, 2 * band + 1          # coefficients 0-2, 3-7, 8-14 of sh[:, 1:]
        for channel in range(3):
            coeffs.extend(range(first, first + width))
            channels.extend([channel] * width)
    return np.array(coeffs, np.intp), np.array(channels, np.intp)


def looks_like_ksplat(head: bytes, file_size: int) -> bool:
    """``head`` (at least the first 44 bytes of a file of ``file_size`` bytes) is a plausible ksplat header."""
    if len(head) < MAIN_HEADER.size or file_size < MAIN_HEADER_BYTES:
        return False
    major, minor, max_sections, _, _, _, level, *_ = MAIN_HEADER.unpack_from(head)
    # splat counts are left to the decoder, whose error then says what is wrong with this ksplat file
    return (major == 0 and 1 <= minor < 64 and head[2:4] == b"\0\0" and level in KSPLAT_LEVELS
            and 1 <= max_sections <= MAX_SECTIONS
            and MAIN_HEADER_BYTES + max_sections * SECTION_HEADER_BYTES <= file_size)


def decode_ksplat(data: bytes, source: str | os.PathLike = "<bytes>") -> Gaussians:
    """The bytes of a ``.ksplat`` file -> ``Gaussians`` (raw decoded values, not validated)."""
    where = f"{source}: {TITLE}"
    size = len(data)
    if size < MAIN_HEADER_BYTES:
        raise SplatFormatError(f"{where}: {size} bytes, shorter than the {MAIN_HEADER_BYTES}-byte header")
    major, minor, max_sections, _, _, total, level, *_, sh_min, sh_max = MAIN_HEADER.unpack_from(data)
    if major != 0 or minor < 1:
        raise SplatFormatError(f"{where}: version {major}.{minor} is not supported (0.1 and later 0.x)")
    if level not in KSPLAT_LEVELS:
        raise SplatFormatError(f"{where}: compression level {level} is not valid (0, 1 or 2)")
    if not 1 <= max_sections <= MAX_SECTIONS:
        raise SplatFormatError(f"{where}: {max_sections} sections declared (1..{MAX_SECTIONS} supported)")
    offset = MAIN_HEADER_BYTES + max_sections * SECTION_HEADER_BYTES
    if offset > size:
        raise SplatFormatError(f"{where}: truncated: {max_sections} section headers need {offset} bytes, "
                               f"the file has {size}")
    sh_min = sh_min if sh_min and np.isfinite(sh_min) else DEFAULT_SH_MIN
    sh_max = sh_max if sh_max and np.isfinite(sh_max) else DEFAULT_SH_MAX
    headers = [SECTION_HEADER.unpack_from(data, MAIN_HEADER_BYTES + s * SECTION_HEADER_BYTES)
               for s in range(max_sections)]
    for s, h in enumerate(headers):
        if h[-1] > 3:
            raise SplatFormatError(f"{where}: section {s}: SH degree {h[-1]} is not valid (0..3)")
    degree = max((h[-1] for h in headers if h[0] > 0), default=0)
    declared = sum(h[0] for h in headers)
    if declared != total:
        raise SplatFormatError(f"{where}: the sections hold {declared} splats, the header declares {total}")
    if total > size:     # every splat takes more than one byte: a cheap bound before allocating
        raise SplatFormatError(f"{where}: the header declares {total} splats, impossible for a {size}-byte file")
    means = np.empty((total, 3), np.float32)
    quats = np.empty((total, 4), np.float32)
    log_scales = np.empty((total, 3), np.float32)
    opacity_logits = np.empty(total, np.float32)
    sh = np.zeros((total, (degree + 1) ** 2, 3), np.float32)
    done = 0
    for s, (count, capacity_splats, bucket_capacity, buckets, block_size, bucket_bytes, q_range, _storage,
            full, partial, section_degree) in enumerate(headers):
        at = f"{where}: section {s}"
        if count > capacity_splats:
            raise SplatFormatError(f"{at}: {count} splats in room for {capacity_splats}")
        dtype = _record_dtype(level, SH_VALUES[section_degree])
        bucket_area = bucket_bytes * buckets + 4 * partial
        end = offset + bucket_area + dtype.itemsize * capacity_splats
        if end > size:
            raise SplatFormatError(f"{at}: truncated: its buckets and {capacity_splats} records end at byte {end}, "
                                   f"the file has {size} bytes")
        records = np.frombuffer(data, dtype, count=count, offset=offset + bucket_area)
        rows = slice(done, done + count)
        if level == 0:
            means[rows] = records["center"]
        else:
            if bucket_bytes != BUCKET_STORAGE_BYTES and buckets:
                raise SplatFormatError(f"{at}: {bucket_bytes} bytes per bucket, expected {BUCKET_STORAGE_BYTES}")
            sizes = np.frombuffer(data, "<u4", count=partial, offset=offset).astype(np.int64)
            in_full = min(count, full * bucket_capacity)
            ends = np.cumsum(sizes)                              # end (exclusive) of each partial bucket
            if (full and bucket_capacity == 0) or in_full + int(ends[-1] if partial else 0) < count \
                    or full + partial > buckets:
                raise SplatFormatError(f"{at}: the buckets ({full} full of {bucket_capacity}, {partial} partial, "
                                       f"{buckets} in all) do not cover its {count} splats")
            bucket_of = np.concatenate([np.arange(in_full, dtype=np.int64) // max(bucket_capacity, 1),
                                        full + np.searchsorted(ends, np.arange(count - in_full), side="right")])
            centres = np.frombuffer(data, "<f4", count=3 * buckets, offset=offset + 4 * partial).reshape(buckets, 3)
            q_range = q_range or DEFAULT_RANGE[level]
            step = np.float64(block_size) / 2.0 / q_range
            means[rows] = ((records["center"].astype(np.float64) - q_range) * step
                           + centres[bucket_of].astype(np.float64))
        scales = records["scale"].astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):     # negative / NaN -> NaN, reported by validation
            log_scales[rows] = np.where(scales == 0, np.float32(ZERO_SCALE_LOG), np.log(scales))
        quats[rows] = records["rot"]
        rgba = records["rgba"]
        sh[rows, 0, :] = dc_from_rgb(rgba[:, :3] * np.float32(1.0 / 255.0))
        opacity_logits[rows] = logit_from_unit(rgba[:, 3] * np.float32(1.0 / 255.0))
        stored = records["sh"]
        if level == 2:       # the 256 byte values, computed as the reference does (float64, then float32)
            stored = (sh_min + np.arange(256) / 255.0 * (sh_max - sh_min)).astype(np.float32)[stored]
        at_value = 0
        for band in range(1, section_degree + 1):    # channel-major inside a band -> [N, coefficient, channel]
            first, width = band * band - 1, 2 * band + 1
            block = stored[:, at_value: at_value + 3 * width].reshape(count, 3, width)
            sh[rows, 1 + first: 1 + first + width, :] = block.transpose(0, 2, 1)
            at_value += 3 * width
        done += count
        offset = end
    if offset != size:
        raise SplatFormatError(f"{where}: {size - offset} bytes after the last section")
    return Gaussians(means, quats, log_scales, opacity_logits, sh)


def read_ksplat(path: str | os.PathLike) -> Gaussians:
    """Read a ``.ksplat`` file -> ``Gaussians`` (not validated); ``SplatFormatError`` when malformed."""
    path = Path(path)
    return decode_ksplat(read_file_bytes(path, TITLE), path)


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------
class BucketLayout(NamedTuple):
    """Where each splat goes in a levels 1-2 section.

    Fields:
        order: ``[N]`` input index of each stored splat (full buckets first, then the partial ones).
        centres: ``[B, 3]`` float32 bucket centres, full buckets first.
        full: number of full buckets (``BUCKET_CAPACITY`` splats each).
        partial_sizes: ``[B - full]`` uint32 splat counts of the partial buckets.
    """

    order: np.ndarray
    centres: np.ndarray
    full: int
    partial_sizes: np.ndarray


def bucket_layout(means: np.ndarray, block_size: float = BLOCK_SIZE,
                  capacity: int = BUCKET_CAPACITY) -> BucketLayout:
    """``[N, 3]`` centres -> the bucket of every splat: cubes of ``block_size``, cut into ``capacity`` splats."""
    n = means.shape[0]
    cells = np.floor(means.astype(np.float64) / block_size).astype(np.int64)     # [N, 3]
    if n == 0:
        return BucketLayout(np.zeros(0, np.int64), np.zeros((0, 3), np.float32), 0, np.zeros(0, np.uint32))
    low = cells.min(axis=0)
    span = cells.max(axis=0) - low + 1
    key = ((cells[:, 0] - low[0]) * span[1] + (cells[:, 1] - low[1])) * span[2] + (cells[:, 2] - low[2])
    unique_keys, first, counts = np.unique(key, return_index=True, return_counts=True)
    cell_of_key = cells[first]                                   # [C, 3]
    inverse = np.searchsorted(unique_keys, key)
    by_cell = np.argsort(inverse, kind="stable")                 # splats grouped by cell, input order inside
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(n) - np.repeat(starts, counts)             # place of each grouped splat inside its cell
    in_full = rank < np.repeat(counts // capacity * capacity, counts)
    order = np.concatenate([by_cell[in_full], by_cell[~in_full]])
    full_cells = np.repeat(cell_of_key, counts // capacity, axis=0)
    remainder = counts % capacity
    partial_cells = cell_of_key[remainder > 0]
    centres = ((np.concatenate([full_cells, partial_cells]) + 0.5) * block_size).astype(np.float32)
    return BucketLayout(order, centres, int(full_cells.shape[0]), remainder[remainder > 0].astype(np.uint32))


def encode_ksplat(gaussians: Gaussians, compression_level: int = 1,
                  max_sh_degree: int = KSPLAT_MAX_SH_DEGREE) -> bytes:
    """``Gaussians`` -> the bytes of a one-section ``.ksplat`` file at ``compression_level`` (0, 1, 2).

    Levels 1-2 store the splats in :func:`bucket_layout` order; level 0 keeps the input order.
    """
    if compression_level not in KSPLAT_LEVELS:
        raise ValueError(f"ksplat compression level {compression_level} is not valid (choose one of {KSPLAT_LEVELS})")
    g = gaussians
    require_finite(g, TITLE)
    n = len(g)
    degree = min(g.sh_degree, max_sh_degree, 3)
    level = compression_level
    if level == 0:
        order = np.arange(n)
        layout = BucketLayout(order, np.zeros((0, 3), np.float32), 0, np.zeros(0, np.uint32))
        block_size, q_range, capacity = 0.0, 0, 0
    else:
        layout = bucket_layout(g.means)
        order = layout.order
        block_size, q_range, capacity = BLOCK_SIZE, DEFAULT_RANGE[level], BUCKET_CAPACITY
    dtype = _record_dtype(level, SH_VALUES[degree])
    records = np.zeros(n, dtype)
    means = g.means[order].astype(np.float64)
    scales = np.exp(g.log_scales[order].astype(np.float64))
    if level == 0:
        records["center"] = means
        records["scale"] = scales
    else:
        bucket_of = np.repeat(np.arange(len(layout.centres)),
                              np.concatenate([np.full(layout.full, BUCKET_CAPACITY), layout.partial_sizes]))
        offsets = (means - layout.centres[bucket_of]) / (block_size / 2.0) * q_range
        records["center"] = np.clip(np.round(offsets + q_range), 0, 65535).astype(np.uint16)
        records["scale"] = np.clip(scales, F16_MIN_SUBNORMAL, F16_MAX)
    records["rot"] = g.normalized_quats()[order]
    records["rgba"][:, :3] = unorm_to_byte(rgb_from_dc(g.sh[order, 0, :]))
    records["rgba"][:, 3] = unorm_to_byte(unit_from_logit(g.opacity_logits[order]))
    sh_min, sh_max = 0.0, 0.0
    if degree:
        coeffs, channels = _sh_slots(degree)
        stored = g.sh[order, 1:, :][:, coeffs, channels].astype(np.float64)        # [N, SH_VALUES[degree]]
        if level == 2:
            bound = float(np.abs(stored).max(initial=0.0))
            sh_max = np.float32(bound) if bound > 0 else np.float32(DEFAULT_SH_MAX)
            sh_min = -sh_max
            stored = np.clip(np.round((stored - sh_min) / (sh_max - sh_min) * 255.0), 0, 255)
        records["sh"] = stored
    centre = (g.means.min(axis=0) + g.means.max(axis=0)) / 2 if n else np.zeros(3)
    main = bytearray(MAIN_HEADER_BYTES)
    MAIN_HEADER.pack_into(main, 0, 0, 1, 1, 1, n, n, level, *(float(c) for c in centre), sh_min, sh_max)
    buckets = len(layout.centres)
    bucket_area = 4 * len(layout.partial_sizes) + BUCKET_STORAGE_BYTES * buckets
    section = bytearray(SECTION_HEADER_BYTES)
    SECTION_HEADER.pack_into(section, 0, n, n, capacity, buckets, block_size,
                             BUCKET_STORAGE_BYTES if level else 0, q_range, bucket_area + records.nbytes,
                             layout.full, len(layout.partial_sizes), degree)
    return b"".join([bytes(main), bytes(section), layout.partial_sizes.astype("<u4").tobytes(),
                     layout.centres.astype("<f4").tobytes(), records.tobytes()])


def write_ksplat(path: str | os.PathLike, gaussians: Gaussians, compression_level: int = 1,
                 max_sh_degree: int = KSPLAT_MAX_SH_DEGREE) -> None:
    """Write ``gaussians`` as a ``.ksplat`` file, atomically (extras dropped; see :func:`encode_ksplat`)."""
    write_bytes_atomic(path, encode_ksplat(gaussians, compression_level, max_sh_degree))
