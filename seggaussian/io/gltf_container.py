"""The glTF 2.0 container, as far as a splat reader needs it: the GLB header and chunks, the JSON, buffers (the GLB's
BIN chunk, base64 ``data:`` URIs, files beside a ``.gltf``: nothing is fetched), accessors (every component type,
``normalized``, ``byteStride``; sparse accessors refused), node matrices. Every problem is a one-line
``SplatFormatError`` naming the file and the field (glTF 2.0 specification: "Binary glTF Layout", "Accessors",
"Buffers and Buffer Views", "Transformations")."""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from seggaussian.core.rotations import quats_to_rotmats
from seggaussian.io.splat_common import SplatFormatError

__all__ = ["GLB_MAGIC", "GltfDocument", "looks_like_gltf", "parse_glb", "parse_json", "load_buffers", "node_matrices",
           "pack_glb", "COMPONENT_DTYPES", "TYPE_WIDTHS", "BYTE", "UBYTE", "SHORT", "USHORT", "UINT", "FLOAT",
           "ARRAY_BUFFER"]

TITLE = "glTF"
GLB_MAGIC = b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
GLB_HEADER = struct.Struct("<4sII")
CHUNK_HEADER = struct.Struct("<II")
BYTE, UBYTE, SHORT, USHORT, UINT, FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
#: ``bufferView.target`` of vertex attributes.
ARRAY_BUFFER = 34962
COMPONENT_DTYPES = {BYTE: np.dtype("<i1"), UBYTE: np.dtype("<u1"), SHORT: np.dtype("<i2"), USHORT: np.dtype("<u2"),
                    UINT: np.dtype("<u4"), FLOAT: np.dtype("<f4")}
TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def looks_like_gltf(head: bytes) -> bool:
    """``head`` starts a GLB (``glTF`` magic) or a glTF JSON document (an object naming ``asset``)."""
    if head.startswith(GLB_MAGIC):
        return True
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    return text.startswith(b"{") and b'"asset"' in head


class GltfDocument:
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
        """Accessor ``index``'s values for ``semantic``: ``[count, width]`` float64, normalized integers scaled."""
        field = f"attribute {semantic} (accessor {index})"
        acc = self.item("accessors", index, field)
        kind, components = allowed
        ctype, normalized = acc.get("componentType"), acc.get("normalized", False)
        if acc.get("type") != kind:
            raise self.fail(field, f"type {acc.get('type')!r}, expected {kind!r}")
        if not isinstance(normalized, bool):
            raise self.fail(field, f"normalized {normalized!r} is not true or false")
        if not isinstance(ctype, int) or isinstance(ctype, bool) or ctype not in components:
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
        data = self.view_bytes(view, acc["bufferView"])
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
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite values are reported by the checks after
            values = raw.astype(np.float64)
        if normalized:
            limit = float(np.iinfo(dtype).max)
            values = np.maximum(values / limit, -1.0)
        return values

    def view_bytes(self, view: dict, index: int) -> memoryview:
        """The bytes of buffer view ``index`` (``view``), checked to lie inside its buffer."""
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


def parse_glb(data: bytes, where: str) -> tuple[dict, bytes | None]:
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
    return parse_json(chunks[0][1], where), binary


def parse_json(text: bytes, where: str) -> dict:
    try:
        doc = json.loads(text.decode("utf-8-sig").rstrip(" \x00"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise SplatFormatError(f"{where}: {TITLE}: the JSON does not parse ({' '.join(str(exc).split())})") from None
    if not isinstance(doc, dict):
        raise SplatFormatError(f"{where}: {TITLE}: the JSON is a {type(doc).__name__}, expected an object")
    return doc


def load_buffers(doc: dict, binary: bytes | None, base: Path | None, where: str) -> list[bytes]:
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
            data = external_buffer(uri, base, field)
        if len(data) < length:
            raise SplatFormatError(f"{field}: {len(data)} bytes, byteLength says {length}: truncated?")
        out.append(bytes(data[:length]) if len(data) != length else data)
    return out


def external_buffer(uri: str, base: Path | None, field: str) -> bytes:
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


def node_matrices(doc: GltfDocument, mesh_index: int) -> list[np.ndarray]:
    """Global 4x4 matrices of the nodes that instantiate mesh ``mesh_index`` (identity when none does)."""
    nodes = doc.array("nodes")
    parent: dict[int, int] = {}
    for i, node in enumerate(nodes):
        if not isinstance(node, dict):
            raise doc.fail(f"nodes[{i}]", "expected a JSON object")
        children = node.get("children", [])
        if not isinstance(children, list):
            raise doc.fail(f"nodes[{i}].children", f"{children!r} is not a JSON array")
        for child in children:
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
            matrix = local_matrix(doc, nodes[at], at) @ matrix
            at = parent.get(at)
        out.append(matrix)
    return out or [np.eye(4)]


def local_matrix(doc: GltfDocument, node: dict, index: int) -> np.ndarray:
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
    rot = quats_to_rotmats(np.array([[w, x, y, z]]))[0]  # glTF's x, y, z, w in ours (w first)
    matrix = np.eye(4)
    matrix[:3, :3] = rot * s[None, :]
    matrix[:3, 3] = t
    return matrix



def pack_glb(text: bytes, blob: bytes) -> bytes:
    """A GLB of the JSON ``text`` and the binary ``blob`` (each chunk padded to 4 bytes: spaces, zeros)."""
    text += b" " * (-len(text) % 4)
    blob += b"\x00" * (-len(blob) % 4)
    total = GLB_HEADER.size + 2 * CHUNK_HEADER.size + len(text) + len(blob)
    return b"".join([GLB_HEADER.pack(GLB_MAGIC, GLB_VERSION, total), CHUNK_HEADER.pack(len(text), CHUNK_JSON), text,
                     CHUNK_HEADER.pack(len(blob), CHUNK_BIN), blob])
