"""Shared helpers of the source readers and writers: errors, checked file reading, atomic writes.

Readers never write into the raw tree; writers (the synthetic generator, render caches) write every
file to a temporary name in the same folder and then ``os.replace`` it, so no half-written file
is ever visible.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from seggaussian.util.atomic import write_bytes_atomic


class SourceError(ValueError):
    """A raw scene file is missing or malformed. The message names the file and the field."""

    def __init__(self, path: Path | str, field: str | None, problem: str):
        self.path = Path(path)
        self.field = field
        where = f"{self.path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {problem}")


class EmptySceneError(SourceError):
    """The scene has no labelled vertex (after mapping and masking): skip it and count it."""


# ---------------------------------------------------------------------------------------------
# reading


def require_file(path: Path, what: str) -> Path:
    """``path`` if it is a file, else a SourceError saying what was expected there."""
    if not path.is_file():
        raise SourceError(path, None, f"missing ({what})")
    return path


def read_json(path: Path, what: str):
    """Parse a JSON file; a missing or corrupt file is a SourceError naming it."""
    require_file(path, what)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SourceError(path, None, f"corrupt JSON ({what}): {err}") from None


def json_field(data, path: Path, key: str, kind: type | tuple[type, ...]):
    """``data[key]`` checked to be of ``kind``; otherwise a SourceError naming file and field."""
    if not isinstance(data, dict):
        raise SourceError(path, None, f"expected a JSON object at the top level, got {type(data).__name__}")
    if key not in data:
        raise SourceError(path, key, "field missing")
    value = data[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        names = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        raise SourceError(path, key, f"expected {names}, got {type(value).__name__}")
    return value


def finite_number(value, path: Path, field: str) -> float:
    """A finite float from a JSON/text value, else a SourceError naming the field."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SourceError(path, field, f"expected a number, got {value!r}") from None
    if not np.isfinite(number):
        raise SourceError(path, field, f"not finite ({value!r})")
    return number


def read_mesh_ply(path: Path, *, face_properties: tuple[str, ...] = ()) -> dict:
    """Vertices, colours and polygon faces of a mesh PLY (binary or ASCII).

    Returns a dict with ``points`` ``[P,3]`` float64, ``colors`` ``[P,3]`` uint8 (grey when the file
    has none), ``faces`` list-like ``[F, n]`` int64 (n = 3 or 4; None without faces), and every
    requested face property as an array ``[F]``.
    """
    from plyfile import PlyData, PlyParseError

    require_file(path, "mesh PLY")
    ply = None
    for list_len in (3, 4):  # fast memory-mapped read when every face has the same size
        try:
            ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": list_len}})
            break
        except (PlyParseError, ValueError, EOFError, OSError, IndexError):
            continue
    if ply is None:
        try:
            ply = PlyData.read(str(path))
        except (PlyParseError, ValueError, EOFError, OSError, IndexError) as err:
            raise SourceError(path, None, f"unreadable PLY: {err}") from None
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise SourceError(path, "vertex", "element missing")
    vertex = ply["vertex"].data
    fields = vertex.dtype.names or ()
    for axis in ("x", "y", "z"):
        if axis not in fields:
            raise SourceError(path, f"vertex.{axis}", "property missing")
    points = np.stack([np.array(vertex[a], dtype=np.float64) for a in ("x", "y", "z")], axis=1)
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise SourceError(path, "vertex.x/y/z", f"{bad} vertices hold NaN/Inf")
    if all(c in fields for c in ("red", "green", "blue")):
        colors = np.stack([np.asarray(vertex[c]) for c in ("red", "green", "blue")], axis=1)
        if colors.dtype.kind == "f":  # some writers store colours as floats in [0, 1]
            colors = np.clip(np.round(colors * 255.0), 0, 255)
        colors = colors.astype(np.uint8)
    else:
        colors = np.full((len(points), 3), 128, dtype=np.uint8)
    out = {"points": points, "colors": colors, "faces": None}
    if "face" in names:
        face = ply["face"].data
        ffields = face.dtype.names or ()
        key = "vertex_indices" if "vertex_indices" in ffields else ("vertex_index" if "vertex_index" in ffields else None)
        if key is None:
            raise SourceError(path, "face.vertex_indices", "property missing")
        polys = face[key]
        if len(polys) == 0:
            out["faces"] = np.zeros((0, 3), dtype=np.int64)
        elif isinstance(polys, np.ndarray) and polys.ndim == 2 and polys.dtype != object:
            faces = np.array(polys, dtype=np.int64)
            if faces.shape[1] not in (3, 4):
                raise SourceError(path, f"face.{key}", f"expected triangles or quads, got {faces.shape[1]} vertices per face")
            if faces.size and (faces.min() < 0 or faces.max() >= len(points)):
                raise SourceError(path, f"face.{key}", f"index out of range [0, {len(points)})")
            out["faces"] = faces
        else:
            lengths = np.fromiter((len(p) for p in polys), dtype=np.int64, count=len(polys))
            if lengths.min() != lengths.max() or lengths[0] not in (3, 4):
                raise SourceError(path, f"face.{key}", f"expected all triangles or all quads, got sizes {sorted(set(lengths.tolist()))}")
            faces = np.stack([np.asarray(p, dtype=np.int64) for p in polys]) if len(polys) else np.zeros((0, 3), np.int64)
            if faces.size and (faces.min() < 0 or faces.max() >= len(points)):
                raise SourceError(path, f"face.{key}", f"index out of range [0, {len(points)})")
            out["faces"] = faces
        for prop in face_properties:
            if prop not in ffields:
                raise SourceError(path, f"face.{prop}", "property missing")
            out[prop] = np.array(face[prop])
    elif face_properties:
        raise SourceError(path, "face", "element missing")
    return out


