"""One entry point for every splat file: detect the format from the content, read, validate, write.

Detection looks at the bytes, never at the file name:

=================  ===============================================================================
format             how it is recognised
=================  ===============================================================================
``ply``            starts with ``ply`` and the header has no ``chunk`` element (the Inria layout)
``compressed_ply`` starts with ``ply``; a ``chunk`` element and a ``packed_position`` vertex property
``spz``            starts with ``NGSP``, or is a gzip stream whose payload starts with ``NGSP``
``gltf``           starts with ``glTF`` (GLB), or is a JSON object naming ``asset`` (``.gltf``); the splat is
                   the ``KHR_gaussian_splatting`` primitive
``ksplat``         none of the above; a plausible mkkellogg header (version 0.1+, compression level 0-2,
                   section table inside the file)
``splat``          none of the above; size a multiple of 32 and the first records plausible
=================  ===============================================================================

Anything else is a :class:`~seggaussian.io.splat_common.SplatFormatError` naming the file and listing
what was looked for. Every reader's Gaussians then go through the same validation as a PLY
(:func:`seggaussian.io.validate.validate_gaussians`, policy ``on_invalid``).

Writing picks the format from ``fmt`` or, when not given, from the output name (``.compressed.ply``,
``.splat``, ``.spz``, ``.ksplat``, ``.glb`` / ``.gltf``, else ``.ply``): there are no bytes to look at yet.
What each format holds (SH degree, extras columns) is in ``CAPABILITIES``; ``check_writable`` refuses what the
target would lose.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.compressed_ply import is_compressed_ply_header, read_compressed_ply, write_compressed_ply
from seggaussian.io.gltf import looks_like_gltf, read_gltf, write_gltf
from seggaussian.io.ksplat import looks_like_ksplat, read_ksplat, write_ksplat
from seggaussian.io.ply.header import read_ply_header
from seggaussian.io.ply.reader import read_gaussians_ply, read_vertex_table, vertex_table_to_gaussians
from seggaussian.io.ply.writer import gaussians_to_vertex_table, write_vertex_table
from seggaussian.io.splat import looks_like_splat, read_splat, write_splat
from seggaussian.io.splat_common import FORMAT_TITLES, SplatFormatError
from seggaussian.io.spz import DEFAULT_WRITE_VERSION, GZIP_MAGIC, SPZ_MAGIC_BYTES, read_spz, spz_payload_head, write_spz
from seggaussian.io.validate import InvalidGaussiansError, validate_gaussians

__all__ = ["FORMATS", "SplatFormat", "LoadedSplat", "FormatCapability", "CAPABILITIES", "detect_format",
           "read_gaussians", "read_gaussians_raw", "write_gaussians", "format_for_output", "scene_stem",
           "check_writable"]

SplatFormat = Literal["ply", "compressed_ply", "splat", "spz", "ksplat", "gltf"]
#: Every format read and written.
FORMATS: tuple[str, ...] = ("ply", "compressed_ply", "splat", "spz", "ksplat", "gltf")


class FormatCapability(NamedTuple):
    """What a format can store.

    Fields:
        max_sh_degree: the highest SH degree written.
        extras: whether per-Gaussian extras columns (labels) are stored.
    """

    max_sh_degree: int
    extras: bool


#: What each format stores when written (``ksplat``: levels 0-2 write SH degree 2 at most).
CAPABILITIES = {
    "ply": FormatCapability(3, True),
    "compressed_ply": FormatCapability(3, False),
    "splat": FormatCapability(0, False),
    "spz": FormatCapability(3, False),
    "ksplat": FormatCapability(2, False),
    "gltf": FormatCapability(3, True),
}
#: Bytes read to detect the format (a PLY header is parsed separately, up to its own limit).
SNIFF_BYTES = 4096


class LoadedSplat(NamedTuple):
    """A read and validated splat file.

    Fields:
        gaussians: the Gaussians after validation.
        report: the ``ValidationReport``.
        format: the detected format (one of ``FORMATS``).
    """

    gaussians: Gaussians
    report: object
    format: str


def detect_format(path: str | os.PathLike) -> str:
    """The format of ``path`` from its content; ``SplatFormatError`` when it is none of ``FORMATS``."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(SNIFF_BYTES)
    except OSError as exc:
        raise SplatFormatError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    if size == 0:
        raise SplatFormatError(f"{path}: empty file (0 bytes), not a splat file")
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        return "compressed_ply" if is_compressed_ply_header(read_ply_header(path)) else "ply"
    if head.startswith(SPZ_MAGIC_BYTES):
        return "spz"
    if head.startswith(GZIP_MAGIC):
        with open(path, "rb") as f:
            payload = spz_payload_head(f.read(1 << 16))
        if payload.startswith(SPZ_MAGIC_BYTES):
            return "spz"
        raise SplatFormatError(f"{path}: a gzip file whose content is not SPZ (no 'NGSP' magic); "
                               "gunzip it first if it holds a PLY")
    if looks_like_gltf(head):
        return "gltf"
    if looks_like_ksplat(head, size):
        return "ksplat"
    if looks_like_splat(head, size):
        return "splat"
    first = head[:8]
    raise SplatFormatError(
        f"{path}: unknown splat format (starts with {first!r}, {size} bytes): not a PLY file ('ply' header), "
        f"not SPZ ('NGSP' or gzip), not glTF ('glTF' or a JSON object naming 'asset'), "
        f"not a mkkellogg .ksplat (version 0.1 header), "
        f"not an antimatter15 .splat (32-byte records"
        f"{'' if size % 32 == 0 else f'; {size} is not a multiple of 32'})"
    )


