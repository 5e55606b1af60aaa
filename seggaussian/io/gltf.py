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

Checked on reading (one-line ``SplatFormatError``s naming the file and field; the container by ``gltf_container``):
``asset.version`` 2.x, ``extensionsRequired``, mode ``POINTS``, kernel ``ellipse`` (the pre-ratification draft's
``_SCALE``/``_ROTATION`` without a kernel are refused as such), colour space, projection ``perspective``, each
accessor's type and component type, SH degrees complete without gaps, scales finite and >= 0, opacities in [0, 1],
unit rotations (within ``UNIT_TOLERANCE``). Several splat primitives are read as one scene.

Writing: a GLB (``.glb``) or a ``.gltf`` whose one buffer is embedded as a base64 ``data:`` URI; one scene, one node
(no transform), one mesh, one primitive, float attributes in one buffer view each (4-byte aligned), ``POSITION``
with its ``min``/``max``; ``KHR_gaussian_splatting`` in ``extensionsUsed`` (not required: a viewer without it draws
the points in their ``COLOR_0``). ``legend`` (class names and colours) goes in the root ``extras.seggaussian``.

Compression: ``compression="spz"`` writes ``KHR_gaussian_splatting_compression_spz_2`` (a draft by the same authors,
the only form CesiumJS 1.145 draws as splats): accessors without buffer views, an SPZ version-2 file in one buffer
view, ``COLOR_0``, ``SCALE``, ``ROTATION`` and the SH degrees above 0 named as in the draft's example, both extensions
required; our ``_`` attributes stay plain. It is read as well. The blob holds glTF's coordinates as they are
(``SPZ_BLOB_CORRECTION``).
"""

from __future__ import annotations

import base64
import json
import os
import re
from pathlib import Path
from typing import Mapping, NamedTuple

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.frames.similarity import Similarity, transform_gaussians
from seggaussian.io.gltf_container import (ARRAY_BUFFER, BYTE, FLOAT, GLB_MAGIC, SHORT, UBYTE, USHORT, GltfDocument,
                                           load_buffers, looks_like_gltf, node_matrices, pack_glb, parse_glb,
                                           parse_json)
from seggaussian.io.ply.writer import write_atomic
from seggaussian.io.splat_common import (SplatFormatError, logit_from_unit, read_file_bytes, require_finite,
                                         rgb_from_dc, unit_from_logit, unorm_to_byte)
from seggaussian.io.spz import decode_spz, encode_spz, frame_signs

__all__ = ["GLB_MAGIC", "EXTENSION", "SPZ_EXTENSION", "COMPRESSIONS", "GLTF_FRAME", "GltfSplat", "looks_like_gltf",
           "decode_gltf", "read_gltf", "encode_gltf", "write_gltf", "attribute_name", "extra_name", "flipped"]

TITLE = "glTF (KHR_gaussian_splatting)"
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
#: our files so: correlation 0.9995 with our rasterizer, 0.47 when the blob is written in RUB). Our SPZ writer stores
#: RUB from RDF and our reader undoes it, so the Gaussians (RDF) are turned by the flips taking LUF to RUB (``LDB``:
#: x and z negated) before writing the blob and after reading it. (The draft's text asks for "LUF" in Niantic's
#: pack/unpack options, which would store RUB; the renderer of its authors decides.)
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


def _splat_primitives(doc: GltfDocument) -> list[tuple[str, dict, int]]:
    found = []
    for m, mesh in enumerate(doc.array("meshes")):
        primitives = mesh.get("primitives", []) if isinstance(mesh, dict) else None
        if not isinstance(primitives, list):
            raise doc.fail(f"meshes[{m}].primitives", "expected a JSON array")
        for p, primitive in enumerate(primitives):
            if isinstance(primitive, dict) and EXTENSION in (primitive.get("extensions") or {}):
                found.append((f"meshes[{m}].primitives[{p}]", primitive, m))
    return found


def _check_primitive(doc: GltfDocument, field: str, primitive: dict) -> tuple[dict, dict | None]:
    """The primitive's attributes and its SPZ compression object (None without), once its extension is checked."""
    ext = primitive["extensions"][EXTENSION]
    if not isinstance(ext, dict):
        raise doc.fail(f"{field}.extensions.{EXTENSION}", "expected a JSON object")
    if primitive.get("mode", 4) != POINTS_MODE:
        raise doc.fail(f"{field}.mode", f"{primitive.get('mode', 4)!r}; the extension requires POINTS (0)")
    attributes = primitive.get("attributes")
    if not isinstance(attributes, dict):
        raise doc.fail(f"{field}.attributes", "expected a JSON object")
    if "kernel" not in ext and {"_SCALE", "_ROTATION"} & set(attributes):  # as in CesiumJS's older test tiles
        raise doc.fail(f"{field}.attributes", f"_SCALE/_ROTATION without a kernel: the extension's pre-ratification "
                                              f"draft, not read (the ratified one names them {PREFIX}SCALE, "
                                              f"{PREFIX}ROTATION)")
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
    spz = nested.get(SPZ_EXTENSION)
    if spz is not None and not isinstance(spz, dict):
        raise doc.fail(f"{field}.extensions.{EXTENSION}.extensions.{SPZ_EXTENSION}", "expected a JSON object")
    return attributes, spz


