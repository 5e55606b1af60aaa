"""glTF 2.0 splats: the ``KHR_gaussian_splatting`` extension, in a ``.glb`` (binary) or a ``.gltf`` (JSON) file.

The extension (Khronos, ``extensions/2.0/Khronos/KHR_gaussian_splatting`` of KhronosGroup/glTF; "Release
Candidate" when this was written) stores one Gaussian per point of a ``POINTS`` (mode 0) mesh primitive whose
``extensions.KHR_gaussian_splatting`` names ``kernel: "ellipse"`` and a ``colorSpace``. Attributes and their
conventions, as the extension defines them (and as read and written here):

=============================================  =======  ============================================================
attribute                                      type     content
=============================================  =======  ============================================================
``POSITION``                                   VEC3     float; the mean, metres, in glTF's frame (below)
``KHR_gaussian_splatting:ROTATION``            VEC4     unit quaternion **x, y, z, w** (glTF order); float, or
                                                        normalized signed byte / short
``KHR_gaussian_splatting:SCALE``               VEC3     **linear** standard deviations (not logs), >= 0; float, or
                                                        (normalized) unsigned byte / short
``KHR_gaussian_splatting:OPACITY``             SCALAR   **linear** opacity in [0, 1] (not a logit); float, or
                                                        normalized unsigned byte / short
``KHR_gaussian_splatting:SH_DEGREE_0_COEF_0``  VEC3     float; the DC coefficient (colour = 0.5 + SH_C0 * it)
``KHR_gaussian_splatting:SH_DEGREE_l_COEF_n``  VEC3     float; degree ``l`` 1-3, ``n = m + l`` for order ``m`` from
                                                        ``-l`` to ``l``: 3DGS's coefficient ``l^2 + n``, RGB
``COLOR_0``                                    VEC4     fallback colour for viewers without the extension: linear
                                                        RGB (the sRGB colour of the DC decoded) and opacity; written,
                                                        ignored on reading
``_SEMANTIC``, ``_INSTANCE``, ``_<NAME>``      SCALAR   our per-Gaussian columns (``Gaussians.extras``: labels and
                                                        any other 1-D column), application-specific attributes that
                                                        other readers ignore; integers as (unsigned) short, else float
=============================================  =======  ============================================================

The SH basis is 3DGS's (real SH with the Condon-Shortley phase; degree 1 is ``-C1 y, C1 z, -C1 x``), evaluated on the
view direction in glTF's frame. Colour space: ``srgb_rec709_display`` (what 3DGS trainers produce) is read and
written; ``lin_rec709_display`` is refused (its colours would need the sRGB curve applied to an SH sum).

Frame. glTF is right-handed, metres, +Y up, the front of an asset facing +Z and its left side +X (glTF 2.0,
"Coordinate System and Units"): in axis letters LUF, as Niantic's SPZ library names glTF's frame. ``Gaussians``
hold RDF, so reading and writing turn the scene by 180 degrees about z: positions ``(-x, -y, z)``,
quaternions ``(w, -x, -y, z)``, SH coefficients times the parity of their basis polynomial under x, y -> -x, -y
(``seggaussian.io.spz.frame_signs("LUF")``). The global transform of the node that instantiates the mesh is applied
on reading when it is a similarity (translation, rotation, positive uniform scale); anything else is refused.

Checked on reading, each a one-line ``SplatFormatError`` naming the file and the field: the container (GLB header,
chunk lengths, 4-byte alignment; JSON), ``asset.version`` 2.x, ``extensionsRequired`` (only the extension), mode
``POINTS``, kernel ``ellipse``, colour space, projection ``perspective``, every accessor (type, component type,
count, in bounds; no sparse accessors), the SH degrees complete and without gaps, scales >= 0 and finite, opacities in
[0, 1], rotations unit (within ``UNIT_TOLERANCE``). Files with several splat primitives are read as one scene.

Writing: a GLB (``.glb``) or a ``.gltf`` whose one buffer is embedded as a base64 ``data:`` URI; one scene, one node
(no transform), one mesh, one primitive, float attributes in one buffer view each (4-byte aligned), ``POSITION``
with its ``min``/``max``; ``KHR_gaussian_splatting`` in ``extensionsUsed`` (not required: a viewer without it draws
the points in their ``COLOR_0``). ``legend`` (class names and colours) goes in the root ``extras.seggaussian``.
"""

from __future__ import annotations

import base64
import json
import os
import re
import struct
from pathlib import Path
from typing import Mapping, NamedTuple

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_atomic
from seggaussian.io.splat_common import (
    SplatFormatError,
    logit_from_unit,
    read_file_bytes,
    rgb_from_dc,
    unit_from_logit,
    unorm_to_byte,
)
from seggaussian.io.spz import decode_spz, encode_spz, frame_signs

__all__ = ["GLB_MAGIC", "EXTENSION", "SPZ_EXTENSION", "COMPRESSIONS", "GLTF_FRAME", "GltfSplat", "looks_like_gltf", "decode_gltf", "read_gltf",
           "encode_gltf", "write_gltf", "attribute_name", "extra_name"]

