"""Niantic SPZ files, versions 1 to 4 (the versions Niantic's reference library reads).

Versions 1-3: a 16-byte header and the attribute blocks one after the other, normally inside one gzip
stream (an unwrapped stream is read too). Version 4: a 32-byte plain header, optional extensions, a
table of contents (per stream: uint64 compressed size, uint64 uncompressed size) and one zstd stream
per attribute. Header (little endian)::

    uint32 magic 0x5053474e ("NGSP"), uint32 version, uint32 N, uint8 sh_degree, uint8 fractional_bits,
    uint8 flags (1 = antialiased, 2 = extensions), uint8 reserved (v4: number of streams),
    v4 only: uint32 toc_offset, 12 reserved bytes

Attributes, in this order (each a block of N records):

* positions: v1 float16 x3; v2+ signed 24-bit fixed point x3, value ``q / 2^fractional_bits``.
* alphas: uint8, opacity ``a / 255`` (logit clamped by ``UNIT_OPACITY_EPS``, as splat-transform).
* colours: uint8 x3, ``f_dc = (c / 255 - 0.5) / 0.15`` (SPZ's colour scale, not SH_C0).
* scales: uint8 x3, ``log_scale = s / 16 - 10``.
* rotations: v1-2 uint8 x3 = x, y, z as ``b / 127.5 - 1`` with ``w = sqrt(1 - x^2 - y^2 - z^2)``;
  v3+ uint32 "smallest three": bits 30..31 the index of the largest component in (x, y, z, w) order,
  then three 10-bit fields (the last remaining component in the lowest bits), each a 9-bit magnitude
  ``m / 511 / sqrt(2)`` and a sign bit (bit 9); the largest is ``sqrt(1 - sum of squares)``.
* SH: uint8 ``(b - 128) / 128``, per Gaussian coefficient-major with the channel innermost.
* extensions (flag 2): records ``uint32 type, uint32 byte length, payload``; v4 between the header and the table
  of contents, v1-3 after the SH block (where Niantic's writer puts them; its reader, 0.2.3, fails to read them
  there and drops them). The one read is SPZ_ADOBE_coordinate_system (``0xADBE0003``, a uint32 frame code of
  Niantic's ``CoordinateSystem``); others are skipped, as Niantic's library skips unknown ones.

Frame. SPZ stores RUB (x right, y up, z back: OpenGL/three.js; Niantic's README, "Coordinate System"), the
toolkit's ``Gaussians`` and 3DGS PLY RDF (x right, y down, z forward: OpenCV/COLMAP). The two differ by
``P = diag(1, -1, -1)``, a 180-degree turn about x and its own inverse, so reading (RUB -> RDF) and writing
(RDF -> RUB) apply the same signs, those of Niantic's ``coordinateConverter`` (src/cc/splat-types.h):
positions ``(x, -y, -z)``; rotations ``R -> P R P``, the quaternion ``(w, x, y, z) -> (w, x, -y, -z)``; scales,
opacity and the DC colour unchanged; each SH coefficient times the parity of its basis polynomial under
``(y, z) -> (-y, -z)`` (``_SH_PARITY``): band 1 ``(-, -, +)``, band 2 ``(-, +, +, -, +)``, band 3
``(-, +, -, -, +, -, +)``, Niantic's ``flipSh``. A file whose coordinate-system extension names another frame of
Niantic's standard family (three axis letters, ``seggaussian.frames.axes``) is read from that frame; the rotated
family (y and z exchanged) is refused. Files are written in RUB without extensions. @playcanvas/splat-transform
reads and writes SPZ without any conversion: its decode of a file is ours with y and z negated (``P``).

SH degree 4 (72 coefficients) is refused: the toolkit stops at degree 3.

Quantisation steps: positions ``2^-fractional_bits`` (1/4096 m as written here), colour ``1 / (255 *
0.15)`` in ``f_dc`` units, log scale 1/16, opacity 1/255, SH 1/128, quaternion components ``1 / (511 *
sqrt(2))`` (v3+) or 1/127.5 (v2).

Reading: gzip is inflated in one call by libdeflate (the ``deflate`` package: about 1.6x zlib's speed and
1.25x ISA-L's on SPZ payloads), zlib naming the problem when a stream is refused. Positions, rotations and
SH go through one-pass compiled loops (``seggaussian.io.spz_kernels``, the frame's signs applied in the same
pass), bit-identical to the numpy references kept here (``decode_*_reference``); the rest is numpy on whole
blocks.

Writing: versions 2 and 3 (gzip; 3 by default, what web viewers read) and 4 (zstd), 12 fractional bits; extras are dropped. zstd comes from
the ``zstandard`` package.
"""

