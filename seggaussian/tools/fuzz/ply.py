"""The PLY fuzz target of the shared harness (``seggaussian.tools.fuzz.engine``): header mutators (counts, names,
types, formats, extra elements, line endings) and seed files, real and written by our own writer.
"""

from __future__ import annotations

import functools
import re
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.header import PlyFormatError, read_ply_header
from seggaussian.io.ply.reader import read_gaussians_ply
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.tools.fuzz.engine import BYTE_MUTATORS, END_HEADER, FuzzTarget, Mutator


def _split(data: bytes) -> tuple[list[bytes], bytes] | None:
    """Header lines (without ``end_header``) and the body, or None when there is no header."""
    match = END_HEADER.search(data[: 1 << 20])
    if match is None:
        return None
    head = data[: match.start()]
    lines = head.split(b"\n")
    if head.endswith(b"\n"):
        lines = lines[:-1]
    return lines, data[match.end():]


def _join(lines: list[bytes], body: bytes) -> bytes:
    return b"\n".join(lines) + b"\nend_header\n" + body


def _header_lines(kind: bytes):
    def indices(lines: list[bytes]) -> list[int]:
        return [i for i, line in enumerate(lines) if line.startswith(kind)]
    return indices


_properties = _header_lines(b"property ")
_elements = _header_lines(b"element ")


def _has_elements(lines: list[bytes]) -> bool:
    return bool(_elements(lines))


def _has_properties(lines: list[bytes]) -> bool:
    return bool(_properties(lines))


def _has_two_lines(lines: list[bytes]) -> bool:
    return len(lines) >= 2


def _header_mutator(applies: Callable[[list[bytes]], bool] | None = None) -> Callable[..., Mutator]:
    """Make ``mutate(lines, body, rng) -> bytes`` a :data:`Mutator` of whole files: a file without a PLY header,
    or whose header lines ``applies`` rejects, comes back unchanged (before any random draw)."""
    def wrap(mutate: Callable[[list[bytes], bytes, np.random.Generator], bytes]) -> Mutator:
        @functools.wraps(mutate)
        def mutator(data: bytes, rng: np.random.Generator) -> bytes:
            parts = _split(data)
            if parts is None or (applies is not None and not applies(parts[0])):
                return data
            return mutate(*parts, rng)
        return mutator
    return wrap


