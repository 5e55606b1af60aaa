"""3D Gaussian Splatting PLY files (the Inria ``save_ply`` layout): read, validate, write.

Layout of the ``vertex`` element, in this order when we write it::

    x, y, z, [nx, ny, nz], f_dc_0..2, f_rest_0..M-1, opacity, scale_0..2, rot_0..3, [extras...]

* SH degree d in 0..3 is inferred from M = 3 * ((d + 1)^2 - 1) (0, 9, 24 or 45); any other M is an error.
* ``f_rest`` is channel-major: the (num_sh_coeffs - 1) higher-order coefficients of R, then of G, then of B.
  In memory ``Gaussians.sh`` is ``[N, num_sh_coeffs, 3]`` with ``sh[:, 0] = f_dc`` and
  ``sh[:, k, c] = f_rest[c * (num_sh_coeffs - 1) + k - 1]`` for k >= 1.
* Normals (always zero in Inria files) are optional. On read, all-zero normals are dropped; normals
  holding any non-zero value are kept as extras ``nx, ny, nz`` and written back in the normal slot.
* Any other scalar vertex property becomes ``Gaussians.extras[name]`` with its file dtype
  (``semantic`` and ``instance`` are returned as int32). Consecutive properties ``base_0 .. base_{k-1}``
  (k >= 2, same type) become one ``[N, k]`` extra ``base``; a 2D extra is written back that way.
* Standard properties stored with another numeric type (``double``, ``uchar``, ...) are converted to
  float32, the type of ``Gaussians``; extras keep their type.
* Binary little/big endian and ASCII are read and written. Our own files re-written with the same
  options are byte-identical; foreign files are value-identical (same properties, same values).

Binary bodies are decoded with one ``np.fromfile`` into a structured dtype (no per-row Python);
``read_vertex_table_plyfile`` is the slow, obviously-correct reference built on ``plyfile``.
"""

from __future__ import annotations

import errno
import os
import re
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from seggaussian.util.atomic import atomic_path
from seggaussian.core.gaussians import Gaussians, sh_degree_from_coeffs
from seggaussian.io.validate import InvalidGaussiansError, validate_gaussians

__all__ = [
    "PlyFormatError",
    "PlyProperty",
    "PlyElement",
    "PlyHeader",
    "read_ply_header",
    "read_vertex_table",
    "read_vertex_table_plyfile",
    "vertex_table_to_gaussians",
    "gaussians_to_vertex_table",
    "read_gaussians_ply",
    "write_gaussians_ply",
    "write_vertex_table",
    "ply_property_names",
]

PlyFormat = Literal["ascii", "binary_little_endian", "binary_big_endian"]

#: PLY scalar type names (both spellings of the spec) -> numpy type code without byte order.
PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
#: numpy type code -> the PLY type name we write (the names of the Inria files and of plyfile).
PLY_TYPE_NAMES: dict[str, str] = {
    "i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort",
    "i4": "int", "u4": "uint", "f4": "float", "f8": "double",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_BYTE_ORDER = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}
#: A header longer than this is not a 3DGS header (protects against reading a huge non-PLY file).
MAX_HEADER_BYTES = 1 << 20
#: Extras always written as int32 PLY ``int`` properties so that viewers and our tools read them back.
LABEL_EXTRAS = ("semantic", "instance")
_NORMALS = ("nx", "ny", "nz")
#: ``f_rest_<i>`` spelled exactly as the layout writes it (no sign, no leading zero): ``f_rest_05`` is an
#: extra column, not coefficient 5.
_F_REST = re.compile(r"f_rest_(0|[1-9][0-9]*)$")
_INDEXED = re.compile(r"(.+)_(\d+)$")


class PlyFormatError(ValueError):
    """A PLY file that cannot be read as 3DGS Gaussians; the message names the file and the problem."""


class PlyProperty(NamedTuple):
    """One property of a PLY element."""

    name: str
    #: numpy type code without byte order (``f4``, ``u1``, ...).
    dtype: str
    #: True for ``property list ...`` (unsupported in the vertex element of a 3DGS file).
    is_list: bool = False
    #: numpy type code of a list's length prefix (``u1``, ...); empty for a scalar property.
    count_dtype: str = ""