from __future__ import annotations

import gzip
import os
import struct
import zlib
from pathlib import Path

import deflate
import numpy as np

from seggaussian.util.atomic import write_bytes_atomic
from seggaussian.frames.axes import axes_to_rdf
from seggaussian.core.gaussians import Gaussians
from seggaussian.io import spz_kernels
from seggaussian.io.splat_common import (SplatFormatError, logit_from_unit, read_file_bytes, require_finite,
                                         unit_from_logit)

__all__ = ["SPZ_MAGIC", "SPZ_VERSIONS", "SPZ_FRAME", "read_spz", "decode_spz", "encode_spz", "write_spz",
           "spz_payload_head", "frame_signs"]

TITLE = "Niantic SPZ"
SPZ_MAGIC = 0x5053474E
SPZ_MAGIC_BYTES = b"NGSP"
GZIP_MAGIC = b"\x1f\x8b"
#: Versions read; versions written are 2, 3 and 4.
SPZ_VERSIONS = (1, 2, 3, 4)
WRITE_VERSIONS = (2, 3, 4)
#: Version written when none is asked for: 3, the newest that the web viewers read (Spark 2.2.0 reads 2 and 3,
#: GaussianSplats3D 0.4.7 only 2; neither reads 4's zstd streams: tests/seggaussian/io/test_web_viewer.py), and
#: Niantic's library reads it too. ``--spz-version 4`` / ``version=4`` writes the zstd layout.
DEFAULT_WRITE_VERSION = 3
LEGACY_HEADER = struct.Struct("<IIIBBBB")              # 16 bytes
V4_HEADER = struct.Struct("<IIIBBBBI12s")              # 32 bytes
TOC_ENTRY = struct.Struct("<QQ")
#: The 8-byte trailer of a gzip member: CRC-32 and length (mod 2^32) of the payload.
GZIP_TRAILER = struct.Struct("<II")
#: ``wbits`` of a gzip-wrapped deflate stream (zlib's convention).
GZIP_WBITS = 16 + 15
#: SPZ quantises the DC colour with this scale instead of SH_C0.
SPZ_COLOR_SCALE = 0.15
#: Fixed-point fraction bits we write (1/4096 m, the reference library's choice).
WRITE_FRACTIONAL_BITS = 12
#: Largest SH degree accepted (the toolkit's MAX_SH_DEGREE); SPZ itself allows 4.
MAX_SPZ_SH_DEGREE = 3
#: Cap on the decompressed size relative to the file (protects against a header claiming billions of points).
MAX_EXPANSION = 1024
#: Deflate's largest compression ratio (a run of one byte): a gzip file of L bytes inflates to < 1032 L.
GZIP_MAX_RATIO = 1032
#: Compressed bytes inflated to read the payload's header (a deflate block header is far smaller).
HEAD_INPUT_BYTES = 1 << 16
_SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15, 4: 24}
#: zstd compression level of the written v4 streams.
ZSTD_LEVEL = 3
#: The frame SPZ stores without a coordinate-system extension, as axis letters (``Gaussians`` hold RDF).
SPZ_FRAME = "RUB"
#: Header flag: extension records follow (v4: between the header and the table of contents; v1-3: after the SH).
FLAG_EXTENSIONS = 2
EXTENSION_RECORD = struct.Struct("<II")               # type, payload byte length
#: SPZ_ADOBE_coordinate_system: a uint32 payload, a code of Niantic's CoordinateSystem (below) naming the stored frame.
COORDINATE_SYSTEM_EXTENSION = 0xADBE0003
#: Niantic's CoordinateSystem codes (src/cc/splat-types.h). 0 (UNSPECIFIED) is read as RUB, as Niantic's loader
#: does; 1-8 are the standard family (the letters name the x, y, z directions); 9-16 the rotated family.
COORDINATE_SYSTEMS = {0: "RUB", 1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF",
                      9: "LFD", 10: "RFD", 11: "LFU", 12: "RFU", 13: "LBD", 14: "RBD", 15: "LBU", 16: "RBU"}