def _decode_spz_primitive(doc: GltfDocument, field: str, attributes: dict, spz: dict) -> dict[str, np.ndarray]:
    """The attribute values (glTF frame) of a primitive compressed by ``SPZ_EXTENSION``: its buffer view holds an
    SPZ file (gzip-wrapped) storing glTF's coordinates as they are (``SPZ_BLOB_CORRECTION``)."""
    where = f"{field}.extensions.{EXTENSION}.extensions.{SPZ_EXTENSION}"
    view = spz.get("bufferView")
    blob = bytes(doc.view_bytes(doc.item("bufferViews", view, f"{where}.bufferView"), view))
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


def _decode_primitive(doc: GltfDocument, field: str, attributes: dict) -> dict[str, np.ndarray]:
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


def _extra_values(doc: GltfDocument, attributes: dict, n: int) -> dict[str, np.ndarray]:
    """The ``_NAME`` attributes (our extras columns) as ``{"_name": [n]}``."""
    out = {}
    for semantic, accessor in attributes.items():
        if semantic.startswith("_"):
            column = semantic[1:].lower()
            if _EXTRA_NAME.match(column):
                out["_" + column] = doc.accessor(accessor, semantic, EXTRA_TYPE, n)[:, 0]
    return out


def _check_values(doc: GltfDocument, field: str, values: dict) -> None:
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
    if np.array_equal(matrix, np.eye(4)):
        return values
    sim = Similarity.from_matrix(matrix, source="its global transform")
    if sim.is_reflection:
        raise ValueError("its global transform is a reflection (negative determinant), which the extension leaves "
                         "undefined")
    moved = _file_frame_values(transform_gaussians(_gaussians_in_file_frame(values), sim))
    return {**values, **moved, PREFIX + "OPACITY": values[PREFIX + "OPACITY"]}


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
        doc, binary = parse_glb(data, where)
    else:
        doc, binary = parse_json(data, where), None
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
    document = GltfDocument(doc, load_buffers(doc, binary, base, where), where)
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
        for matrix in node_matrices(document, mesh_index):
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
        integral = (np.isfinite(column).all() and np.array_equal(column, np.round(column))
                    and np.abs(column).max(initial=0) < 2 ** 31)
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
    require_finite(g, TITLE)
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
    return pack_glb(text, bytes(blob))


def write_gltf(path: str | os.PathLike, gaussians: Gaussians, *, binary: bool | None = None,
               legend: Mapping | None = None, compression: str = "none") -> None:
    """Write ``gaussians`` (RDF) atomically as a ``.glb`` (``binary``; default: unless the name ends in ``.gltf``),
    ``compression`` as in ``encode_gltf``."""
    if binary is None:
        binary = not str(path).lower().endswith(".gltf")
    write_atomic(path, [encode_gltf(gaussians, binary=binary, legend=legend, compression=compression)])