def read_gaussians_raw(path: str | os.PathLike, fmt: str | None = None) -> tuple[Gaussians, str]:
    """Decode ``path`` (format detected unless ``fmt`` is given) -> ``(Gaussians, format)``, not validated."""
    path = Path(path)
    fmt = fmt or detect_format(path)
    if fmt == "ply":
        header = read_ply_header(path)
        return vertex_table_to_gaussians(read_vertex_table(path, header), source=header.path), fmt
    if fmt == "compressed_ply":
        return read_compressed_ply(path), fmt
    if fmt == "splat":
        return read_splat(path), fmt
    if fmt == "spz":
        return read_spz(path), fmt
    if fmt == "ksplat":
        return read_ksplat(path), fmt
    if fmt == "gltf":
        return read_gltf(path).gaussians, fmt
    raise ValueError(f"unknown splat format {fmt!r}, expected one of {FORMATS}")


def read_gaussians(path: str | os.PathLike, on_invalid: str = "error") -> LoadedSplat:
    """Detect, decode and validate (``on_invalid`` as in ``read_gaussians_ply``) any supported splat file."""
    path = Path(path)
    if (fmt := detect_format(path)) == "ply":
        gaussians, report = read_gaussians_ply(path, on_invalid=on_invalid)
        return LoadedSplat(gaussians, report, fmt)
    gaussians, fmt = read_gaussians_raw(path, fmt)
    try:
        gaussians, report = validate_gaussians(gaussians, on_invalid=on_invalid,
                                               source=f"{path} ({FORMAT_TITLES[fmt]})")
    except InvalidGaussiansError as exc:
        raise SplatFormatError(str(exc)) from None
    return LoadedSplat(gaussians, report, fmt)


def scene_stem(path: str | os.PathLike) -> str:
    """The file name without its splat suffix (``room.compressed.ply`` -> ``room``, ``room.spz`` -> ``room``)."""
    name = Path(path).name
    for suffix in (".compressed.ply", ".ply", ".splat", ".spz", ".ksplat", ".glb", ".gltf"):
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return Path(path).stem


def format_for_output(path: str | os.PathLike, fmt: str | None = None) -> str:
    """``fmt`` when given (checked), else the format the output name asks for (default ``ply``)."""
    if fmt is not None:
        if fmt not in FORMATS:
            raise ValueError(f"unknown splat format {fmt!r}, expected one of {', '.join(FORMATS)}")
        return fmt
    name = Path(path).name.lower()
    if name.endswith(".compressed.ply"):
        return "compressed_ply"
    if name.endswith(".splat"):
        return "splat"
    if name.endswith(".spz"):
        return "spz"
    if name.endswith(".ksplat"):
        return "ksplat"
    if name.endswith((".glb", ".gltf")):
        return "gltf"
    return "ply"


def write_gaussians(path: str | os.PathLike, gaussians: Gaussians, fmt: str | None = None, *,
                    spz_version: int = DEFAULT_WRITE_VERSION, ksplat_level: int = 1, ply_comments: tuple[str, ...] = (),
                    legend: dict | None = None, gltf_compression: str = "none") -> str:
    """Write ``gaussians`` atomically in ``fmt`` (or the format of the name) -> the format written.

    ``ply`` and ``gltf`` keep extras (labels); the other formats hold the splat attributes alone. ``legend`` (class
    names and colours) goes into a glTF file's extras; ``ply_comments`` into a PLY header; ``gltf_compression``
    ``spz`` writes glTF with the SPZ compression extension (what CesiumJS renders).
    """
    fmt = format_for_output(path, fmt)
    if fmt == "ply":
        write_vertex_table(path, gaussians_to_vertex_table(gaussians, byte_order="="), comments=ply_comments)
    elif fmt == "compressed_ply":
        write_compressed_ply(path, gaussians)
    elif fmt == "splat":
        write_splat(path, gaussians)
    elif fmt == "ksplat":
        write_ksplat(path, gaussians, compression_level=ksplat_level)
    elif fmt == "gltf":
        write_gltf(path, gaussians, legend=legend, compression=gltf_compression)
    else:
        write_spz(path, gaussians, version=spz_version)
    return fmt


def check_writable(gaussians: Gaussians, fmt: str, *, drop: bool = False) -> tuple[Gaussians, dict]:
    """``gaussians`` as ``fmt`` can hold them, and what had to go (``{"sh_degree": (from, to), "extras": [...]}``;
    empty when nothing): ``ValueError`` (one line) when something would be lost, unless ``drop``."""
    capability = CAPABILITIES[fmt]
    lost: dict = {}
    if gaussians.sh_degree > capability.max_sh_degree:
        lost["sh_degree"] = (gaussians.sh_degree, capability.max_sh_degree)
    if gaussians.extras and not capability.extras:
        lost["extras"] = sorted(gaussians.extras)
    if lost and not drop:
        what = []
        if "sh_degree" in lost:
            what.append(f"SH degree {gaussians.sh_degree} (it stores degree {capability.max_sh_degree} at most)")
        if "extras" in lost:
            what.append(f"the per-Gaussian columns {', '.join(lost['extras'])} (it has no field for them)")
        raise ValueError(f"{FORMAT_TITLES[fmt]} cannot hold {' and '.join(what)}; convert to a format that does "
                         "(ply, gltf), or pass --drop to discard them")
    if not lost:
        return gaussians, lost
    keep = (capability.max_sh_degree + 1) ** 2
    sh = np.ascontiguousarray(gaussians.sh[:, :keep])
    extras = gaussians.extras if capability.extras else {}
    return Gaussians(gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, sh, extras), lost