ROTATED_FAMILY = range(9, 17)
#: Per SH coefficient of bands 1-3 (3DGS order, after the DC), the parity (exponent mod 2) of x, y and z in its
#: basis polynomial: band 1 ``-C1 y, C1 z, -C1 x``; band 2 ``xy, yz, 2z^2 - x^2 - y^2, xz, x^2 - y^2``; band 3
#: ``y(3x^2 - y^2), xyz, y(4z^2 - x^2 - y^2), z(2z^2 - 3x^2 - 3y^2), x(4z^2 - x^2 - y^2), z(x^2 - y^2),
#: x(x^2 - 3y^2)``. Under the axis flips ``f`` the coefficient is multiplied by ``prod(f ** parity)``.
_SH_PARITY = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0],
                       [1, 1, 0], [0, 1, 1], [0, 0, 0], [1, 0, 1], [0, 0, 0],
                       [0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 0, 1], [1, 0, 0]], dtype=np.int64)


def frame_signs(frame: str = SPZ_FRAME) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The signs that take Gaussians stored in the standard-family ``frame`` (three axis letters, e.g. ``RUB``) to
    RDF, and back (each frame change here is a set of axis flips ``F = diag(f)``, its own inverse).

    Returns float32 ``[3]`` position signs ``f``; ``[4]`` quaternion signs (w, x, y, z) ``(1, d f)`` with
    ``d = det F`` (``R -> F R F``: a rotation about ``v`` becomes one about ``d F v``); ``[15]`` SH signs of bands
    1-3, ``prod(f ** parity)`` per basis polynomial (``_SH_PARITY``). For ``RUB``: ``(1, -1, -1)``,
    ``(1, 1, -1, -1)`` and Niantic's ``flipSh`` of RUB -> RDF."""
    f = np.diag(axes_to_rdf(frame))
    if not np.all(np.abs(f) == 1.0):
        raise ValueError(f"{TITLE}: frame {frame!r} is not an axis flip of RDF (y and z exchanged); not supported")
    det = float(np.prod(f))
    sh = np.prod(np.where(_SH_PARITY == 1, f[None, :], 1.0), axis=1)
    return f.astype(np.float32), np.concatenate([[1.0], det * f]).astype(np.float32), sh.astype(np.float32)


def _gunzip(data: bytes, source) -> bytes:
    """One gzip member (what SPZ writers produce) -> its payload, CRC and length checked.

    libdeflate inflates it in one call. It sizes its output by the trailer's length field and ignores bytes
    after the member, so that field is bounded before the call (deflate expands at most ``GZIP_MAX_RATIO``
    times) and the trailer is compared with the payload after it: a trailer that is not the last 8 bytes of
    the file means bytes after the stream. Whatever libdeflate refuses, or any mismatch, goes through zlib,
    whose error names the problem (broken stream, truncated stream, bytes after it). The one tail this cannot
    see is one ending in the member's own trailer (the member written twice): it is read as one member, as
    Niantic's library reads every tail.
    """
    if len(data) > GZIP_TRAILER.size:
        crc, length = GZIP_TRAILER.unpack_from(data, len(data) - GZIP_TRAILER.size)
        if length <= GZIP_MAX_RATIO * len(data):
            try:
                payload = deflate.gzip_decompress(data)
            except (deflate.DeflateError, MemoryError):      # a broken stream, or a length no buffer fits
                payload = None
            if payload is not None and len(payload) == length and deflate.crc32(payload) == crc:
                return payload
    return _gunzip_zlib(data, source)