TITLE = "glTF (KHR_gaussian_splatting)"
GLB_MAGIC = b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
GLB_HEADER = struct.Struct("<4sII")
CHUNK_HEADER = struct.Struct("<II")
EXTENSION = "KHR_gaussian_splatting"
PREFIX = EXTENSION + ":"
#: The SPZ compression extension (a draft extending this one; CesiumJS renders splats only from it).
SPZ_EXTENSION = "KHR_gaussian_splatting_compression_spz_2"
#: The SPZ version its blob holds ("v2 of the SPZ compression format").
SPZ_BLOB_VERSION = 2
#: Compressions written: ``none`` (the base extension's float attributes) or ``spz`` (``SPZ_EXTENSION``).
COMPRESSIONS = ("none", "spz")
#: The SPZ blob stores glTF's coordinates as they are (LUF, not SPZ's own RUB), as CesiumJS reads it (it unpacks the
#: blob with the coordinate system ``UNSPECIFIED``: no conversion; tests/seggaussian/io/test_cesium_viewer.py renders
#: our files so: correlation 0.9995 with our rasterizer, 0.47 when the blob is written in RUB). Our SPZ writer stores RUB from RDF and our reader undoes it, so the Gaussians (RDF) are turned by
#: the flips taking LUF to RUB (``LDB``: x and z negated) before writing the blob and after reading it. (The draft's
#: text asks for "LUF" in Niantic's pack/unpack options, which would store RUB; the renderer of its authors decides.)
SPZ_BLOB_CORRECTION = "LDB"
#: The frame glTF stores, as axis letters (``Gaussians`` hold RDF).
GLTF_FRAME = "LUF"
KERNEL = "ellipse"
COLOR_SPACE = "srgb_rec709_display"
PROJECTION = "perspective"
SORTING = "cameraDistance"
POINTS_MODE = 0
#: Largest deviation of a stored rotation's norm from 1 (the extension stores unit quaternions; a normalized byte
#: quaternion is off by up to about 2/127).
UNIT_TOLERANCE = 0.02
#: Key of our entry in the root ``extras``.
EXTRAS_KEY = "seggaussian"
#: Largest integer a float32 holds exactly (integer extras beyond the short ranges are written as floats up to it).
FLOAT_EXACT_INT = 1 << 24

BYTE, UBYTE, SHORT, USHORT, UINT, FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
#: ``bufferView.target`` of vertex attributes.
ARRAY_BUFFER = 34962
COMPONENT_DTYPES = {BYTE: np.dtype("<i1"), UBYTE: np.dtype("<u1"), SHORT: np.dtype("<i2"), USHORT: np.dtype("<u2"),
                    UINT: np.dtype("<u4"), FLOAT: np.dtype("<f4")}
TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
#: Accepted (accessor type, {component type: must be normalized (True), must not be (False), either (None)}).
ATTRIBUTE_TYPES = {
    "POSITION": ("VEC3", {FLOAT: False}),
    PREFIX + "ROTATION": ("VEC4", {FLOAT: False, BYTE: True, SHORT: True}),
    PREFIX + "SCALE": ("VEC3", {FLOAT: False, UBYTE: None, USHORT: None}),
    PREFIX + "OPACITY": ("SCALAR", {FLOAT: False, UBYTE: True, USHORT: True}),
}
SH_TYPE = ("VEC3", {FLOAT: False})
EXTRA_TYPE = ("SCALAR", {FLOAT: False, BYTE: False, UBYTE: False, SHORT: False, USHORT: False})
_SH_SEMANTIC = re.compile(re.escape(PREFIX) + r"SH_DEGREE_(\d+)_COEF_(\d+)$")
_EXTRA_NAME = re.compile(r"[a-z][a-z0-9_]*$")


class GltfSplat(NamedTuple):
    """A decoded glTF splat file.

    Fields:
        gaussians: the Gaussians (RDF), with ``_NAME`` attributes as extras (``name`` lower-cased).
        legend: the root ``extras.seggaussian`` object (``{}`` when absent).
    """

    gaussians: Gaussians
    legend: dict


def attribute_name(degree: int, coef: int) -> str:
    """The semantic of SH coefficient ``coef`` (0 .. 2 degree) of ``degree``."""
    return f"{PREFIX}SH_DEGREE_{degree}_COEF_{coef}"


def extra_name(column: str) -> str:
    """The application-specific attribute of the extras column ``column`` (``semantic`` -> ``_SEMANTIC``)."""
    return "_" + column.upper()


def looks_like_gltf(head: bytes) -> bool:
    """``head`` starts a GLB (``glTF`` magic) or a glTF JSON document (an object naming ``asset``)."""
    if head.startswith(GLB_MAGIC):
        return True
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    return text.startswith(b"{") and b'"asset"' in head