@_header_mutator(_has_elements)
def ply_count(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """An element count set to 0, n - 1, n + 1, 2n, a huge number, a negative or a non-number."""
    i = _elements(lines)[int(rng.integers(0, len(_elements(lines))))]
    words = lines[i].split()
    n = int(words[2]) if len(words) == 3 and words[2].isdigit() else 1
    new = [b"0", str(max(0, n - 1)).encode(), str(n + 1).encode(), str(2 * n).encode(), b"4294967295",
           b"-1", b"1e3", b"99999999999999999999"][int(rng.integers(0, 8))]
    lines[i] = b" ".join(words[:2] + [new])
    return _join(lines, body)


@_header_mutator(_has_properties)
def ply_rename(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """A property renamed: zero-padded index (``f_rest_05``), another property's name, upper case or
    a suffix."""
    props = _properties(lines)
    i = props[int(rng.integers(0, len(props)))]
    words = lines[i].split()
    name = words[-1]
    kind = int(rng.integers(0, 4))
    if kind == 0:
        match = re.match(rb"(.*_)(\d+)$", name)
        name = match.group(1) + b"0" + match.group(2) if match else name + b"_0"
    elif kind == 1:
        name = lines[props[int(rng.integers(0, len(props)))]].split()[-1]
    elif kind == 2:
        name = name.upper()
    else:
        name = name + b"x"
    lines[i] = b" ".join(words[:-1] + [name])
    return _join(lines, body)


@_header_mutator(_has_properties)
def ply_retype(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """A property's type changed (``float`` -> ``double``, ``uchar``, ``int``, ...) or made a list."""
    i = _properties(lines)[int(rng.integers(0, len(_properties(lines))))]
    words = lines[i].split()
    types = [b"double", b"uchar", b"int", b"short", b"float", b"char", b"uint", b"float128", b"list uchar int"]
    new = types[int(rng.integers(0, len(types)))]
    lines[i] = b"property " + new + b" " + words[-1]
    return _join(lines, body)


@_header_mutator(_has_two_lines)
def ply_drop_line(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """A property, element, format or comment line removed or duplicated."""
    i = int(rng.integers(1, len(lines)))
    if rng.random() < 0.5:
        del lines[i]
    else:
        lines.insert(i, lines[i])
    return _join(lines, body)


@_header_mutator()
def ply_format(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """The ``format`` line changed to another format (binary body under an ASCII header and back)."""
    formats = [b"ascii", b"binary_little_endian", b"binary_big_endian", b"binary", b"ascii 2.0"]
    for i, line in enumerate(lines):
        if line.startswith(b"format"):
            lines[i] = b"format " + formats[int(rng.integers(0, len(formats)))] + b" 1.0"
    return _join(lines, body)


@_header_mutator()
def ply_ascii_body(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """The body replaced by whitespace-separated numbers (an ASCII body under whatever the header says)."""
    rows = int(rng.integers(1, 300))
    values = rng.normal(size=(rows, int(rng.integers(1, 70))))
    text = b"\n".join(b" ".join(b"%.6g" % v for v in row) for row in values) + b"\n"
    return _join(lines, text)


@_header_mutator()
def ply_extra_element(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """An element declared after the vertices (``face`` with a list, or a scalar element) with no data,
    too little data, or exactly its data."""
    n = int(rng.integers(1, 20))
    scalar = rng.random() < 0.5
    lines = lines + ([f"element extra {n}".encode(), b"property float w"] if scalar
                     else [f"element face {n}".encode(), b"property list uchar int vertex_indices"])
    record = np.float32(1).tobytes() if scalar else b"\x03" + np.arange(3, dtype="<i4").tobytes()
    have = [0, n // 2, n][int(rng.integers(0, 3))]
    return _join(lines, body + record * have)


@_header_mutator()
def ply_crlf(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """Header lines ended with CRLF (and, half the time, the whole file's newlines)."""
    head = b"\r\n".join(lines) + b"\r\nend_header\r\n"
    return head + (body.replace(b"\n", b"\r\n") if rng.random() < 0.5 else body)


@_header_mutator()
def ply_header_junk(lines: list[bytes], body: bytes, rng: np.random.Generator) -> bytes:
    """A comment, an unknown keyword, a blank line or non-ASCII bytes inserted in the header."""
    junk = [b"comment fuzz", b"obj_info x", b"bogus keyword", b"", b"property float late", b"\xff\xfe",
            b"element", b"format binary_little_endian 1.0"][int(rng.integers(0, 8))]
    lines.insert(int(rng.integers(1, len(lines) + 1)), junk)
    return _join(lines, body)


PLY_MUTATORS: tuple[tuple[str, Mutator], ...] = (
    ("ply_count", ply_count), ("ply_rename", ply_rename), ("ply_retype", ply_retype),
    ("ply_drop_line", ply_drop_line), ("ply_format", ply_format), ("ply_ascii_body", ply_ascii_body),
    ("ply_extra_element", ply_extra_element), ("ply_crlf", ply_crlf), ("ply_header_junk", ply_header_junk),
)


#: Records kept from a large real seed file (its header count edited to match): mutants stay small.
MAX_SEED_RECORDS = 2000


def real_ply_seed(path: Path, max_records: int = MAX_SEED_RECORDS) -> tuple[str, bytes]:
    """A real binary 3DGS PLY as a seed, cut to its first ``max_records`` vertices (header count edited)."""
    header = read_ply_header(path)
    vertex = header.element("vertex")
    data = Path(path).read_bytes()
    if vertex.count <= max_records or header.format == "ascii" or len(header.elements) != 1:
        return Path(path).name, data
    itemsize = sum(np.dtype(p.dtype).itemsize for p in vertex.properties)
    head = data[: header.body_offset].replace(f"element vertex {vertex.count}".encode(),
                                               f"element vertex {max_records}".encode(), 1)
    body = data[header.body_offset: header.body_offset + max_records * itemsize]
    return f"{Path(path).name}[:{max_records}]", head + body


def written_ply_seeds(seed: int = 0) -> list[tuple[str, bytes]]:
    """Seeds written by our own writer: SH 1 with labels (binary LE), SH 2 big endian, SH 0 ASCII."""
    rng = np.random.default_rng(seed)
    seeds = []
    cases = (("sh1_labels_le", 40, 1, {"binary": True}), ("sh2_be", 30, 2, {"binary": True, "endian": ">"}),
             ("sh0_ascii", 20, 0, {"binary": False}))
    with tempfile.TemporaryDirectory() as tmp:
        for name, n, degree, options in cases:
            k = (degree + 1) ** 2
            quats = rng.normal(size=(n, 4)).astype(np.float32)
            g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), quats,
                          rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32),
                          rng.normal(size=n).astype(np.float32), rng.normal(size=(n, k, 3)).astype(np.float32))
            if name == "sh1_labels_le":
                g = g.with_extras(semantic=rng.integers(-1, 100, n).astype(np.int32),
                                  instance=rng.integers(0, 9, n).astype(np.int32))
            path = Path(tmp) / f"{name}.ply"
            write_gaussians_ply(path, g, **options)
            seeds.append((f"written:{name}", path.read_bytes()))
    return seeds


def ply_target(real_files: Sequence[Path] = (), seed: int = 0) -> FuzzTarget:
    """The 3DGS PLY reader (``on_invalid='error'``) over the real files given plus our written seeds."""
    seeds = [real_ply_seed(Path(p)) for p in real_files] + written_ply_seeds(seed)
    return FuzzTarget("ply", lambda path: read_gaussians_ply(path)[0], seeds, PLY_MUTATORS + BYTE_MUTATORS,
                      (PlyFormatError,), ".ply")