def _gunzip_zlib(data: bytes, source) -> bytes:
    """``_gunzip`` by zlib: slower, but it tells a broken stream, a truncated one and trailing bytes apart."""
    inflater = zlib.decompressobj(GZIP_WBITS)
    try:
        out = inflater.decompress(data)
    except zlib.error as exc:
        raise SplatFormatError(f"{source}: {TITLE}: broken gzip stream ({exc})") from None
    if not inflater.eof:
        raise SplatFormatError(f"{source}: {TITLE}: truncated gzip stream (no end of stream after {len(data)} bytes)")
    if inflater.unused_data:
        raise SplatFormatError(f"{source}: {TITLE}: {len(inflater.unused_data)} bytes after the gzip stream")
    return out


def spz_payload_head(data: bytes, size: int = 16) -> bytes:
    """The first ``size`` bytes of the (gunzipped when gzip-wrapped) payload; b"" when not decodable."""
    if not data.startswith(GZIP_MAGIC):
        return data[:size]
    try:
        return zlib.decompressobj(GZIP_WBITS).decompress(data[:HEAD_INPUT_BYTES], size)
    except zlib.error:
        return b""


def _sizes(version: int, n: int, degree: int) -> list[tuple[str, int]]:
    return [("positions", n * 3 * (2 if version == 1 else 3)), ("alphas", n), ("colors", n * 3), ("scales", n * 3),
            ("rotations", n * (4 if version >= 3 else 3)), ("sh", n * 3 * _SH_DIM[degree])]


def _zstd_decompress(blob: bytes, expected: int, source, name: str) -> bytes:
    try:
        import zstandard
    except ImportError:
        raise SplatFormatError(f"{source}: {TITLE} version 4 needs the 'zstandard' package "
                               "(pip install zstandard)") from None
    try:
        out = zstandard.ZstdDecompressor().decompress(blob, max_output_size=expected)
    except zstandard.ZstdError as exc:
        raise SplatFormatError(f"{source}: {TITLE}: the '{name}' zstd stream is broken ({exc})") from None
    if len(out) != expected:
        raise SplatFormatError(f"{source}: {TITLE}: the '{name}' stream holds {len(out)} bytes, expected {expected}")
    return out


def _parse_header(head: bytes, where: str, bound: int) -> tuple[dict, list[tuple[str, int]]]:
    """Header fields and block sizes from the first 16 bytes of a payload of at most ``bound`` bytes."""
    if len(head) < LEGACY_HEADER.size:
        raise SplatFormatError(f"{where}: {len(head)} bytes, shorter than the 16-byte header")
    magic, version, n, degree, frac, flags, reserved = LEGACY_HEADER.unpack_from(head)
    if magic != SPZ_MAGIC:
        raise SplatFormatError(f"{where}: bad magic {head[:4]!r}, expected {SPZ_MAGIC_BYTES!r}")
    if version not in SPZ_VERSIONS:
        raise SplatFormatError(f"{where}: version {version} is not supported (supported: {SPZ_VERSIONS})")
    if degree > 4:
        raise SplatFormatError(f"{where}: SH degree {degree} is not valid (0..4)")
    if degree > MAX_SPZ_SH_DEGREE:
        raise SplatFormatError(f"{where}: SH degree {degree} is not supported (the toolkit reads degrees 0..3)")
    if frac > 24:
        raise SplatFormatError(f"{where}: {frac} fractional bits; at most 24 fit a 24-bit position")
    header = {"version": version, "num_points": n, "sh_degree": degree, "fractional_bits": frac,
              "antialiased": bool(flags & 1), "has_extensions": bool(flags & FLAG_EXTENSIONS), "frame": SPZ_FRAME}
    sizes = _sizes(version, n, degree)
    if sum(s for _, s in sizes) > bound + 1024:
        raise SplatFormatError(f"{where}: the header claims {n} points, impossible for a file of this size")
    return header, sizes


