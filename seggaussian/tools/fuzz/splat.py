"""Fuzz targets of the non-PLY splat formats for the shared harness in ``seggaussian.tools.fuzz.engine``.

One ``FuzzTarget`` per format (``.splat``, compressed PLY, SPZ v1-v4 gzip-wrapped and raw, ``.ksplat`` at
compression levels 0-2, glTF as GLB, as JSON and with SPZ compression), all read through
``seggaussian.io.formats.read_gaussians`` (content detection + decode + validation, what every command runs).
Seeds are written by our writers (SPZ v1 is assembled from a v2 payload: no writer emits it). Mutators: the
harness's byte mutators for every format, its PLY header mutators for compressed PLY, plus format-aware ones:
SPZ header fields (count, version, SH degree, fraction bits, stream count, TOC offset) and byte flips inside
the gzip payload (re-wrapped, so they pass the CRC), and NaN / Inf written into float fields (.splat records,
compressed-PLY chunk bounds, SPZ v1 float16 positions, .ksplat block size, SH range and record floats), and
.ksplat header fields (section count, splat counts, compression level, buckets, SH degree), glTF JSON fields
(accessor counts, types, offsets, indices; buffer view ranges; node matrices and children).
"""

from __future__ import annotations

import gzip
import json
import struct
import zlib
import tempfile
from pathlib import Path

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians, write_gaussians
from seggaussian.io.gltf_container import GLB_MAGIC, pack_glb
from seggaussian.io.ply.header import PlyFormatError
from seggaussian.io.spz import GZIP_MAGIC, encode_spz
from seggaussian.tools.fuzz.engine import BYTE_MUTATORS, FuzzTarget, Mutator
from seggaussian.tools.fuzz.ply import PLY_MUTATORS

__all__ = ["splat_targets", "SPLAT_TARGET_NAMES"]

SPLAT_TARGET_NAMES = ("splat", "compressed_ply", "spz1", "spz2", "spz3", "spz3_raw", "spz4", "ksplat", "glb", "gltf",
                      "glb_spz")
_BAD_FLOATS = (np.nan, np.inf, -np.inf)


def _gaussians(rng: np.random.Generator, n: int, degree: int) -> Gaussians:
    k = (degree + 1) ** 2
    return Gaussians.from_arrays(rng.uniform(-2, 2, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-6, 0, (n, 3)),
                                 rng.normal(size=n), rng.uniform(-1, 1, (n, k, 3)))


def _spz_v1(g: Gaussians) -> bytes:
    """A version-1 SPZ payload (float16 positions, 3-byte rotations), not gzip-wrapped; positions in SPZ's RUB
    axes like the rest of the payload (y and z negated)."""
    payload = gzip.decompress(encode_spz(g, version=2))
    head = bytearray(payload[:16])
    head[4:8] = struct.pack("<I", 1)
    rub = g.means * np.array([1.0, -1.0, -1.0], np.float32)
    return bytes(head) + rub.astype("<f2").tobytes() + payload[16 + 9 * len(g):]


def _on_payload(mutate):
    """Apply ``mutate`` to the SPZ payload, inside the gzip wrapper when there is one."""
    def wrapped(data: bytes, rng: np.random.Generator) -> bytes:
        if data.startswith(GZIP_MAGIC):
            try:
                payload = gzip.decompress(data)
            except (OSError, EOFError, zlib.error):   # an earlier mutation broke the stream
                return data
            return gzip.compress(mutate(bytearray(payload), rng), mtime=0)
        return mutate(bytearray(data), rng)
    return wrapped


def _spz_header_field(data: bytearray, rng: np.random.Generator) -> bytes:
    if len(data) < 32:
        return bytes(data)
    field, size = ((4, 4), (8, 4), (12, 1), (13, 1), (14, 1), (15, 1), (16, 4))[int(rng.integers(7))]
    value = int(rng.choice([0, 1, 2, 3, 4, 5, 25, 39, 41, 255, 2**20, 2**31 - 1, 2**32 - 1])) % (256 ** size)
    data[field: field + size] = value.to_bytes(size, "little")
    return bytes(data)


