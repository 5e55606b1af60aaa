"""3D Gaussian Splatting PLY files (the Inria ``save_ply`` layout): the layout, and reading it with validation.

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


Binary bodies are decoded with one ``np.fromfile`` into a structured dtype (no per-row Python); the header is
parsed by ``header``, the writer is ``writer`` and ``reference.read_vertex_table_plyfile`` is the slow,
obviously-correct reference built on ``plyfile``.
"""

from __future__ import annotations

import os
import re

import numpy as np

from seggaussian.core.gaussians import Gaussians, sh_degree_from_coeffs
from seggaussian.io.ply.header import (PLY_TYPE_NAMES, PlyElement, PlyFormatError, PlyHeader, _record_dtype,
                                       element_extents, read_ply_header)
from seggaussian.io.validate import InvalidGaussiansError, validate_gaussians

__all__ = [
    "read_vertex_table",
    "vertex_table_to_gaussians",
    "read_gaussians_ply",
    "ply_property_names",
]

#: Extras always written as int32 PLY ``int`` properties so that viewers and our tools read them back.
LABEL_EXTRAS = ("semantic", "instance")
_NORMALS = ("nx", "ny", "nz")
#: ``f_rest_<i>`` spelled exactly as the layout writes it (no sign, no leading zero): ``f_rest_05`` is an
#: extra column, not coefficient 5.
_F_REST = re.compile(r"f_rest_(0|[1-9][0-9]*)$")
_INDEXED = re.compile(r"(.+)_(\d+)$")


# --------------------------------------------------------------------------------------------
# body -> structured table
# --------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------
# structured table -> Gaussians
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
