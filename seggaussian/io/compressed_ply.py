"""SuperSplat / PlayCanvas compressed PLY: 256-Gaussian chunks with per-chunk bounds, packed uint32 attributes.

Layout (binary little endian PLY, elements in this order)::

    element chunk  ceil(N / 256)   float min_x min_y min_z max_x max_y max_z
                                   float min_scale_x .. min_scale_z max_scale_x .. max_scale_z
                                   [float min_r min_g min_b max_r max_g max_b]   (optional, 18 vs 12 properties)
    element vertex N               uint packed_position packed_rotation packed_scale packed_color
    element sh     N               uchar f_rest_0 .. f_rest_{M-1}   (optional, M = 9, 24 or 45; channel-major)

Gaussian i belongs to chunk i // 256. Decoding (the rules of @playcanvas/splat-transform):

* position, 11/10/11 bits (x in bits 21..31, y in 11..20, z in 0..10): ``lerp(min, max, q / (2^b - 1))``.
* scale: the same packing of the *log* scales between ``min_scale_*`` and ``max_scale_*``.
* colour, 8/8/8/8 bits (r in 24..31, g, b, opacity in 0..7): r, g, b are ``lerp(min_r, max_r, q / 255)``
  with chunk colour bounds, ``q / 255`` without; ``f_dc = (c - 0.5) / SH_C0``; the opacity is
  ``q / 255``, stored as a logit clamped by ``UNIT_OPACITY_EPS`` (the reference returns +-inf for 0 and 255).
* rotation, 2 + 3 x 10 bits: bits 30..31 name the largest component of the unit quaternion
  (rot_0..rot_3 = w, x, y, z order), the other three in order are ``(q / 1023 - 0.5) * sqrt(2)`` (most
  significant first), and the largest is ``sqrt(1 - a^2 - b^2 - c^2)``.
* SH: byte ``v`` -> ``n = 0`` (v = 0), ``1`` (v = 255), else ``(v + 0.5) / 256``; coefficient ``(n - 0.5) * 8``.

Quantisation steps (what the tests allow): position ``(max - min) / 2047`` (x, z) and ``/ 1023`` (y) per
chunk; log scale likewise; colour ``(max - min) / 255`` in colour units; opacity 1/255; quaternion
components ``sqrt(2) / 1023``; SH ``8 / 256``.

Writing follows the same rules. The Gaussians are stored in Morton (Z-curve) order first, as the
reference writer does (:func:`morton_order`: 10 bits per axis over the bounds, ties kept in input order,
runs of more than 256 equal codes re-sorted over their own bounds), so each chunk is spatially compact and
its bounds tight; the scale bounds are clamped to [-20, 20] as the reference does, and chunk colour bounds
are always written. Extras are not representable and dropped.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from seggaussian.core.constants import SH_C0
from seggaussian.core.gaussians import Gaussians, sh_degree_from_coeffs
from seggaussian.io.ply.header import PlyElement, PlyHeader, read_ply_header
from seggaussian.io.ply.writer import write_atomic
from seggaussian.io.splat_common import SplatFormatError, dc_from_rgb, logit_from_unit, require_finite, unit_from_logit

__all__ = ["CHUNK_SIZE", "is_compressed_ply_header", "read_compressed_ply", "encode_compressed_ply",
           "write_compressed_ply", "morton_order"]

TITLE = "compressed PLY"
#: Gaussians per chunk.
CHUNK_SIZE = 256
CHUNK_BOUNDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
CHUNK_COLOURS = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
VERTEX_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
#: A chunk whose extent is below this is written with all values at its minimum (the reference's rule).
MIN_CHUNK_EXTENT = 1e-5
#: Log-scale bounds are clamped to +-this when written (the reference writer's rule: infinite scales occur).
LOG_SCALE_BOUND = 20.0
#: Quaternion component scale: the three small components lie in [-1/sqrt(2), 1/sqrt(2)].
ROT_NORM = np.float32(np.sqrt(2.0))
#: For each index of the largest component, the indices of the three others (stored in this order).
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.intp)


def _sh_table() -> np.ndarray:
    """``[256]`` float32 decoded value of each SH byte."""
    v = np.arange(256, dtype=np.float64)
    n = np.where(v == 0, 0.0, np.where(v == 255, 1.0, (v + 0.5) / 256.0))
    return ((n - 0.5) * 8.0).astype(np.float32)


SH_DECODE = _sh_table()


def is_compressed_ply_header(header: PlyHeader) -> bool:
    """The header declares a ``chunk`` element and a ``vertex`` element with ``packed_position``."""
    names = {e.name: e for e in header.elements}
    return "chunk" in names and "vertex" in names and any(
        p.name == "packed_position" for p in names["vertex"].properties)


def _check_layout(header: PlyHeader) -> tuple[bool, int]:
    """Validate the element layout -> (has chunk colours, SH rest count); error naming what is wrong."""
    path = header.path
    where = f"{path}: {TITLE}"
    if header.format != "binary_little_endian":
        raise SplatFormatError(f"{where}: format {header.format}, expected binary_little_endian")
    names = [e.name for e in header.elements]
    unknown = [n for n in names if n not in ("chunk", "vertex", "sh")]
    if unknown or len(set(names)) != len(names):
        raise SplatFormatError(f"{where}: elements {names}; expected chunk, vertex and optionally sh")
    chunk, vertex = header.element("chunk"), header.element("vertex")
    props = [p.name for p in chunk.properties]
    if props not in (list(CHUNK_BOUNDS), list(CHUNK_BOUNDS + CHUNK_COLOURS)):
        raise SplatFormatError(f"{where}: chunk properties {props}; expected the 12 bounds "
                               f"{list(CHUNK_BOUNDS)} optionally followed by {list(CHUNK_COLOURS)}")
    if any(p.dtype != "f4" or p.is_list for p in chunk.properties):
        raise SplatFormatError(f"{where}: chunk properties must be float")
    if [p.name for p in vertex.properties] != list(VERTEX_PACKED) or any(
            p.dtype != "u4" or p.is_list for p in vertex.properties):
        raise SplatFormatError(f"{where}: vertex properties must be uint {', '.join(VERTEX_PACKED)}, found "
                               f"{[(p.name, p.dtype) for p in vertex.properties]}")
    expected_chunks = -(-vertex.count // CHUNK_SIZE)
    if chunk.count != expected_chunks:
        raise SplatFormatError(f"{where}: {chunk.count} chunks for {vertex.count} vertices; expected "
                               f"ceil({vertex.count} / {CHUNK_SIZE}) = {expected_chunks}")
    num_rest = 0
    if "sh" in names:
        sh = header.element("sh")
        num_rest = len(sh.properties)
        if num_rest not in (9, 24, 45) or [p.name for p in sh.properties] != [f"f_rest_{i}" for i in range(num_rest)]:
            raise SplatFormatError(f"{where}: sh element with {num_rest} properties; expected f_rest_0.. with "
                                   "9, 24 or 45 of them")
        if any(p.dtype != "u1" or p.is_list for p in sh.properties):
            raise SplatFormatError(f"{where}: sh properties must be uchar")
        if sh.count != vertex.count:
            raise SplatFormatError(f"{where}: sh element has {sh.count} rows for {vertex.count} vertices")
    return len(props) == len(CHUNK_BOUNDS) + len(CHUNK_COLOURS), num_rest


def _element_dtype(element: PlyElement) -> np.dtype:
    """Little-endian record dtype of a (list-free, checked by ``_check_layout``) element."""
    return np.dtype([(p.name, "<" + p.dtype) for p in element.properties])


def _read_elements(header: PlyHeader) -> dict[str, np.ndarray]:
    """Every element as a structured array, after checking the body size."""
    dtypes = [(e, _element_dtype(e)) for e in header.elements]
    needed = sum(e.count * dt.itemsize for e, dt in dtypes)
    available = header.file_size - header.body_offset
    if available < needed:
        raise SplatFormatError(
            f"{header.path}: {TITLE}: truncated body: the header declares {needed} bytes "
            f"({', '.join(f'{e.count} {e.name}' for e, _ in dtypes)}) but only {available} bytes follow the header")
    out = {}
    with open(header.path, "rb") as f:
        f.seek(header.body_offset)
        for element, dtype in dtypes:
            out[element.name] = np.fromfile(f, dtype=dtype, count=element.count)
            if out[element.name].shape[0] != element.count:
                raise SplatFormatError(f"{header.path}: {TITLE}: truncated while reading '{element.name}'")
    return out


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    mask = np.uint32((1 << bits) - 1)
    return ((packed >> np.uint32(shift)) & mask).astype(np.float32) * np.float32(1.0 / ((1 << bits) - 1))


def _lerp_chunks(t: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``[N]`` per-Gaussian ``lo + (hi - lo) * t`` with ``lo, hi`` per chunk ``[C]``."""
    n = t.shape[0]
    lo_n = np.repeat(lo, CHUNK_SIZE)[:n]
    return lo_n + (np.repeat(hi, CHUNK_SIZE)[:n] - lo_n) * t