def _payload_flip(data: bytearray, rng: np.random.Generator) -> bytes:
    for _ in range(int(rng.integers(1, 9))):
        i = int(rng.integers(len(data))) if data else 0
        if data:
            data[i] ^= int(rng.integers(1, 256))
    return bytes(data)


def _splat_nan(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    if len(out) >= 32:
        record, field = int(rng.integers(len(out) // 32)), int(rng.integers(6))
        out[record * 32 + 4 * field: record * 32 + 4 * field + 4] = struct.pack("<f", rng.choice(_BAD_FLOATS))
    return bytes(out)


def _chunk_nan(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    start = out.find(b"end_header\n")
    if start >= 0:
        offset = start + len(b"end_header\n") + 4 * int(rng.integers(18))
        out[offset: offset + 4] = struct.pack("<f", rng.choice(_BAD_FLOATS))
    return bytes(out)


def _f16_nan(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    if len(out) > 16 + 2 * 120:
        offset = 16 + 2 * int(rng.integers(120))
        out[offset: offset + 2] = np.array([rng.choice(_BAD_FLOATS)], "<f2").tobytes()
    return bytes(out)


#: glTF JSON fields set to odd values by ``gltf_json_field``: (array, field).
_GLTF_FIELDS = (("accessors", "count"), ("accessors", "componentType"), ("accessors", "type"),
                ("accessors", "byteOffset"), ("accessors", "bufferView"), ("accessors", "normalized"),
                ("bufferViews", "byteLength"), ("bufferViews", "byteOffset"), ("bufferViews", "byteStride"),
                ("bufferViews", "buffer"), ("buffers", "byteLength"), ("meshes", "primitives"), ("nodes", "mesh"),
                ("nodes", "matrix"), ("nodes", "children"))
_GLTF_VALUES = (0, 1, -1, 3, 4, 5121, 5126, 2**31, 1e300, None, "VEC3", "x", [], {}, [1, 2], True)


def gltf_json_field(data: bytes, rng: np.random.Generator) -> bytes:
    """One field of a glTF document (GLB or JSON) set to an odd value (a wrong count, type, offset, index...)."""
    binary = data.startswith(GLB_MAGIC)
    try:
        if binary:
            size = struct.unpack_from("<I", data, 12)[0]
            doc, blob = json.loads(data[20: 20 + size]), data[28 + size:]
        else:
            doc = json.loads(data)
    except (ValueError, struct.error):
        return data
    key, field = _GLTF_FIELDS[int(rng.integers(len(_GLTF_FIELDS)))]
    items = doc.get(key) if isinstance(doc, dict) else None
    if not isinstance(items, list) or not items or not isinstance(items[0], dict):
        return data
    items[int(rng.integers(len(items)))][field] = _GLTF_VALUES[int(rng.integers(len(_GLTF_VALUES)))]
    text = json.dumps(doc).encode()
    return pack_glb(text, blob) if binary else text


#: (offset, size) of the .ksplat header fields mutated: main header counts and level, section header fields.
_KSPLAT_FIELDS = ((0, 1), (1, 1), (4, 4), (8, 4), (12, 4), (16, 4), (20, 2)) + tuple(
    (4096 + offset, size) for offset, size in ((0, 4), (4, 4), (8, 4), (12, 4), (20, 2), (24, 4), (32, 4), (36, 4),
                                               (40, 2)))


def _ksplat_header_field(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    offset, size = _KSPLAT_FIELDS[int(rng.integers(len(_KSPLAT_FIELDS)))]
    if len(out) >= offset + size:
        value = int(rng.choice([0, 1, 2, 3, 4, 7, 39, 41, 255, 256, 2**16 - 1, 2**20, 2**31 - 1, 2**32 - 1]))
        out[offset: offset + size] = (value % (256 ** size)).to_bytes(size, "little")
    return bytes(out)


def _ksplat_nan(data: bytes, rng: np.random.Generator) -> bytes:
    """NaN / Inf into the block size, the SH range or a float (float32 or float16) of the records."""
    out = bytearray(data)
    bad = rng.choice(_BAD_FLOATS)
    where = int(rng.integers(3))
    if where == 0 and len(out) >= 4096 + 20:
        out[4096 + 16: 4096 + 20] = struct.pack("<f", bad)
    elif where == 1 and len(out) >= 44:
        offset = 36 + 4 * int(rng.integers(2))          # sh_min or sh_max
        out[offset: offset + 4] = struct.pack("<f", bad)
    elif len(out) > 5120 + 64:
        offset = 5120 + 2 * int(rng.integers((len(out) - 5120) // 2 - 2))
        out[offset: offset + 2] = np.array([bad], "<f2").tobytes()
    return bytes(out)


SPZ_MUTATORS: tuple[tuple[str, Mutator], ...] = (
    ("spz_header_field", _on_payload(_spz_header_field)),
    ("spz_payload_flip", _on_payload(_payload_flip)),
)


def splat_targets(seed: int = 0) -> list[FuzzTarget]:
    """One ``FuzzTarget`` per name of ``SPLAT_TARGET_NAMES`` (seeds written with generator ``seed``)."""
    rng = np.random.default_rng(seed)
    scenes = {"sh0": _gaussians(rng, 40, 0), "sh1": _gaussians(rng, 40, 1), "sh3": _gaussians(rng, 30, 3)}
    seeds: dict[str, list[tuple[str, bytes]]] = {name: [] for name in SPLAT_TARGET_NAMES}
    with tempfile.TemporaryDirectory() as tmp:
        for label, g in scenes.items():
            for name, fmt, options in (("compressed_ply", "compressed_ply", {}), ("spz2", "spz", {"spz_version": 2}),
                                       ("spz3", "spz", {"spz_version": 3}), ("spz4", "spz", {"spz_version": 4})):
                path = Path(tmp) / f"{name}_{label}"
                write_gaussians(path, g, fmt, **options)
                seeds[name].append((f"written:{label}", path.read_bytes()))
            seeds["spz3_raw"].append((f"written:{label}", gzip.decompress(seeds["spz3"][-1][1])))
            seeds["spz1"].append((f"assembled:{label}", _spz_v1(g)))
        for label, g in scenes.items():
            for level in (0, 1, 2):
                path = Path(tmp) / f"ksplat{level}_{label}"
                write_gaussians(path, g, "ksplat", ksplat_level=level)
                seeds["ksplat"].append((f"written:l{level}:{label}", path.read_bytes()))
        path = Path(tmp) / "seed.splat"
        write_gaussians(path, scenes["sh0"], "splat")
        seeds["splat"].append(("written:sh0", path.read_bytes()))
        labels = {"semantic": np.arange(30, dtype=np.int32) % 7}
        for name, suffix, compression in (("glb", ".glb", "none"), ("gltf", ".gltf", "none"),
                                          ("glb_spz", ".glb", "spz")):
            for label in ("sh0", "sh3"):
                path = Path(tmp) / f"{name}_{label}{suffix}"
                g = scenes[label] if label == "sh0" else scenes[label].with_extras(**labels)
                write_gaussians(path, g, "gltf", gltf_compression=compression)
                seeds[name].append((f"written:{label}", path.read_bytes()))
    extra: dict[str, tuple[tuple[str, Mutator], ...]] = {
        "splat": (("splat_nan", _splat_nan),),
        "compressed_ply": PLY_MUTATORS + (("chunk_nan", _chunk_nan),),
        "spz1": SPZ_MUTATORS + (("spz1_f16_nan", _f16_nan),),
        "ksplat": (("ksplat_header_field", _ksplat_header_field), ("ksplat_nan", _ksplat_nan)),
        **{name: (("gltf_json_field", gltf_json_field),) for name in ("glb", "gltf")},
        "glb_spz": (("gltf_json_field", gltf_json_field),),
    }

    def read(path: Path) -> Gaussians:
        return read_gaussians(path).gaussians

    return [FuzzTarget(name, read, seeds[name], extra.get(name, SPZ_MUTATORS if name.startswith("spz") else ())
                       + BYTE_MUTATORS, (PlyFormatError,), ".bin")
            for name in SPLAT_TARGET_NAMES]