class PlyElement(NamedTuple):
    """One element declared in a PLY header."""

    name: str
    count: int
    properties: tuple[PlyProperty, ...]


class PlyHeader(NamedTuple):
    """A parsed PLY header."""

    path: Path
    #: ``ascii``, ``binary_little_endian`` or ``binary_big_endian``.
    format: str
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    #: Byte offset of the first body byte (just after ``end_header`` and its newline).
    body_offset: int
    #: Size of the whole file in bytes.
    file_size: int

    def element(self, name: str) -> PlyElement:
        for element in self.elements:
            if element.name == name:
                return element
        raise PlyFormatError(f"{self.path}: no '{name}' element in the header")

    @property
    def byte_order(self) -> str:
        """``<``, ``>`` or ``=`` (ASCII)."""
        return _BYTE_ORDER[self.format]


# --------------------------------------------------------------------------------------------
# header
# --------------------------------------------------------------------------------------------
def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Parse the header of a PLY file; ``PlyFormatError`` naming the file and the problem otherwise."""
    path = Path(path)
    try:
        file_size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise PlyFormatError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    if file_size == 0:
        raise PlyFormatError(f"{path}: empty file (0 bytes), not a PLY file")
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        first = head[:16].split(b"\n")[0]
        raise PlyFormatError(f"{path}: not a PLY file (it starts with {first!r}, expected 'ply')")
    match = re.search(rb"(?:^|\n)end_header[ \t]*\r?\n", head)
    if match is None:
        if len(head) >= MAX_HEADER_BYTES:
            raise PlyFormatError(f"{path}: no 'end_header' line in the first {MAX_HEADER_BYTES} bytes")
        raise PlyFormatError(f"{path}: truncated header (no 'end_header' line)")
    try:
        text = head[: match.start()].decode("ascii")
    except UnicodeDecodeError:
        raise PlyFormatError(f"{path}: the header is not ASCII text") from None

    if text.endswith("\n"):
        raise PlyFormatError(f"{path}: blank line before 'end_header'")
    fmt = None
    comments: list[str] = []
    elements: list[list] = []  # [name, count, [properties]]
    for lineno, raw in enumerate(text.splitlines()[1:], start=2):
        words = raw.split()
        where = f"{path}: header line {lineno} ({raw.strip()!r})"
        if not words:
            raise PlyFormatError(f"{where}: blank line in the header")
        keyword = words[0]
        if keyword in ("format", "obj_info") and elements:
            raise PlyFormatError(f"{where}: '{keyword}' after the first element (it belongs before the elements)")
        if keyword in ("comment", "obj_info"):
            comments.append(raw.strip()[len(keyword):].strip())
        elif keyword == "format":
            if fmt is not None:
                raise PlyFormatError(f"{where}: a second 'format' line")
            if len(words) != 3 or words[1] not in _FORMATS:
                raise PlyFormatError(f"{where}: unknown format, expected one of {', '.join(_FORMATS)}")
            fmt = words[1]
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyFormatError(f"{where}: expected 'element NAME COUNT' with a non-negative count")
            elements.append([words[1], int(words[2]), []])
        elif keyword == "property":
            if not elements:
                raise PlyFormatError(f"{where}: property before any element")
            if len(words) == 5 and words[1] == "list":
                for t in words[2:4]:
                    if t not in PLY_TYPES:
                        raise PlyFormatError(f"{where}: unknown PLY type {t!r}")
                if PLY_TYPES[words[2]][0] not in "iu":
                    raise PlyFormatError(f"{where}: the length of a list must have an integer type, not {words[2]!r}")
                elements[-1][2].append(PlyProperty(words[4], PLY_TYPES[words[3]], True, PLY_TYPES[words[2]]))
            elif len(words) == 3:
                if words[1] not in PLY_TYPES:
                    raise PlyFormatError(f"{where}: unknown PLY type {words[1]!r}")
                elements[-1][2].append(PlyProperty(words[2], PLY_TYPES[words[1]]))
            else:
                raise PlyFormatError(f"{where}: expected 'property TYPE NAME' or 'property list T T NAME'")
        else:
            raise PlyFormatError(f"{where}: unknown header keyword {keyword!r}")
    if fmt is None:
        raise PlyFormatError(f"{path}: no 'format' line in the header")
    parsed = tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements)
    for element in parsed:
        names = [p.name for p in element.properties]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise PlyFormatError(f"{path}: element '{element.name}' declares {duplicates} more than once")
    return PlyHeader(path, fmt, parsed, tuple(comments), match.end(), file_size)


def _record_dtype(element: PlyElement, byte_order: str) -> np.dtype:
    return np.dtype([(p.name, byte_order + p.dtype) for p in element.properties])


# --------------------------------------------------------------------------------------------
# body -> structured table
# --------------------------------------------------------------------------------------------
def _list_element_bytes(header: PlyHeader, element: PlyElement, offset: int, data: memoryview) -> int:
    """Bytes taken by ``element`` (which has list properties) in a binary body starting at ``offset``.

    Walks the records (list counts are in the data); stops with a clear error as soon as a record would
    run past the end of the file, so a huge declared count costs at most one pass over the file.
    """
    order = header.byte_order
    position = offset
    end = len(data)
    for row in range(element.count):
        for prop in element.properties:
            if not prop.is_list:
                position += np.dtype(prop.dtype).itemsize
                continue
            count_type, item_type = prop.count_dtype, prop.dtype
            width = np.dtype(count_type).itemsize
            if position + width > end:
                position = end + 1
                break
            count = int(np.frombuffer(data, dtype=order + count_type, count=1, offset=position)[0])
            if count < 0:
                raise PlyFormatError(f"{header.path}: element '{element.name}' record {row}: list property "
                                     f"'{prop.name}' has a negative length {count}")
            position += width + count * np.dtype(item_type).itemsize
        if position > end:
            raise PlyFormatError(
                f"{header.path}: truncated body: element '{element.name}' declares {element.count} records "
                f"but the file ends inside record {row}"
            )
    return position - offset


def element_extents(header: PlyHeader) -> list[tuple[PlyElement, int, int]]:
    """``(element, first body byte, bytes)`` of every element of a binary PLY, in file order.

    The body must be exactly as long as the header declares: missing records (a truncated file, a count
    larger than the data, an element with no data at all) and bytes after the last element (trailing
    garbage, a count smaller than the data, an ASCII body under a binary header) are both errors that
    state the declared and the actual size.
    """
    path = header.path
    extents = []
    offset = header.body_offset
    data = None
    for element in header.elements:
        if any(p.is_list for p in element.properties):
            if data is None:
                with open(path, "rb") as f:
                    data = memoryview(f.read())
            size = _list_element_bytes(header, element, offset, data)
        else:
            size = element.count * _record_dtype(element, header.byte_order).itemsize
        extents.append((element, offset, size))
        offset += size
    declared = offset - header.body_offset
    available = header.file_size - header.body_offset
    if declared != available:
        what = ", ".join(
            f"{e.count} {'vertices' if e.name == 'vertex' else repr(e.name) + ' records'}"
            + ("" if any(p.is_list for p in e.properties)
               else f" of {_record_dtype(e, header.byte_order).itemsize} bytes")
            for e in header.elements)
        if declared > available:
            vertex = [x for x in extents if x[0].name == "vertex"]
            complete = ""
            if vertex:
                v, start, _ = vertex[0]
                itemsize = _record_dtype(v, header.byte_order).itemsize
                complete = f" ({max(0, header.file_size - start) // max(itemsize, 1)} complete vertices)"
            raise PlyFormatError(
                f"{path}: truncated body: the header declares {what} ({declared} bytes) but only {available} "
                f"bytes follow the header{complete}"
            )
        raise PlyFormatError(
            f"{path}: body size mismatch: the header declares {what} ({declared} bytes) but {available} bytes "
            f"follow the header ({available - declared} bytes more than declared: trailing data, a wrong "
            f"element count, or a body in another format than the header's {header.format!r})"
        )
    return extents


def read_vertex_table(path: str | os.PathLike, header: PlyHeader | None = None) -> np.ndarray:
    """The ``vertex`` element as a structured array ``[N]`` with native byte order.

    Every element declared in the header must be complete and the body must hold nothing else
    (``element_extents``). Binary files: one ``np.fromfile`` with the record dtype. ASCII files: tokens
    parsed as float64 and cast per property (integers checked to be integral and in range).
    """
    header = header or read_ply_header(path)
    path = header.path
    vertex = header.element("vertex")
    lists = [p.name for p in vertex.properties if p.is_list]
    if lists:
        raise PlyFormatError(
            f"{path}: vertex property {lists[0]!r} is a list property; a 3DGS PLY has scalar properties only"
        )
    if not vertex.properties:
        raise PlyFormatError(f"{path}: the vertex element has no properties")
    if header.format == "ascii":
        return _read_ascii_vertices(header, vertex)

    byte_order = header.byte_order
    dtype = _record_dtype(vertex, byte_order)
    offset = next(start for element, start, _ in element_extents(header) if element is vertex)
    with open(path, "rb") as f:
        f.seek(offset)
        table = np.fromfile(f, dtype=dtype, count=vertex.count)
    if table.shape[0] != vertex.count:  # the file shrank while we read it
        raise PlyFormatError(f"{path}: truncated body: read {table.shape[0]} of {vertex.count} vertices")
    if byte_order == ">" and np.little_endian or byte_order == "<" and not np.little_endian:
        table = table.astype(table.dtype.newbyteorder("="))
    return table


def _ascii_line_counts_ok(element: PlyElement, rows: list[bytes]) -> int | None:
    """Index of the first line of ``element`` whose values do not fit its properties, or None."""
    fixed = len(element.properties)
    if not any(p.is_list for p in element.properties):
        for i, row in enumerate(rows):
            if len(row.split()) != fixed:
                return i
        return None
    for i, row in enumerate(rows):
        tokens = row.split()
        position = 0
        for prop in element.properties:
            if not prop.is_list:
                position += 1
                continue
            try:
                count = int(tokens[position])
            except (IndexError, ValueError):
                return i
            if count < 0:
                return i
            position += 1 + count
        if position != len(tokens):
            return i
    return None


def _read_ascii_vertices(header: PlyHeader, vertex: PlyElement) -> np.ndarray:
    path = header.path
    with open(path, "rb") as f:
        f.seek(header.body_offset)
        body = f.read()
    lines = [line for line in body.splitlines() if line.strip()]
    declared = sum(e.count for e in header.elements)
    start = 0
    rows = []
    for element in header.elements:
        element_rows = lines[start: start + element.count]
        if len(element_rows) < element.count:
            what = ("vertices", "vertex lines") if element is vertex else (f"'{element.name}' records", "lines for it")
            raise PlyFormatError(
                f"{path}: truncated body: the header declares {element.count} {what[0]} but the file has only "
                f"{len(element_rows)} {what[1]} (body: {len(lines)} lines, the header declares {declared})"
            )
        if element is vertex:
            rows = element_rows
        else:
            bad = _ascii_line_counts_ok(element, element_rows)
            if bad is not None:
                raise PlyFormatError(f"{path}: '{element.name}' line {bad} does not match the properties the "
                                     f"header declares for that element")
        start += element.count
    if len(lines) != declared:
        raise PlyFormatError(
            f"{path}: body size mismatch: the header declares {declared} lines "
            f"({', '.join(f'{e.count} {e.name}' for e in header.elements)}) but the body has {len(lines)} "
            f"non-empty lines ({len(lines) - declared} more: trailing data or a wrong element count)"
        )
    num_props = len(vertex.properties)
    tokens = b" ".join(rows).split()
    if len(tokens) != vertex.count * num_props:
        counts = np.fromiter((len(r.split()) for r in rows), dtype=np.int64, count=len(rows))
        bad = int(np.flatnonzero(counts != num_props)[0])
        raise PlyFormatError(
            f"{path}: vertex line {bad} has {counts[bad]} values, the header declares {num_props} properties"
        )
    try:
        values = np.array(tokens, dtype=np.float64).reshape(vertex.count, num_props)
    except ValueError as exc:
        raise PlyFormatError(f"{path}: a vertex line holds a value that is not a number ({exc})") from None
    table = np.empty(vertex.count, dtype=_record_dtype(vertex, "="))
    for j, prop in enumerate(vertex.properties):
        column = values[:, j]
        if prop.dtype[0] in "iu":
            info = np.iinfo(np.dtype(prop.dtype))
            ok = np.isfinite(column) & (column == np.round(column)) & (column >= info.min) & (column <= info.max)
            if not ok.all():
                raise PlyFormatError(
                    f"{path}: property '{prop.name}' ({PLY_TYPE_NAMES[prop.dtype]}) has {int((~ok).sum())} values "
                    f"that are not integers in [{info.min}, {info.max}]"
                )
        table[prop.name] = column
    return table


def read_vertex_table_plyfile(path: str | os.PathLike) -> np.ndarray:
    """Slow reference reader: the ``vertex`` element through ``plyfile``, native byte order."""
    from plyfile import PlyData

    data = PlyData.read(str(path))["vertex"].data
    return np.asarray(data).astype(data.dtype.newbyteorder("="))


# --------------------------------------------------------------------------------------------
# structured table <-> Gaussians
# --------------------------------------------------------------------------------------------
def ply_property_names(sh_degree: int, normals: bool = False) -> list[str]:
    """Standard 3DGS vertex properties in the order we write them."""
    k = (sh_degree + 1) ** 2
    names = ["x", "y", "z"] + (list(_NORMALS) if normals else [])
    names += [f"f_dc_{c}" for c in range(3)] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    return names


def _float32_view(table: np.ndarray, names: list[str]) -> np.ndarray | None:
    """``[N, len(names)]`` float32 *view* of consecutive native float32 fields, or None.

    Works on the record bytes (``[N, itemsize]`` uint8 -> float32), so no per-field strided pass.
    """
    if not names or table.dtype.names is None or not table.flags.c_contiguous:
        return None
    fields = table.dtype.fields
    first = fields[names[0]][1]
    for j, name in enumerate(names):
        dtype, offset = fields[name][:2]
        if dtype != np.dtype(np.float32) or offset != first + 4 * j:
            return None
    raw = table.view(np.uint8).reshape(table.shape[0], table.dtype.itemsize)
    return raw[:, first: first + 4 * len(names)].view(np.float32)


def _columns_f32(table: np.ndarray, names: list[str]) -> np.ndarray:
    """``[N, len(names)]`` float32 values of the named fields: a view when possible, else a copy."""
    view = _float32_view(table, names)
    if view is not None:
        return view
    out = np.empty((table.shape[0], len(names)), dtype=np.float32)
    for j, name in enumerate(names):
        out[:, j] = table[name]
    return out


def vertex_table_to_gaussians(table: np.ndarray, source: str | os.PathLike = "<table>") -> Gaussians:
    """Structured vertex table (native byte order) -> ``Gaussians``; raw values, no validation."""
    names = list(table.dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [name for name in required if name not in names]
    if missing:
        raise PlyFormatError(
            f"{source}: missing vertex propert{'y' if len(missing) == 1 else 'ies'} "
            f"{', '.join(repr(m) for m in missing)} required by the 3DGS layout"
        )
    for name in required:
        kind = table.dtype.fields[name][0].kind
        if kind not in "fiu":
            raise PlyFormatError(f"{source}: vertex property '{name}' is not numeric")
    rest_indices = sorted(int(m.group(1)) for m in map(_F_REST.match, names) if m)
    num_rest = len(rest_indices)
    if rest_indices != list(range(num_rest)):
        raise PlyFormatError(
            f"{source}: f_rest_* properties are not numbered 0..{num_rest - 1} (found indices {rest_indices[:8]}...)"
        )
    if num_rest % 3 != 0:
        degree = None
    else:
        try:
            degree = sh_degree_from_coeffs(num_rest // 3 + 1)
        except ValueError:
            degree = None
    if degree is None:
        raise PlyFormatError(
            f"{source}: {num_rest} f_rest_* properties; a 3DGS PLY has 0, 9, 24 or 45 "
            f"(3 channels x ((d+1)^2 - 1) for SH degree d = 0..3)"
        )
    k = (degree + 1) ** 2
    standard = ply_property_names(degree)
    n = table.shape[0]
    colour_names = standard[3: 6 + 3 * (k - 1)]
    colours = _columns_f32(table, colour_names)                       # [N, 3K]: f_dc, then f_rest
    # gather [N, 3 num_sh_coeffs] (f_dc_0..2, then f_rest channel-major) into [N, num_sh_coeffs, 3] in one np.take per row
    order = np.empty((k, 3), dtype=np.intp)
    order[0] = np.arange(3)
    order[1:] = 3 + np.arange(3)[None, :] * (k - 1) + np.arange(k - 1)[:, None]
    sh = np.take(colours, order.reshape(-1), axis=1).reshape(n, k, 3)
    means = np.array(_columns_f32(table, standard[0:3]), dtype=np.float32, order="C")
    tail = _columns_f32(table, standard[6 + 3 * (k - 1):])           # [N, 8]: opacity, scales, rots
    opacity_logits = np.array(tail[:, 0], dtype=np.float32, order="C")
    log_scales = np.array(tail[:, 1:4], dtype=np.float32, order="C")
    quats = np.array(tail[:, 4:8], dtype=np.float32, order="C")

    extra_names = [name for name in names if name not in set(standard)]
    extras: dict[str, np.ndarray] = {}
    if all(name in extra_names for name in _NORMALS):
        normals = _columns_f32(table, list(_NORMALS)) if n else np.zeros((0, 3), np.float32)
        nonzero = bool(np.any(normals != 0) | np.any(np.isnan(normals)))
        for name in _NORMALS:
            if nonzero:
                extras[name] = np.ascontiguousarray(table[name])
            extra_names.remove(name)
    extras.update(_group_extras(table, extra_names))
    for name in LABEL_EXTRAS:
        if name in extras and extras[name].ndim == 1 and extras[name].dtype != np.int32:
            column = extras[name]
            if column.dtype.kind == "f" and not np.all(np.isfinite(column) & (column == np.round(column))):
                raise PlyFormatError(f"{source}: vertex property '{name}' holds non-integer label values")
            if column.size and (column.min() < np.iinfo(np.int32).min or column.max() > np.iinfo(np.int32).max):
                raise PlyFormatError(f"{source}: vertex property '{name}' holds labels outside the int32 range")
            extras[name] = column.astype(np.int32)
    return Gaussians(means, quats, log_scales, opacity_logits, sh, extras)


def _group_extras(table: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    """Extras by name; runs ``base_0 .. base_{k-1}`` (k >= 2, adjacent, same dtype) become ``[N, k]``."""
    extras: dict[str, np.ndarray] = {}
    i = 0
    while i < len(names):
        match = _INDEXED.match(names[i])
        run = 1
        if match and match.group(2) == "0":
            base = match.group(1)
            dtype = table.dtype.fields[names[i]][0]
            while (i + run < len(names) and names[i + run] == f"{base}_{run}"
                   and table.dtype.fields[names[i + run]][0] == dtype):
                run += 1
            if run >= 2 and base not in extras and base not in names:
                extras[base] = np.stack([table[names[i + j]] for j in range(run)], axis=1)
                i += run
                continue
            run = 1
        extras[names[i]] = np.ascontiguousarray(table[names[i]])
        i += 1
    return extras


def _extra_columns(name: str, column: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """An extra as PLY-typed 1D columns (``name`` or ``name_0..name_{k-1}``)."""
    column = np.asarray(column)
    if column.dtype == np.bool_:
        column = column.astype(np.uint8)
    if name in LABEL_EXTRAS and column.dtype.kind in "iu":
        info = np.iinfo(np.int32)
        if column.size and (column.min() < info.min or column.max() > info.max):
            raise ValueError(f"extras[{name!r}] holds labels outside the int32 range")
        column = column.astype(np.int32)
    if column.dtype.kind in "iu" and column.dtype.itemsize == 8:
        target = np.dtype(np.int32 if column.dtype.kind == "i" else np.uint32)
        info = np.iinfo(target)
        if column.size and (column.min() < info.min or column.max() > info.max):
            raise ValueError(f"extras[{name!r}] ({column.dtype}) holds values outside the PLY {target} range")
        column = column.astype(target)
    code = column.dtype.str[1:]
    if code not in PLY_TYPE_NAMES:
        raise TypeError(f"extras[{name!r}] has dtype {column.dtype}, which has no PLY type")
    if column.ndim == 1:
        return [(name, column)]
    if column.ndim == 2:
        return [(f"{name}_{j}", column[:, j]) for j in range(column.shape[1])]
    raise ValueError(f"extras[{name!r}] has shape {column.shape}; PLY extras must be [N] or [N, k]")


def gaussians_to_vertex_table(gaussians: Gaussians, *, normals: bool = True, byte_order: str = "<") -> np.ndarray:
    """``Gaussians`` -> structured vertex table in the standard property order (extras last)."""
    n = len(gaussians)
    k = gaussians.num_sh_coeffs
    extras = dict(gaussians.extras)
    stored_normals = all(name in extras for name in _NORMALS)
    columns: list[tuple[str, np.ndarray]] = []
    standard = ply_property_names(gaussians.sh_degree, normals=normals or stored_normals)
    for name in extras:
        if name in standard or any(c[0] in standard for c in _extra_columns(name, extras[name][:0])):
            if not (stored_normals and name in _NORMALS):
                raise ValueError(f"extras[{name!r}] collides with a standard 3DGS property name")
    for name, column in extras.items():
        if not (stored_normals and name in _NORMALS):
            columns += _extra_columns(name, column)
    fields = [(name, byte_order + "f4") for name in standard]
    if stored_normals:
        normal_types = {name: np.asarray(extras[name]).dtype.str[1:] for name in _NORMALS}
        fields = [(f[0], byte_order + normal_types[f[0]]) if f[0] in _NORMALS else f for f in fields]
    fields += [(name, byte_order + column.dtype.str[1:]) for name, column in columns]
    names = [f[0] for f in fields]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate PLY property names among the extras: {names}")
    table = np.empty(n, dtype=np.dtype(fields))

    # f_rest is channel-major on disk: [N, num_sh_coeffs-1, 3] -> [N, 3, num_sh_coeffs-1] -> [N, 3(num_sh_coeffs-1)]
    f_rest = gaussians.sh[:, 1:, :].transpose(0, 2, 1)
    blocks = [("x", gaussians.means), ("f_dc_0", gaussians.sh[:, 0, :]), ("f_rest_0", f_rest),
              ("opacity", gaussians.opacity_logits[:, None]), ("scale_0", gaussians.log_scales),
              ("rot_0", gaussians.quats)]
    if not stored_normals and "nx" in names:
        blocks.append(("nx", np.zeros((n, 3), np.float32)))
    position = {name: i for i, name in enumerate(names)}
    for first, block in blocks:
        width = block.shape[1] * (block.shape[2] if block.ndim == 3 else 1)
        if width == 0:
            continue
        block_names = names[position[first]: position[first] + width]
        view = _float32_view(table, block_names)
        if view is not None:  # one row-wise pass per block
            target = view.reshape(block.shape)  # splits the contiguous last axis: stays a view
            if n and not np.may_share_memory(target, table):
                raise AssertionError("internal: reshaped PLY column view is a copy")
            target[...] = block
        else:
            flat = block.reshape(n, width)
            for j, name in enumerate(block_names):
                table[name] = flat[:, j]
    if stored_normals:
        for name in _NORMALS:
            table[name] = extras[name]
    for name, column in columns:
        table[name] = column
    return table


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------
def _header_bytes(fmt: str, table: np.ndarray, comments: tuple[str, ...] = ()) -> bytes:
    lines = ["ply", f"format {fmt} 1.0"] + [f"comment {c}" for c in comments]
    lines.append(f"element vertex {table.shape[0]}")
    for name in table.dtype.names:
        lines.append(f"property {PLY_TYPE_NAMES[table.dtype.fields[name][0].str[1:]]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _ascii_body(table: np.ndarray) -> bytes:
    """One line per vertex; float32 with 9 and float64 with 17 significant digits (exact round trip)."""
    import io

    n = table.shape[0]
    names = table.dtype.names
    if n == 0:
        return b""
    formats = []
    for name in names:
        code = table.dtype.fields[name][0].str[1:]
        formats.append("%.9g" if code == "f4" else "%.17g" if code == "f8" else "%d")
    values = np.empty((n, len(names)), dtype=np.float64)  # exact for every PLY type
    for j, name in enumerate(names):
        values[:, j] = table[name]
    buffer = io.BytesIO()
    np.savetxt(buffer, values, fmt=formats, delimiter=" ", newline="\n")
    return buffer.getvalue()


def write_atomic(path: str | os.PathLike, chunks) -> None:
    """Write ``chunks`` (bytes-like or arrays) to a temp file in the same folder, then ``os.replace``."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        expected = 0
        for chunk in chunks:
            if isinstance(chunk, np.ndarray):  # bytes of the array without a copy; f.write raises on a short write
                chunk = np.ascontiguousarray(chunk).reshape(-1).view(np.uint8)
            expected += len(chunk)
            f.write(chunk)
        f.flush()
        os.fsync(f.fileno())
        written = os.fstat(f.fileno()).st_size
        if written != expected:  # ndarray.tofile and some file systems do not report a short write
            raise OSError(errno.EFBIG, f"short write ({written} of {expected} bytes)", str(path))