def _read_extensions(zone: bytes, where: str) -> str:
    """The stored frame named by the extension records in ``zone`` (``SPZ_FRAME`` when none names one)."""
    frame, offset = SPZ_FRAME, 0
    while offset < len(zone):
        if len(zone) - offset < EXTENSION_RECORD.size:
            raise SplatFormatError(f"{where}: {len(zone) - offset} stray bytes at the end of the extension records")
        kind, length = EXTENSION_RECORD.unpack_from(zone, offset)
        offset += EXTENSION_RECORD.size
        if length > len(zone) - offset:
            raise SplatFormatError(f"{where}: extension 0x{kind:08X} declares {length} bytes, only "
                                   f"{len(zone) - offset} remain")
        if kind == COORDINATE_SYSTEM_EXTENSION:
            if length != 4:
                raise SplatFormatError(f"{where}: coordinate-system extension of {length} bytes, expected 4")
            code = struct.unpack_from("<I", zone, offset)[0]
            if code not in COORDINATE_SYSTEMS:
                raise SplatFormatError(f"{where}: coordinate-system extension names unknown frame code {code} (0..16)")
            if code in ROTATED_FAMILY:
                raise SplatFormatError(f"{where}: stored in the rotated frame {COORDINATE_SYSTEMS[code]} "
                                       "(coordinate-system extension), not supported (standard-family frames only)")
            frame = COORDINATE_SYSTEMS[code]
        offset += length
    return frame


def _split_streams(data: bytes, source) -> tuple[dict, dict[str, np.ndarray]]:
    """Header fields and the raw attribute blocks (uint8 arrays) of a decoded payload."""
    where = f"{source}: {TITLE}"
    header, sizes = _parse_header(data, where, MAX_EXPANSION * max(len(data), 1))
    version, n, degree = header["version"], header["num_points"], header["sh_degree"]
    blocks: dict[str, np.ndarray] = {}
    if version < 4:
        offset = LEGACY_HEADER.size
        needed = offset + sum(s for _, s in sizes)
        if len(data) < needed:
            raise SplatFormatError(f"{where}: truncated: the header declares {n} points (SH degree {degree}), "
                                   f"{needed} bytes, but the payload has {len(data)}")
        raw = np.frombuffer(data, np.uint8)
        for name, size in sizes:
            blocks[name] = raw[offset: offset + size]
            offset += size
        if header["has_extensions"]:          # records after the SH block; without the flag, a tail is ignored
            header["frame"] = _read_extensions(data[offset:], where)
        return header, blocks
    if len(data) < V4_HEADER.size:
        raise SplatFormatError(f"{where}: {len(data)} bytes, shorter than the 32-byte version-4 header")
    *_, num_streams, toc_offset, _reserved = V4_HEADER.unpack_from(data)
    present = [(name, size) for name, size in sizes if size > 0]
    if n == 0:
        present = [(name, 0) for name, _ in sizes[:5]]
    if num_streams != len(present):
        raise SplatFormatError(f"{where}: {num_streams} streams declared, expected {len(present)} "
                               f"({', '.join(name for name, _ in present)})")
    toc_end = toc_offset + num_streams * TOC_ENTRY.size
    if toc_offset < V4_HEADER.size or toc_end > len(data):
        raise SplatFormatError(f"{where}: table of contents at byte {toc_offset} lies outside the "
                               f"{len(data)}-byte file")
    if header["has_extensions"]:
        header["frame"] = _read_extensions(data[V4_HEADER.size: toc_offset], where)
    offset = toc_end
    for i, (name, size) in enumerate(present):
        compressed, uncompressed = TOC_ENTRY.unpack_from(data, toc_offset + i * TOC_ENTRY.size)
        if uncompressed != size:
            raise SplatFormatError(f"{where}: stream '{name}' declares {uncompressed} bytes, expected {size} "
                                   f"for {n} points")
        if compressed > len(data) - offset:
            raise SplatFormatError(f"{where}: truncated: stream '{name}' ({compressed} bytes) runs past the end "
                                   f"of the file")
        blob = data[offset: offset + compressed]
        offset += compressed
        blocks[name] = np.frombuffer(_zstd_decompress(blob, size, source, name) if size else b"", np.uint8)
    if offset != len(data):
        raise SplatFormatError(f"{where}: {len(data) - offset} bytes after the last stream")
    for name, size in sizes:
        blocks.setdefault(name, np.zeros(size, np.uint8))
    return header, blocks