# --- reading -------------------------------------------------------------------------------------------------------
class _Document:
    """The JSON of a glTF file and its buffers' bytes, with checked access to accessors."""

    def __init__(self, doc: dict, buffers: list[bytes], where: str):
        self.doc, self.buffers, self.where = doc, buffers, where

    def fail(self, field: str, problem: str) -> SplatFormatError:
        return SplatFormatError(f"{self.where}: {TITLE}: {field}: {problem}")

    def array(self, key: str) -> list:
        value = self.doc.get(key, [])
        if not isinstance(value, list):
            raise self.fail(key, f"expected a JSON array, got {type(value).__name__}")
        return value

    def item(self, key: str, index, field: str) -> dict:
        items = self.array(key)
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(items):
            raise self.fail(field, f"index {index!r} is not one of the {len(items)} {key}")
        value = items[index]
        if not isinstance(value, dict):
            raise self.fail(f"{key}[{index}]", "expected a JSON object")
        return value

    def accessor(self, index, semantic: str, allowed: tuple[str, dict], count: int | None) -> np.ndarray:
        """The values of accessor ``index`` (``[count, width]`` float64, normalized integers scaled) for ``semantic``."""
        field = f"attribute {semantic} (accessor {index})"
        acc = self.item("accessors", index, field)
        kind, components = allowed
        ctype, normalized = acc.get("componentType"), bool(acc.get("normalized", False))
        if acc.get("type") != kind:
            raise self.fail(field, f"type {acc.get('type')!r}, expected {kind!r}")
        if ctype not in components:
            names = ", ".join(COMPONENT_DTYPES[c].name for c in components)
            raise self.fail(field, f"component type {ctype!r} is not one the extension allows here ({names})")
        if components[ctype] is not None and components[ctype] != normalized:
            raise self.fail(field, f"normalized must be {str(components[ctype]).lower()} for component type "
                                   f"{COMPONENT_DTYPES[ctype].name}")
        n = acc.get("count")
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            raise self.fail(field, f"count {n!r} is not a non-negative integer")
        if count is not None and n != count:
            raise self.fail(field, f"count {n} differs from POSITION's {count}")
        if "sparse" in acc:
            raise self.fail(field, "sparse accessors are not supported")
        if "bufferView" not in acc:
            raise self.fail(field, "no bufferView (an all-zero accessor): not a splat attribute")
        dtype, width = COMPONENT_DTYPES[ctype], TYPE_WIDTHS[kind]
        view = self.item("bufferViews", acc["bufferView"], f"{field} bufferView")
        data = self._view_bytes(view, acc["bufferView"])
        offset = acc.get("byteOffset", 0)
        element = dtype.itemsize * width
        stride = view.get("byteStride", element)
        for name, value in (("byteOffset", offset), ("bufferView.byteStride", stride)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise self.fail(field, f"{name} {value!r} is not a non-negative integer")
        if stride < element or stride % dtype.itemsize or offset % dtype.itemsize:
            raise self.fail(field, f"byteStride {stride} / byteOffset {offset} do not fit elements of {element} bytes")
        needed = offset + (stride * (n - 1) + element if n else 0)
        if needed > len(data):
            raise self.fail(field, f"needs {needed} bytes of its bufferView, which has {len(data)}: truncated?")
        raw = np.ndarray((n, width), dtype=dtype, buffer=data, offset=offset, strides=(stride, dtype.itemsize))
        values = raw.astype(np.float64)
        if normalized:
            limit = float(np.iinfo(dtype).max)
            values = np.maximum(values / limit, -1.0)
        return values

    def _view_bytes(self, view: dict, index: int) -> memoryview:
        field = f"bufferViews[{index}]"
        buffer = view.get("buffer")
        if not isinstance(buffer, int) or isinstance(buffer, bool) or not 0 <= buffer < len(self.buffers):
            raise self.fail(field, f"buffer {buffer!r} is not one of the {len(self.buffers)} buffers")
        start, length = view.get("byteOffset", 0), view.get("byteLength")
        for name, value in (("byteOffset", start), ("byteLength", length)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise self.fail(field, f"{name} {value!r} is not a non-negative integer")
        data = self.buffers[buffer]
        if start + length > len(data):
            raise self.fail(field, f"bytes {start}..{start + length} lie beyond buffer {buffer} ({len(data)} bytes): "
                                   "truncated?")
        return memoryview(data)[start: start + length]


def _parse_glb(data: bytes, where: str) -> tuple[dict, bytes | None]:
    if len(data) < GLB_HEADER.size + CHUNK_HEADER.size:
        raise SplatFormatError(f"{where}: {TITLE}: {len(data)} bytes, shorter than a GLB header and its JSON chunk")
    magic, version, length = GLB_HEADER.unpack_from(data)
    if version != GLB_VERSION:
        raise SplatFormatError(f"{where}: {TITLE}: GLB version {version}, expected {GLB_VERSION}")
    if length != len(data):
        raise SplatFormatError(f"{where}: {TITLE}: the GLB header says {length} bytes, the file has {len(data)}"
                               f"{': truncated' if length > len(data) else ''}")
    chunks, at = [], GLB_HEADER.size
    while at < length:
        if at + CHUNK_HEADER.size > length:
            raise SplatFormatError(f"{where}: {TITLE}: a chunk header at byte {at} runs past the end of the file")
        size, kind = CHUNK_HEADER.unpack_from(data, at)
        start = at + CHUNK_HEADER.size
        if size % 4 or start + size > length:
            raise SplatFormatError(f"{where}: {TITLE}: chunk {len(chunks)} at byte {at} has length {size}: "
                                   f"{'not a multiple of 4' if size % 4 else 'past the end of the file'}")
        chunks.append((kind, data[start: start + size]))
        at = start + size
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise SplatFormatError(f"{where}: {TITLE}: the first GLB chunk is not JSON")
    binary = None
    if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN:
        binary = chunks[1][1]
    return _parse_json(chunks[0][1], where), binary


def _parse_json(text: bytes, where: str) -> dict:
    try:
        doc = json.loads(text.decode("utf-8-sig").rstrip(" \x00"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise SplatFormatError(f"{where}: {TITLE}: the JSON does not parse ({' '.join(str(exc).split())})") from None
    if not isinstance(doc, dict):
        raise SplatFormatError(f"{where}: {TITLE}: the JSON is a {type(doc).__name__}, expected an object")
    return doc


def _load_buffers(doc: dict, binary: bytes | None, base: Path | None, where: str) -> list[bytes]:
    buffers = doc.get("buffers", [])
    if not isinstance(buffers, list):
        raise SplatFormatError(f"{where}: {TITLE}: buffers: expected a JSON array")
    out = []
    for i, buffer in enumerate(buffers):
        field = f"{where}: {TITLE}: buffers[{i}]"
        if not isinstance(buffer, dict):
            raise SplatFormatError(f"{field}: expected a JSON object")
        length, uri = buffer.get("byteLength"), buffer.get("uri")
        if not isinstance(length, int) or isinstance(length, bool) or length < 0:
            raise SplatFormatError(f"{field}: byteLength {length!r} is not a non-negative integer")
        if uri is None:
            if i != 0 or binary is None:
                raise SplatFormatError(f"{field}: no uri, and {'not the first buffer' if i else 'no GLB BIN chunk'}")
            data = binary
        elif not isinstance(uri, str):
            raise SplatFormatError(f"{field}: uri is not a string")
        elif uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise SplatFormatError(f"{field}: a data URI that is not base64")
            try:
                data = base64.b64decode(payload, validate=True)
            except ValueError:
                raise SplatFormatError(f"{field}: the base64 data URI does not decode") from None
        else:
            data = _external_buffer(uri, base, field)
        if len(data) < length:
            raise SplatFormatError(f"{field}: {len(data)} bytes, byteLength says {length}: truncated?")
        out.append(bytes(data[:length]) if len(data) != length else data)
    return out


def _external_buffer(uri: str, base: Path | None, field: str) -> bytes:
    """A buffer in a file beside the .gltf: a relative path without a scheme, inside the .gltf's folder."""
    from urllib.parse import unquote

    if base is None or ":" in uri or uri.startswith(("/", "\\")):
        raise SplatFormatError(f"{field}: uri {uri[:80]!r} is not a file beside the .gltf (only relative paths and "
                               "data: URIs are read; nothing is fetched)")
    path = (base / unquote(uri)).resolve()
    if not path.is_relative_to(base.resolve()):
        raise SplatFormatError(f"{field}: uri {uri[:80]!r} points outside the .gltf's folder")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise SplatFormatError(f"{field}: cannot read {path} ({exc.strerror or exc})") from None


def _node_matrices(doc: _Document, mesh_index: int) -> list[np.ndarray]:
    """Global 4x4 matrices of the nodes that instantiate mesh ``mesh_index`` (identity when none does)."""
    nodes = doc.array("nodes")
    parent: dict[int, int] = {}
    for i, node in enumerate(nodes):
        if not isinstance(node, dict):
            raise doc.fail(f"nodes[{i}]", "expected a JSON object")
        for child in node.get("children", []) or []:
            if not isinstance(child, int) or not 0 <= child < len(nodes) or child in parent:
                raise doc.fail(f"nodes[{i}].children", f"{child!r} is not a node with one parent")
            parent[child] = i
    out = []
    for i, node in enumerate(nodes):
        if node.get("mesh") != mesh_index:
            continue
        matrix, at, seen = np.eye(4), i, set()
        while at is not None:
            if at in seen:
                raise doc.fail(f"nodes[{at}]", "the node hierarchy has a cycle")
            seen.add(at)
            matrix = _local_matrix(doc, nodes[at], at) @ matrix
            at = parent.get(at)
        out.append(matrix)
    return out or [np.eye(4)]


def _local_matrix(doc: _Document, node: dict, index: int) -> np.ndarray:
    def numbers(key, size, default):
        value = node.get(key, default)
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            array = np.empty(0)
        if array.shape != (size,) or not np.isfinite(array).all():
            raise doc.fail(f"nodes[{index}].{key}", f"expected {size} finite numbers")
        return array

    if "matrix" in node:
        return numbers("matrix", 16, None).reshape(4, 4).T  # column-major
    t = numbers("translation", 3, [0, 0, 0])
    x, y, z, w = numbers("rotation", 4, [0, 0, 0, 1])
    s = numbers("scale", 3, [1, 1, 1])
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    matrix = np.eye(4)
    matrix[:3, :3] = rot * s[None, :]
    matrix[:3, 3] = t
    return matrix


def _splat_primitives(doc: _Document) -> list[tuple[str, dict, int]]:
    found = []
    for m, mesh in enumerate(doc.array("meshes")):
        primitives = mesh.get("primitives", []) if isinstance(mesh, dict) else None
        if not isinstance(primitives, list):
            raise doc.fail(f"meshes[{m}].primitives", "expected a JSON array")
        for p, primitive in enumerate(primitives):
            if isinstance(primitive, dict) and EXTENSION in (primitive.get("extensions") or {}):
                found.append((f"meshes[{m}].primitives[{p}]", primitive, m))
    return found


def _check_primitive(doc: _Document, field: str, primitive: dict) -> dict:
    ext = primitive["extensions"][EXTENSION]
    if not isinstance(ext, dict):
        raise doc.fail(f"{field}.extensions.{EXTENSION}", "expected a JSON object")
    if primitive.get("mode", 4) != POINTS_MODE:
        raise doc.fail(f"{field}.mode", f"{primitive.get('mode', 4)!r}; the extension requires POINTS (0)")
    checks = (("kernel", KERNEL, "the only kernel the extension defines"),
              ("colorSpace", COLOR_SPACE, "lin_rec709_display would need the sRGB curve applied to an SH sum; "
                                          "the one read here"),
              ("projection", PROJECTION, "the only projection the extension defines"))
    for key, expected, why in checks:
        value = ext.get(key, PROJECTION if key == "projection" else None)
        if value != expected:
            raise doc.fail(f"{field}.extensions.{EXTENSION}.{key}", f"{value!r}, expected {expected!r} ({why})")
    nested = ext.get("extensions") or {}
    if not isinstance(nested, dict) or set(nested) - {SPZ_EXTENSION}:
        raise doc.fail(f"{field}.extensions.{EXTENSION}.extensions",
                       f"{', '.join(sorted(map(str, nested)))} not supported (read: the base extension and "
                       f"{SPZ_EXTENSION})")
    attributes = primitive.get("attributes")
    if not isinstance(attributes, dict):
        raise doc.fail(f"{field}.attributes", "expected a JSON object")
    spz = nested.get(SPZ_EXTENSION)
    if spz is not None and not isinstance(spz, dict):
        raise doc.fail(f"{field}.extensions.{EXTENSION}.extensions.{SPZ_EXTENSION}", "expected a JSON object")
    return attributes, spz


def _decode_spz_primitive(doc: _Document, field: str, attributes: dict, spz: dict) -> dict[str, np.ndarray]:
    """The attribute values (glTF frame) of a primitive compressed by ``SPZ_EXTENSION``: its buffer view holds an
    SPZ file (gzip-wrapped) storing glTF's coordinates as they are (``SPZ_BLOB_CORRECTION``)."""
    where = f"{field}.extensions.{EXTENSION}.extensions.{SPZ_EXTENSION}"
    view = spz.get("bufferView")
    blob = bytes(doc._view_bytes(doc.item("bufferViews", view, f"{where}.bufferView"), view))
    g = flipped(decode_spz(blob, f"{doc.where}: {where}"), SPZ_BLOB_CORRECTION)
    values = _file_frame_values(flipped(g, GLTF_FRAME))
    for semantic in ("POSITION", PREFIX + "SCALE", PREFIX + "ROTATION"):
        accessor = doc.item("accessors", attributes.get(semantic), f"{field}.attributes.{semantic}")
        if accessor.get("count") != len(g):
            raise doc.fail(f"{field}.attributes.{semantic}", f"count {accessor.get('count')!r} differs from the "
                                                             f"{len(g)} Gaussians of the SPZ data")
    values.update(_extra_values(doc, attributes, len(g)))
    return values


def _file_frame_values(g: Gaussians) -> dict[str, np.ndarray]:
    """``Gaussians`` (already in the file's frame) as the attribute values of the base extension."""
    return {"POSITION": g.means.astype(np.float64),
            PREFIX + "ROTATION": g.normalized_quats().astype(np.float64)[:, [1, 2, 3, 0]],
            PREFIX + "SCALE": np.exp(g.log_scales.astype(np.float64)),
            PREFIX + "OPACITY": unit_from_logit(g.opacity_logits)[:, None],
            "sh": g.sh.astype(np.float64)}


def flipped(g: Gaussians, frame: str) -> Gaussians:
    """``g`` under the axis flips that take the standard-family ``frame`` to RDF (and back: each is its own inverse):
    positions, quaternions and SH coefficients (``seggaussian.io.spz.frame_signs``); extras kept."""
    if frame == "RDF":
        return g
    position_signs, quat_signs, sh_signs = frame_signs(frame)
    sh = g.sh.copy()
    sh[:, 1:] *= sh_signs[: sh.shape[1] - 1, None]
    return Gaussians(g.means * position_signs, g.quats * quat_signs, g.log_scales, g.opacity_logits, sh, g.extras)


def _decode_primitive(doc: _Document, field: str, attributes: dict) -> dict[str, np.ndarray]:
    missing = [s for s in (*ATTRIBUTE_TYPES, attribute_name(0, 0)) if s not in attributes]
    if missing:
        raise doc.fail(f"{field}.attributes", f"missing {', '.join(missing)} (required by the extension)")
    position = doc.accessor(attributes["POSITION"], "POSITION", ATTRIBUTE_TYPES["POSITION"], None)
    n = position.shape[0]
    values = {"POSITION": position}
    for semantic in list(ATTRIBUTE_TYPES)[1:]:
        values[semantic] = doc.accessor(attributes[semantic], semantic, ATTRIBUTE_TYPES[semantic], n)
    degrees: dict[int, set[int]] = {}
    for semantic in attributes:
        match = _SH_SEMANTIC.match(semantic)
        if match:
            degrees.setdefault(int(match.group(1)), set()).add(int(match.group(2)))
        elif semantic.startswith(PREFIX) and semantic not in ATTRIBUTE_TYPES:
            raise doc.fail(f"{field}.attributes", f"{semantic} is not an attribute of the extension")
    degree = max(degrees)
    for d in range(degree + 1):
        if degrees.get(d) != set(range(2 * d + 1)):
            raise doc.fail(f"{field}.attributes", f"SH degree {d} is {'partly ' if d in degrees else 'not '}defined "
                                                  f"while degree {degree} is (each degree up to the highest must be "
                                                  "complete)")
    if degree > 3:
        raise doc.fail(f"{field}.attributes", f"SH degree {degree}: the extension defines degrees 0-3")
    sh = np.empty((n, (degree + 1) ** 2, 3), np.float64)
    for d in range(degree + 1):
        for c in range(2 * d + 1):
            semantic = attribute_name(d, c)
            sh[:, d * d + c] = doc.accessor(attributes[semantic], semantic, SH_TYPE, n)
    values["sh"] = sh
    values.update(_extra_values(doc, attributes, n))
    return values


def _extra_values(doc: _Document, attributes: dict, n: int) -> dict[str, np.ndarray]:
    """The ``_NAME`` attributes (our extras columns) as ``{"_name": [n]}``."""
    out = {}
    for semantic, accessor in attributes.items():
        if semantic.startswith("_"):
            column = semantic[1:].lower()
            if _EXTRA_NAME.match(column):
                out["_" + column] = doc.accessor(accessor, semantic, EXTRA_TYPE, n)[:, 0]
    return out


def _check_values(doc: _Document, field: str, values: dict) -> None:
    scale, opacity, rotation = (values[PREFIX + k] for k in ("SCALE", "OPACITY", "ROTATION"))
    bad = ~(np.isfinite(scale) & (scale >= 0)).all(axis=1)
    if bad.any():
        raise doc.fail(f"{field} {PREFIX}SCALE", f"{int(bad.sum())} Gaussians have a negative or non-finite scale "
                                                 f"(first: row {int(np.argmax(bad))}); scales are linear and >= 0")
    bad = ~((opacity >= 0) & (opacity <= 1)).all(axis=1)
    if bad.any():
        raise doc.fail(f"{field} {PREFIX}OPACITY", f"{int(bad.sum())} Gaussians have an opacity outside [0, 1] (first: "
                                                   f"row {int(np.argmax(bad))}); opacity is linear, not a logit")
    norm = np.linalg.norm(rotation, axis=1)
    bad = ~(np.abs(norm - 1.0) <= UNIT_TOLERANCE)
    if bad.any():
        first = int(np.argmax(bad))
        raise doc.fail(f"{field} {PREFIX}ROTATION", f"{int(bad.sum())} Gaussians have a rotation that is not a unit "
                                                    f"quaternion (first: row {first}, norm {norm[first]:.4g})")


def _transform(values: dict, matrix: np.ndarray) -> dict:
    """``values`` (glTF frame, local) moved by the node's global ``matrix`` (a similarity without reflection)."""
    from seggaussian.frames.similarity import Similarity, transform_gaussians

    if np.array_equal(matrix, np.eye(4)):
        return values
    sim = Similarity.from_matrix(matrix, source="its global transform")
    if sim.is_reflection:
        raise ValueError("its global transform is a reflection (negative determinant), which the extension leaves "
                         "undefined")
    moved = transform_gaussians(_gaussians_in_file_frame(values), sim)
    out = dict(values)
    out.update(_file_frame_values(moved))
    out[PREFIX + "OPACITY"] = values[PREFIX + "OPACITY"]
    return out


def _gaussians_in_file_frame(values: dict) -> Gaussians:
    """The attributes as ``Gaussians`` in the file's own frame (no frame change, opacity as a logit)."""
    rotation = values[PREFIX + "ROTATION"]
    with np.errstate(divide="ignore"):
        log_scales = np.log(values[PREFIX + "SCALE"])
    return Gaussians.from_arrays(values["POSITION"], rotation[:, [3, 0, 1, 2]], log_scales,
                                 logit_from_unit(values[PREFIX + "OPACITY"][:, 0]), values["sh"])


def decode_gltf(data: bytes, source: str | os.PathLike = "<bytes>", base: Path | None = None) -> GltfSplat:
    """The bytes of a ``.glb`` or ``.gltf`` -> ``GltfSplat`` (Gaussians in RDF, not validated); ``base`` is the
    folder relative buffer URIs are read from (``None``: only embedded buffers)."""
    where = str(source)
    if data.startswith(GLB_MAGIC):
        doc, binary = _parse_glb(data, where)
    else:
        doc, binary = _parse_json(data, where), None
    asset = doc.get("asset")
    version = asset.get("version") if isinstance(asset, dict) else None
    if not isinstance(version, str) or not re.fullmatch(r"2\.\d+", version):
        raise SplatFormatError(f"{where}: {TITLE}: asset.version {version!r}, expected glTF 2.x")
    required = doc.get("extensionsRequired", [])
    unknown = ([e for e in required if e not in (EXTENSION, SPZ_EXTENSION)] if isinstance(required, list)
               else [str(required)])
    if unknown:
        raise SplatFormatError(f"{where}: {TITLE}: extensionsRequired names {', '.join(map(str, unknown))}, "
                               "which this reader does not support")
    document = _Document(doc, _load_buffers(doc, binary, base, where), where)
    primitives = _splat_primitives(document)
    if not primitives:
        raise SplatFormatError(f"{where}: {TITLE}: no mesh primitive carries the {EXTENSION} extension: a glTF "
                               "file, but not a splat")
    parts, extras_names = [], None
    for field, primitive, mesh_index in primitives:
        attributes, spz = _check_primitive(document, field, primitive)
        if spz is None:
            values = _decode_primitive(document, field, attributes)
            _check_values(document, field, values)
        else:
            values = _decode_spz_primitive(document, field, attributes, spz)
        names = sorted(k for k in values if k.startswith("_"))
        if extras_names is not None and names != extras_names:
            raise document.fail(field, f"its extra attributes {names} differ from the first primitive's {extras_names}")
        extras_names = names
        for matrix in _node_matrices(document, mesh_index):
            try:
                parts.append(_transform(values, matrix))
            except ValueError as exc:
                raise document.fail(f"the node instantiating {field}", str(exc)) from None
    degrees = {p["sh"].shape[1] for p in parts}
    if len(degrees) > 1:
        raise SplatFormatError(f"{where}: {TITLE}: the splat primitives have different SH degrees")
    merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    g = flipped(_gaussians_in_file_frame(merged), GLTF_FRAME)  # LUF -> RDF
    extras = {}
    for key in extras_names or []:
        column = merged[key]
        integral = np.isfinite(column).all() and np.array_equal(column, np.round(column))
        extras[key[1:]] = column.astype(np.int32) if integral else column.astype(np.float32)
    gaussians = g.with_extras(**extras)
    legend = doc.get("extras", {}).get(EXTRAS_KEY, {}) if isinstance(doc.get("extras"), dict) else {}
    return GltfSplat(gaussians, legend if isinstance(legend, dict) else {})


def read_gltf(path: str | os.PathLike) -> GltfSplat:
    """Read a ``.glb`` / ``.gltf`` splat file -> ``GltfSplat`` (not validated); ``SplatFormatError`` when malformed."""
    path = Path(path)
    return decode_gltf(read_file_bytes(path, TITLE), path, base=path.parent)


# --- writing -------------------------------------------------------------------------------------------------------
def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function decoded (IEC 61966-2-1), ``c`` in [0, 1]."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _label_column(name: str, column: np.ndarray) -> tuple[np.ndarray, int]:
    """An extras column as (values, component type): integers as unsigned/signed short when they fit, else float."""
    if column.ndim != 1:
        raise ValueError(f"{TITLE}: extras column {name!r} has shape {column.shape}; only [N] columns are stored")
    if not _EXTRA_NAME.match(name):
        raise ValueError(f"{TITLE}: extras column {name!r} is not a lower-case name usable as a glTF attribute")
    if np.issubdtype(column.dtype, np.integer) or column.dtype == bool:
        lo, hi = (int(column.min()), int(column.max())) if column.size else (0, 0)
        if 0 <= lo and hi <= 0xFFFF:
            return column.astype("<u2"), USHORT
        if -0x8000 <= lo and hi <= 0x7FFF:
            return column.astype("<i2"), SHORT
        if -FLOAT_EXACT_INT <= lo and hi <= FLOAT_EXACT_INT:
            return column.astype("<f4"), FLOAT
        raise ValueError(f"{TITLE}: extras column {name!r} holds integers beyond +-2^24, which a glTF attribute "
                         "cannot hold exactly")
    values = column.astype("<f4")
    if not np.isfinite(values).all():
        raise ValueError(f"{TITLE}: extras column {name!r} holds NaN/Inf; validate (or repair) before writing")
    return values, FLOAT


def encode_gltf(gaussians: Gaussians, *, binary: bool = True, legend: Mapping | None = None,
                compression: str = "none") -> bytes:
    """``Gaussians`` (RDF) -> the bytes of a ``.glb`` (``binary``) or a ``.gltf`` with an embedded buffer;
    ``compression`` ``spz`` stores the splat as an SPZ blob (``SPZ_EXTENSION``), extras stay plain attributes."""
    if compression not in COMPRESSIONS:
        raise ValueError(f"{TITLE}: unknown compression {compression!r}, expected one of {', '.join(COMPRESSIONS)}")
    g = gaussians
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        if not np.isfinite(getattr(g, name)).all():
            raise ValueError(f"{TITLE}: Gaussians.{name} holds NaN/Inf; validate (or repair) before writing")
    n = len(g)
    stored = flipped(g, GLTF_FRAME)  # RDF -> LUF
    with np.errstate(over="ignore"):
        scales = np.exp(g.log_scales.astype(np.float64)).astype("<f4")
    if not np.isfinite(scales).all():
        raise ValueError(f"{TITLE}: a log-scale overflows float32 once exponentiated; validate (or repair) first")
    opacity = unit_from_logit(g.opacity_logits)
    rgb = np.clip(rgb_from_dc(g.sh[:, 0]), 0.0, 1.0)
    colour = np.empty((n, 4), np.uint8)
    colour[:, :3] = unorm_to_byte(_srgb_to_linear(rgb))
    colour[:, 3] = unorm_to_byte(opacity)
    means = stored.means.astype("<f4")
    sh = stored.sh
    # (semantic, values or None when the SPZ blob holds them, component type, type, normalized)
    columns: list[tuple[str, np.ndarray | None, int, str, bool]] = [
        ("POSITION", means, FLOAT, "VEC3", False),
        ("COLOR_0", colour, UBYTE, "VEC4", True),
        (PREFIX + "SCALE", scales, FLOAT, "VEC3", False),
        (PREFIX + "ROTATION", stored.normalized_quats()[:, [1, 2, 3, 0]].astype("<f4"), FLOAT, "VEC4", False),
    ]
    if compression == "none":
        columns.append((PREFIX + "OPACITY", opacity.astype("<f4"), FLOAT, "SCALAR", False))
    for d in range(0 if compression == "none" else 1, g.sh_degree + 1):
        for c in range(2 * d + 1):
            columns.append((attribute_name(d, c), sh[:, d * d + c].astype("<f4"), FLOAT, "VEC3", False))
    if compression == "spz":
        columns = [(semantic, None, *rest) for semantic, _, *rest in columns]
    for name in sorted(g.extras):
        values, ctype = _label_column(name, np.asarray(g.extras[name]))
        columns.append((extra_name(name), values, ctype, "SCALAR", False))

    blob, views, accessors, attributes = bytearray(), [], [], {}

    def add_view(data: bytes, target: int | None) -> int:
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        if target is not None:
            views[-1]["target"] = target
        blob.extend(data + b"\x00" * (-len(data) % 4))
        return len(views) - 1

    ext: dict = {"kernel": KERNEL, "colorSpace": COLOR_SPACE, "projection": PROJECTION, "sortingMethod": SORTING}
    if compression == "spz":
        ext["extensions"] = {SPZ_EXTENSION: {"bufferView": add_view(
            encode_spz(flipped(g, SPZ_BLOB_CORRECTION), version=SPZ_BLOB_VERSION), None)}}
    for semantic, values, ctype, kind, normalized in columns:
        accessor = {"componentType": ctype, "count": n, "type": kind}
        if values is not None:
            accessor = {"bufferView": add_view(np.ascontiguousarray(values).tobytes(), ARRAY_BUFFER), **accessor}
        if normalized:
            accessor["normalized"] = True
        if semantic == "POSITION":
            accessor["min"] = means.min(axis=0).tolist() if n else [0.0, 0.0, 0.0]
            accessor["max"] = means.max(axis=0).tolist() if n else [0.0, 0.0, 0.0]
        accessors.append(accessor)
        attributes[semantic] = len(accessors) - 1
    buffer = {"byteLength": len(blob)}
    if not binary:
        buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode("ascii")
    used = [EXTENSION] + ([SPZ_EXTENSION] if compression == "spz" else [])
    doc = {"asset": {"version": "2.0", "generator": "seggaussian"}, "extensionsUsed": used}
    if compression == "spz":  # no attribute data outside the blob: no fallback without the extension
        doc["extensionsRequired"] = used
    doc.update({
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "mode": POINTS_MODE, "extensions": {EXTENSION: ext}}]}],
        "buffers": [buffer],
        "bufferViews": views,
        "accessors": accessors,
    })
    if legend:
        doc["extras"] = {EXTRAS_KEY: dict(legend)}
    text = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if not binary:
        return text
    text += b" " * (-len(text) % 4)
    total = GLB_HEADER.size + 2 * CHUNK_HEADER.size + len(text) + len(blob)
    return b"".join([GLB_HEADER.pack(GLB_MAGIC, GLB_VERSION, total), CHUNK_HEADER.pack(len(text), CHUNK_JSON), text,
                     CHUNK_HEADER.pack(len(blob), CHUNK_BIN), bytes(blob)])


def write_gltf(path: str | os.PathLike, gaussians: Gaussians, *, binary: bool | None = None,
               legend: Mapping | None = None, compression: str = "none") -> None:
    """Write ``gaussians`` (RDF) atomically as a ``.glb`` (``binary``; default: unless the name ends in ``.gltf``),
    ``compression`` as in ``encode_gltf``."""
    if binary is None:
        binary = not str(path).lower().endswith(".gltf")
    write_atomic(path, [encode_gltf(gaussians, binary=binary, legend=legend, compression=compression)])