def triangulate_quads(quads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quads ``[F,4]`` -> (triangles ``[T,3]``, source face index ``[T]``); fan split (a,b,c)+(a,c,d).

    Degenerate triangles (a repeated vertex index, e.g. from a collapsed quad) are dropped; the
    caller counts them as ``len(quads) * 2 - len(triangles)``.
    """
    quads = np.asarray(quads, dtype=np.int64)
    if quads.shape[1] == 3:
        return quads, np.arange(len(quads), dtype=np.int64)
    tris = np.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], axis=1).reshape(-1, 3)
    src = np.repeat(np.arange(len(quads), dtype=np.int64), 2)
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
    return tris[keep], src[keep]


# ---------------------------------------------------------------------------------------------
# writing (generator and caches only, never the raw tree of a reader)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``."""
    write_bytes_atomic(path, data)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: Path, payload, *, indent: int | None = 1) -> None:
    atomic_write_text(path, json.dumps(payload, indent=indent, allow_nan=False) + "\n")


def encode_image(image: np.ndarray, ext: str) -> bytes:
    """PNG/JPEG bytes of an RGB uint8 ``[H,W,3]`` or label uint16 ``[H,W]`` image (deterministic)."""
    import cv2

    if image.ndim == 3:
        image = image[:, :, ::-1]  # RGB -> BGR for OpenCV
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if ext.lower() in (".jpg", ".jpeg") else [cv2.IMWRITE_PNG_COMPRESSION, 3]
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(image), params)
    if not ok:
        raise OSError(f"could not encode a {image.shape} {image.dtype} image as {ext}")
    return buf.tobytes()


def atomic_write_image(path: Path, image: np.ndarray) -> None:
    atomic_write_bytes(path, encode_image(image, Path(path).suffix))


def read_image(path: Path, what: str, *, unchanged: bool = False) -> np.ndarray:
    """RGB uint8 ``[H,W,3]`` (or the raw array with ``unchanged``, e.g. uint16 labels)."""
    import cv2

    require_file(path, what)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED if unchanged else cv2.IMREAD_COLOR)
    if image is None:
        raise SourceError(path, None, f"unreadable image ({what})")
    if not unchanged:
        image = image[:, :, ::-1].copy()
    return image


#: Value of a valid (not anonymized) pixel in a ScanNet++ anonymization mask; the toolkit writes
#: 255 = valid, 0 = anonymized, and sets every value below 255 to 0 after resizing/undistorting.
MASK_VALID_VALUE = 255
#: A mask of another size than its view must scale width and height alike, up to this relative
#: difference (rounding of odd sizes when the toolkit or the build resizes).
MASK_ASPECT_TOL = 0.02


def read_valid_mask(path: Path, width: int, height: int) -> np.ndarray:
    """``[height, width]`` bool: True where the pixel is valid, False where an anonymization mask marks it.

    ``path`` is an 8-bit mask image (``MASK_VALID_VALUE`` = valid). A mask of another size than the
    wanted one (a resized view) is resampled conservatively: an output pixel is valid only if every
    mask pixel it covers is valid (area resampling of the anonymized share, any share > 0 is anonymized).
    """
    import cv2

    mask = read_image(path, "anonymization mask", unchanged=True)
    if mask.ndim == 3:
        mask = mask[:, :, 0]
    anonymized = (mask != MASK_VALID_VALUE).astype(np.float32)
    if anonymized.shape != (height, width):
        src_h, src_w = anonymized.shape
        if abs(src_w / width - src_h / height) > MASK_ASPECT_TOL * max(src_w / width, src_h / height):
            raise SourceError(path, None, f"mask is {src_w}x{src_h}, not a resize of the {width}x{height} view")
        anonymized = cv2.resize(anonymized, (width, height), interpolation=cv2.INTER_AREA)
    return anonymized <= 0.0


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    from PIL import Image, UnidentifiedImageError

    require_file(path, what)
    try:
        with Image.open(path) as image:
            return image.size
    except (UnidentifiedImageError, OSError) as err:
        raise SourceError(path, None, f"unreadable image ({what}): {err}") from None


_PLY_TYPES = {"f4": "float", "f8": "double", "u1": "uchar", "i1": "char", "u2": "ushort", "i2": "short", "u4": "uint", "i4": "int"}


def encode_mesh_ply(vertex: np.ndarray, faces: np.ndarray, face_fields: dict[str, np.ndarray] | None = None) -> bytes:
    """Binary little-endian PLY bytes of a mesh.

    ``vertex``: structured array (little-endian scalar fields, written in order); ``faces``:
    ``[F, n]`` int vertex indices written as ``list uchar int vertex_indices``; ``face_fields``:
    extra per-face int32 properties (e.g. Replica's ``object_id``). Same bytes as plyfile writes,
    without its per-row Python loop.
    """
    face_fields = face_fields or {}
    faces = np.asarray(faces)
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertex)}"]
    for name in vertex.dtype.names:
        lines.append(f"property {_PLY_TYPES[vertex.dtype[name].str[1:]]} {name}")
    lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines += [f"property int {name}" for name in face_fields]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    record = np.dtype([("n", "u1"), ("v", "<i4", (faces.shape[1],))] + [(name, "<i4") for name in face_fields])
    face = np.empty(len(faces), dtype=record)
    face["n"] = faces.shape[1]
    face["v"] = faces
    for name, values in face_fields.items():
        face[name] = values
    return header + vertex.astype(vertex.dtype.newbyteorder("<")).tobytes() + face.tobytes()