#: Value of every 10-bit smallest-three field: a 9-bit magnitude ``m / 511 / sqrt(2)``, bit 9 the sign.
_FIELD_DECODE = (np.where(np.arange(1024) & 512, np.float32(-1.0), np.float32(1.0))
                 * ((np.arange(1024) & 511).astype(np.float32) * np.float32(np.sqrt(0.5) / 511.0))).astype(np.float32)
#: Per index of the largest component (x, y, z, w order): where each output component w, x, y, z comes from
#: among [field 0, field 1, field 2, largest]; the fields from the lowest bits up hold the remaining
#: components from the highest index down.
_SLOTS_WXYZ = np.array([[3 if c == largest else [i for i in (3, 2, 1, 0) if i != largest].index(c)
                         for c in (3, 0, 1, 2)] for largest in range(4)], dtype=np.intp)


#: Value of every SH byte, ``(b - 128) / 128`` (exact in float32).
_SH_BYTE_VALUE = ((np.arange(256, dtype=np.float32) - np.float32(128.0)) * np.float32(1.0 / 128.0)).astype(np.float32)


def decode_rotations_v3_reference(packed: np.ndarray, signs: np.ndarray | None = None) -> np.ndarray:
    """``[N]`` uint32 smallest-three -> ``[N, 4]`` float32 (w, x, y, z) times ``signs`` (``[4]``, the frame change;
    default RUB -> RDF): table look-ups and one gather (the numpy reference of ``spz_kernels.decode_rotations_v3``)."""
    signs = frame_signs()[1] if signs is None else signs
    n = packed.shape[0]
    values = np.empty((n, 4), np.float32)                  # field 0, field 1, field 2, largest
    for j in range(3):
        values[:, j] = _FIELD_DECODE[(packed >> np.uint32(10 * j)) & np.uint32(1023)]
    small = values[:, :3]
    np.sqrt(np.maximum(np.float32(0.0), np.float32(1.0) - np.einsum("ij,ij->i", small, small)), out=values[:, 3])
    return np.take_along_axis(values, _SLOTS_WXYZ[(packed >> np.uint32(30)).astype(np.intp)], axis=1) * signs


def decode_rotations_v2_reference(raw: np.ndarray, signs: np.ndarray | None = None) -> np.ndarray:
    """``[N, 3]`` uint8 x, y, z -> ``[N, 4]`` float32 (w, x, y, z), w = sqrt(1 - |xyz|^2), times ``signs`` (``[4]``,
    the frame change; default RUB -> RDF) (the numpy reference of ``spz_kernels.decode_rotations_v2``)."""
    signs = frame_signs()[1] if signs is None else signs
    xyz = raw * np.float32(1.0 / 127.5) - np.float32(1.0)
    w = np.sqrt(np.maximum(np.float32(0.0), np.float32(1.0) - np.einsum("ij,ij->i", xyz, xyz)))
    return (np.concatenate([w[:, None], xyz], axis=1) * signs).astype(np.float32)


def decode_fixed24_reference(raw: np.ndarray, n: int, fractional_bits: int,
                             signs: np.ndarray | None = None) -> np.ndarray:
    """``[N * 9]`` bytes of little-endian signed 24-bit fixed point -> ``[N, 3]`` float32 ``q / 2^bits`` times
    ``signs`` (``[3]``, the frame change; default RUB -> RDF) (the numpy reference of
    ``spz_kernels.decode_fixed24``)."""
    signs = frame_signs()[0] if signs is None else signs
    b = raw.reshape(n, 3, 3).astype(np.int32)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = (fixed ^ 0x800000) - 0x800000                                      # sign-extend 24 bits
    return (fixed * np.float32(1.0 / (1 << fractional_bits)) * signs).astype(np.float32)