def write_vertex_table(path: str | os.PathLike, table: np.ndarray, *, fmt: PlyFormat = "binary_little_endian",
                       comments: tuple[str, ...] = ()) -> None:
    """Write a structured table as the ``vertex`` element of a PLY file, atomically."""
    if fmt not in _FORMATS:
        raise ValueError(f"unknown PLY format {fmt!r}, expected one of {_FORMATS}")
    if fmt == "ascii":
        body = _ascii_body(table)
    else:
        order = _BYTE_ORDER[fmt]
        body = np.ascontiguousarray(table.astype(table.dtype.newbyteorder(order), copy=False))
    write_atomic(path, [_header_bytes(fmt, table, comments), body])


def write_gaussians_ply(
    path: str | os.PathLike,
    gaussians: Gaussians,
    *,
    binary: bool = True,
    endian: Literal["<", ">"] = "<",
    normals: bool = True,
) -> None:
    """Write ``gaussians`` in the Inria 3DGS layout (extras after the standard properties), atomically.

    ``binary=False`` writes ASCII (``endian`` then ignored). ``normals`` writes zero ``nx, ny, nz`` as
    the Inria files do; extras ``nx, ny, nz`` (non-zero normals read from a file) are always written
    in that slot. ``semantic`` / ``instance`` extras are written as PLY ``int``.
    """
    if endian not in ("<", ">"):
        raise ValueError(f"endian must be '<' or '>', got {endian!r}")
    table = gaussians_to_vertex_table(gaussians, normals=normals, byte_order="=")
    fmt = "ascii" if not binary else ("binary_little_endian" if endian == "<" else "binary_big_endian")
    write_vertex_table(path, table, fmt=fmt)


# --------------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------------
def read_gaussians_ply(path: str | os.PathLike, on_invalid: str = "error"):
    """Read a 3DGS PLY -> ``(Gaussians, ValidationReport)``.

    ``on_invalid``: ``error`` (default; ``PlyFormatError`` naming the file, the property and the row
    count), ``drop`` (remove the affected rows), ``repair`` (documented fixes, see
    ``seggaussian.io.validate``) or ``report`` (keep the values as stored, only count the problems).
    """
    header = read_ply_header(path)
    table = read_vertex_table(path, header)
    gaussians = vertex_table_to_gaussians(table, source=header.path)
    try:
        return validate_gaussians(gaussians, on_invalid=on_invalid, source=str(header.path))
    except InvalidGaussiansError as exc:
        raise PlyFormatError(str(exc)) from None
