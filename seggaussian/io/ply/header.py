"""PLY files as a container, for any PLY (3DGS or not; the compressed PLY reader builds on it too): the header
(format, elements, properties, comments) and where each element's bytes lie in a binary body.

Errors are ``PlyFormatError`` naming the file and the problem.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "PlyFormatError",
    "PlyProperty",
    "PlyElement",
    "PlyHeader",
    "read_ply_header",
]

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
# element extents
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