def decode_sh_rows_reference(rest_bytes: np.ndarray, dc: np.ndarray, signs: np.ndarray | None = None) -> np.ndarray:
    """``[M, 3 (K - 1)]`` uint8 SH bytes and ``[M, 3]`` float32 DC -> ``[M, 3 K]`` float32 rows: the DC, then
    ``(b - 128) / 128`` times ``signs`` (``[3 (K - 1)]`` per column, the frame change; default RUB -> RDF) (the numpy
    reference of ``spz_kernels.decode_sh_rows``)."""
    signs = _sh_column_signs(frame_signs()[2], rest_bytes.shape[1]) if signs is None else signs
    out = np.empty((rest_bytes.shape[0], rest_bytes.shape[1] + 3), np.float32)
    out[:, :3] = dc
    np.subtract(rest_bytes, np.float32(128.0), out=out[:, 3:], dtype=np.float32, casting="unsafe")
    out[:, 3:] *= np.float32(1.0 / 128.0)
    out[:, 3:] *= signs
    return out


def _sh_column_signs(sh_signs: np.ndarray, columns: int) -> np.ndarray:
    """``[3 (K - 1)]`` float32: the sign of each SH rest byte column (coefficient-major, channel innermost)."""
    return np.ascontiguousarray(np.repeat(sh_signs[: columns // 3], 3), dtype=np.float32)


def _decode_blocks(header: dict, blocks: dict[str, np.ndarray]) -> Gaussians:
    """Decode the attribute blocks of a payload."""
    n, version, degree = header["num_points"], header["version"], header["sh_degree"]
    position_signs, quat_signs, sh_signs = frame_signs(header["frame"])
    means = np.empty((n, 3), np.float32)
    if version == 1:
        means[:] = blocks["positions"].view("<f2").reshape(n, 3)
        np.negative(means, out=means, where=position_signs < 0)      # a sign flip: NaN (validated later) stays quiet
    else:
        spz_kernels.decode_fixed24(blocks["positions"],
                                   position_signs * np.float32(1.0 / (1 << header["fractional_bits"])),
                                   means.reshape(-1))
    opacity_logits = logit_from_unit(blocks["alphas"] * np.float32(1.0 / 255.0))
    dc = (blocks["colors"].reshape(n, 3) * np.float32(1.0 / 255.0) - np.float32(0.5)) / np.float32(SPZ_COLOR_SCALE)
    log_scales = (blocks["scales"].reshape(n, 3) * np.float32(1.0 / 16.0) - np.float32(10.0)).astype(np.float32,
                                                                                                   copy=False)
    quats = np.empty((n, 4), np.float32)
    if version >= 3:
        spz_kernels.decode_rotations_v3(blocks["rotations"].view("<u4"), _FIELD_DECODE, _SLOTS_WXYZ, quat_signs,
                                        quats)
    else:
        spz_kernels.decode_rotations_v2(blocks["rotations"].reshape(n, 3), quat_signs, quats)
    k = (degree + 1) ** 2
    sh = np.empty((n, k, 3), np.float32)
    spz_kernels.decode_sh_rows(blocks["sh"].reshape(n, 3 * (k - 1)), dc, _SH_BYTE_VALUE,
                               _sh_column_signs(sh_signs, 3 * (k - 1)), sh.reshape(n, 3 * k))
    return Gaussians(means, quats, log_scales, opacity_logits, sh)


def decode_spz(data: bytes, source: str | os.PathLike = "<bytes>") -> Gaussians:
    """The bytes of an SPZ file (gzip-wrapped or not) -> ``Gaussians`` in RDF (converted from the stored frame,
    RUB unless an extension names another; not validated)."""
    if not data:
        raise SplatFormatError(f"{source}: empty file (0 bytes), not a {TITLE} file")
    payload = _gunzip(data, source) if data.startswith(GZIP_MAGIC) else data
    return _decode_blocks(*_split_streams(payload, source))


def read_spz(path: str | os.PathLike) -> Gaussians:
    """Read an SPZ file -> ``Gaussians`` in RDF (not validated); ``SplatFormatError`` when malformed."""
    path = Path(path)
    return decode_spz(read_file_bytes(path, TITLE), path)


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------
def _bytes(values: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.nan_to_num(values, nan=0.0)), 0, 255).astype(np.uint8)


def _encode_rotations_v3(quats: np.ndarray) -> np.ndarray:
    n = quats.shape[0]
    norms = np.linalg.norm(quats.astype(np.float64), axis=1, keepdims=True)
    wxyz = np.where(norms > 0, quats / np.where(norms > 0, norms, 1.0), np.array([1.0, 0, 0, 0]))
    xyzw = wxyz[:, [1, 2, 3, 0]]
    largest = np.argmax(np.abs(xyzw), axis=1)
    xyzw = xyzw * np.where(xyzw[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    packed = largest.astype(np.uint32)
    for i in range(4):          # the component with the highest index ends in the lowest bits
        keep = largest != i
        value = xyzw[:, i]
        magnitude = np.clip(np.round(np.abs(value) / np.sqrt(0.5) * 511.0), 0, 511).astype(np.uint32)
        field = magnitude | (np.uint32(1 << 9) * (value < 0).astype(np.uint32))
        packed = np.where(keep, (packed << np.uint32(10)) | field, packed)
    return packed.astype("<u4")


def encode_spz(gaussians: Gaussians, version: int = DEFAULT_WRITE_VERSION) -> bytes:
    """``Gaussians`` (RDF) -> the bytes of an SPZ file of ``version`` (2, 3: gzip; 4: zstd streams), stored in RUB."""
    if version not in WRITE_VERSIONS:
        raise ValueError(f"SPZ version {version} cannot be written (choose one of {WRITE_VERSIONS})")
    g = gaussians
    n = len(g)
    require_finite(g, TITLE)
    position_signs, quat_signs, sh_signs = (s.astype(np.float64) for s in frame_signs(SPZ_FRAME))  # RDF -> RUB
    limit = (1 << 23) - 1
    fixed = np.round(g.means.astype(np.float64) * position_signs * (1 << WRITE_FRACTIONAL_BITS))
    if n and np.abs(fixed).max() > limit:
        raise ValueError(f"{TITLE}: positions beyond +-{limit / (1 << WRITE_FRACTIONAL_BITS):.0f} m do not fit "
                         f"24-bit fixed point with {WRITE_FRACTIONAL_BITS} fraction bits")
    fixed = fixed.astype(np.int32) & 0xFFFFFF
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], axis=-1).astype(np.uint8)
    alphas = _bytes(unit_from_logit(g.opacity_logits) * 255.0)
    colors = _bytes((g.sh[:, 0, :].astype(np.float64) * SPZ_COLOR_SCALE + 0.5) * 255.0)
    scales = _bytes((g.log_scales.astype(np.float64) + 10.0) * 16.0)
    if version >= 3:
        rotations = _encode_rotations_v3(g.quats.astype(np.float64) * quat_signs).view(np.uint8)
    else:
        wxyz = g.normalized_quats().astype(np.float64) * quat_signs
        wxyz = wxyz * np.where(wxyz[:, :1] < 0, -1.0, 1.0)
        rotations = _bytes((wxyz[:, 1:] + 1.0) * 127.5)
    sh = _bytes(g.sh[:, 1:, :].astype(np.float64) * sh_signs[: g.sh.shape[1] - 1, None] * 128.0 + 128.0)
    degree = g.sh_degree
    blocks = [positions, alphas, colors, scales, rotations, sh]
    payloads = [np.ascontiguousarray(b).tobytes() for b in blocks]
    if version < 4:
        header = LEGACY_HEADER.pack(SPZ_MAGIC, version, n, degree, WRITE_FRACTIONAL_BITS, 0, 0)
        return gzip.compress(header + b"".join(payloads), mtime=0)
    import zstandard

    compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    streams = [p for p in payloads if p] if n else payloads[:5]
    compressed = [compressor.compress(p) for p in streams]
    header = V4_HEADER.pack(SPZ_MAGIC, 4, n, degree, WRITE_FRACTIONAL_BITS, 0, len(streams), V4_HEADER.size,
                            bytes(12))
    toc = b"".join(TOC_ENTRY.pack(len(c), len(p)) for c, p in zip(compressed, streams))
    return header + toc + b"".join(compressed)


def write_spz(path: str | os.PathLike, gaussians: Gaussians, version: int = DEFAULT_WRITE_VERSION) -> None:
    """Write ``gaussians`` (RDF) as an SPZ file of ``version`` (stored in RUB), atomically (extras dropped)."""
    write_bytes_atomic(path, encode_spz(gaussians, version))
