"""Writing 3D Gaussian Splatting PLY files in the layout ``reader`` describes: ``Gaussians`` -> structured vertex
table (standard properties, extras last) -> header and binary or ASCII body, written atomically.
"""

from __future__ import annotations

import errno
import os
from typing import Literal

import numpy as np

from seggaussian.util.atomic import atomic_path
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.header import PLY_TYPE_NAMES, _BYTE_ORDER, _FORMATS
from seggaussian.io.ply.reader import LABEL_EXTRAS, _NORMALS, _float32_view, ply_property_names

__all__ = [
    "gaussians_to_vertex_table",
    "write_gaussians_ply",
    "write_vertex_table",
]

PlyFormat = Literal["ascii", "binary_little_endian", "binary_big_endian"]


# --------------------------------------------------------------------------------------------
# Gaussians -> structured table
# --------------------------------------------------------------------------------------------
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