def decode_rotations(packed: np.ndarray) -> np.ndarray:
    """``[N]`` uint32 2+10+10+10 packed quaternions -> ``[N, 4]`` float32 (w, x, y, z)."""
    n = packed.shape[0]
    small = np.stack([(_unorm(packed, s, 10) - np.float32(0.5)) * ROT_NORM for s in (20, 10, 0)], axis=1)
    largest = (packed >> np.uint32(30)).astype(np.intp)
    m = np.sqrt(np.maximum(np.float32(0.0), np.float32(1.0) - np.einsum("ij,ij->i", small, small)))
    quats = np.empty((n, 4), np.float32)
    np.put_along_axis(quats, _OTHERS[largest], small, axis=1)
    quats[np.arange(n), largest] = m
    return quats


def read_compressed_ply(path: str | os.PathLike, header: PlyHeader | None = None) -> Gaussians:
    """Read a compressed PLY -> ``Gaussians`` (not validated); ``SplatFormatError`` when malformed."""
    header = header or read_ply_header(path)
    has_colours, num_rest = _check_layout(header)
    elements = _read_elements(header)
    chunk, vertex = elements["chunk"], elements["vertex"]
    with np.errstate(invalid="ignore", over="ignore"):   # NaN / Inf bounds give NaN values, reported by validation
        return _decode(chunk, vertex, elements.get("sh"), has_colours, num_rest)


def _decode(chunk: np.ndarray, vertex: np.ndarray, sh_rows: np.ndarray | None, has_colours: bool,
            num_rest: int) -> Gaussians:
    n = vertex.shape[0]
    bounds = {name: np.ascontiguousarray(chunk[name]) for name in chunk.dtype.names}
    pp, pr, ps, pc = (np.ascontiguousarray(vertex[name]) for name in VERTEX_PACKED)
    means = np.empty((n, 3), np.float32)
    log_scales = np.empty((n, 3), np.float32)
    sh = np.empty((n, 1 + num_rest // 3, 3), np.float32)
    for axis, (shift, bits) in enumerate(((21, 11), (11, 10), (0, 11))):
        c = "xyz"[axis]
        means[:, axis] = _lerp_chunks(_unorm(pp, shift, bits), bounds[f"min_{c}"], bounds[f"max_{c}"])
        log_scales[:, axis] = _lerp_chunks(_unorm(ps, shift, bits), bounds[f"min_scale_{c}"],
                                           bounds[f"max_scale_{c}"])
    for channel, name in enumerate("rgb"):
        t = _unorm(pc, 24 - 8 * channel, 8)
        colour = _lerp_chunks(t, bounds[f"min_{name}"], bounds[f"max_{name}"]) if has_colours else t
        sh[:, 0, channel] = dc_from_rgb(colour)
    opacity_logits = logit_from_unit(_unorm(pc, 0, 8))
    quats = decode_rotations(pr)
    if num_rest:
        raw = sh_rows.view(np.uint8).reshape(n, num_rest)
        k = num_rest // 3
        sh[:, 1:, :] = SH_DECODE[raw.reshape(n, 3, k).transpose(0, 2, 1)]   # channel-major bytes -> [N, num_sh_coeffs-1, 3]
    return Gaussians(means, quats, log_scales, opacity_logits, sh)


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------
def _pack_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _chunk_reduce(values: np.ndarray, fn) -> np.ndarray:
    """``[N]`` -> ``[C]`` per-chunk reduction (``np.minimum`` / ``np.maximum``)."""
    return fn.reduceat(values, np.arange(0, values.shape[0], CHUNK_SIZE)) if values.shape[0] else values[:0]


def _normalise(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    n = values.shape[0]
    lo_n, hi_n = np.repeat(lo, CHUNK_SIZE)[:n], np.repeat(hi, CHUNK_SIZE)[:n]
    extent = hi_n - lo_n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(extent < MIN_CHUNK_EXTENT, 0.0, (values - lo_n) / extent)
    return np.clip(t, 0.0, 1.0)


def encode_rotations(quats: np.ndarray) -> np.ndarray:
    """``[N, 4]`` quaternions (w, x, y, z; normalized here) -> ``[N]`` uint32 2+10+10+10."""
    n = quats.shape[0]
    norms = np.linalg.norm(quats.astype(np.float64), axis=1, keepdims=True)
    unit = np.where(norms > 0, quats / np.where(norms > 0, norms, 1.0), np.array([1.0, 0, 0, 0]))
    largest = np.argmax(np.abs(unit), axis=1)
    unit = unit * np.where(unit[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    small = np.take_along_axis(unit, _OTHERS[largest], axis=1)          # [N, 3]
    q = _pack_unorm(small / float(ROT_NORM) + 0.5, 10)
    return (largest.astype(np.uint32) << np.uint32(30)) | (q[:, 0] << np.uint32(20)) | (q[:, 1] << np.uint32(10)) | q[:, 2]


#: Bits per axis of a Morton code (three interleaved fit 30 bits).
MORTON_BITS = 10


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """``[N]`` uint32 10-bit values -> the bits moved to every third position (bit i -> bit 3i)."""
    v = v & np.uint32(0x3FF)
    v = (v ^ (v << np.uint32(16))) & np.uint32(0xFF0000FF)
    v = (v ^ (v << np.uint32(8))) & np.uint32(0x0300F00F)
    v = (v ^ (v << np.uint32(4))) & np.uint32(0x030C30C3)
    return (v ^ (v << np.uint32(2))) & np.uint32(0x09249249)


def morton_order(means: np.ndarray) -> np.ndarray:
    """``[N, 3]`` finite centres -> ``[N]`` indices in Morton order (the reference writer's order).

    Codes quantise each axis to ``MORTON_BITS`` bits between the bounds of the points being sorted
    (truncating, the top clamped); ties keep the input order; a run of more than ``CHUNK_SIZE`` equal
    codes is sorted again over its own bounds, until its points coincide.
    """
    points = means.astype(np.float64)
    order = np.arange(points.shape[0])
    pending = [(0, points.shape[0])]
    top = float(1 << MORTON_BITS)
    while pending:
        start, stop = pending.pop()
        if stop - start < 2:
            continue
        idx = order[start:stop]
        p = points[idx]
        lo, extent = p.min(axis=0), np.ptp(p, axis=0)
        if not (extent > 0).any():
            continue                                        # all points equal: nothing to order
        scale = np.divide(top, extent, out=np.zeros(3), where=extent > 0)
        q = np.minimum(top - 1, (p - lo) * scale).astype(np.uint32)
        codes = (_spread_bits(q[:, 2]) << np.uint32(2)) | (_spread_bits(q[:, 1]) << np.uint32(1)) \
            | _spread_bits(q[:, 0])
        perm = np.argsort(codes, kind="stable")
        order[start:stop] = idx[perm]
        codes = codes[perm]
        edges = np.concatenate([[0], np.flatnonzero(np.diff(codes)) + 1, [codes.shape[0]]])
        for a, b in zip(edges[:-1], edges[1:]):
            if b - a > CHUNK_SIZE:
                pending.append((start + int(a), start + int(b)))
    return order


def encode_compressed_ply(gaussians: Gaussians) -> tuple[bytes, list[np.ndarray]]:
    """``Gaussians`` -> (header bytes, body arrays) of a compressed PLY, in :func:`morton_order`;
    non-finite input is refused."""
    g = gaussians
    n = len(g)
    require_finite(g, TITLE)
    g = g.subset(morton_order(g.means))
    num_chunks = -(-n // CHUNK_SIZE)
    chunk = np.zeros(num_chunks, dtype=[(name, "<f4") for name in CHUNK_BOUNDS + CHUNK_COLOURS])
    packed = np.zeros(n, dtype=[(name, "<u4") for name in VERTEX_PACKED])
    position = np.zeros(n, np.uint32)
    scale = np.zeros(n, np.uint32)
    colour = np.zeros(n, np.uint32)
    rgb = g.sh[:, 0, :].astype(np.float64) * SH_C0 + 0.5
    for axis, (shift, bits) in enumerate(((21, 11), (11, 10), (0, 11))):
        c = "xyz"[axis]
        for values, lo_name, hi_name, out, clamp in (
                (g.means[:, axis], f"min_{c}", f"max_{c}", position, None),
                (g.log_scales[:, axis], f"min_scale_{c}", f"max_scale_{c}", scale, LOG_SCALE_BOUND)):
            values = values.astype(np.float64)
            lo, hi = _chunk_reduce(values, np.minimum), _chunk_reduce(values, np.maximum)
            if clamp is not None:
                lo, hi = np.clip(lo, -clamp, clamp), np.clip(hi, -clamp, clamp)
            lo, hi = lo.astype(np.float32), hi.astype(np.float32)   # decode uses the float32 bounds
            chunk[lo_name], chunk[hi_name] = lo, hi
            out |= _pack_unorm(_normalise(values, lo.astype(np.float64), hi.astype(np.float64)), bits) << np.uint32(shift)
    for channel, name in enumerate("rgb"):
        values = rgb[:, channel]
        lo = _chunk_reduce(values, np.minimum).astype(np.float32)
        hi = _chunk_reduce(values, np.maximum).astype(np.float32)
        chunk[f"min_{name}"], chunk[f"max_{name}"] = lo, hi
        t = _normalise(values, lo.astype(np.float64), hi.astype(np.float64))
        colour |= _pack_unorm(t, 8) << np.uint32(24 - 8 * channel)
    colour |= _pack_unorm(unit_from_logit(g.opacity_logits), 8)
    packed["packed_position"], packed["packed_scale"], packed["packed_color"] = position, scale, colour
    packed["packed_rotation"] = encode_rotations(g.quats)
    k = g.num_sh_coeffs
    lines = ["ply", "format binary_little_endian 1.0", "comment written by seggaussian",
             f"element chunk {num_chunks}"] + [f"property float {p}" for p in CHUNK_BOUNDS + CHUNK_COLOURS]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in VERTEX_PACKED]
    body = [chunk, packed]
    if k > 1:
        rest = g.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)).astype(np.float64)   # channel-major
        body.append(np.ascontiguousarray(np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)))
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii"), body


def write_compressed_ply(path: str | os.PathLike, gaussians: Gaussians) -> None:
    """Write ``gaussians`` as a compressed PLY, atomically (extras dropped)."""
    sh_degree_from_coeffs(gaussians.num_sh_coeffs)
    header, body = encode_compressed_ply(gaussians)
    write_atomic(Path(path), [header, *body])
