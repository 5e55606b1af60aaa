"""``seggaussian convert``: any splat file (format detected by content) to any format we write (chosen by the output
name), validated on reading, moved by ``--transform`` when given, and refused when the target cannot hold what the
source has (SH bands beyond the format's degree, per-Gaussian columns such as labels) unless ``drop`` says to
discard them, which the result then counts."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from seggaussian.frames.frame_config import FrameConfig, frame_record, to_scene_frame
from seggaussian.io.formats import check_writable, format_for_output, read_gaussians, write_gaussians
from seggaussian.io.gltf import read_gltf
from seggaussian.io.spz import DEFAULT_WRITE_VERSION
from seggaussian.io.validate import ValidationReport


@dataclass(frozen=True)
class ConvertConfig:
    """How ``convert_splat`` reads and writes."""

    #: ``error`` (refuse invalid values), ``drop`` (remove those rows) or ``repair`` (documented fixes).
    on_invalid: str = "error"
    #: Discard what OUT's format cannot hold (SH bands beyond its degree, per-Gaussian columns such as labels) and
    #: count it in the summary; without it such a conversion is refused.
    drop: bool = False
    #: SPZ version written when OUT ends in .spz (2 and 3: gzip; 4: zstd streams).
    spz_version: int = DEFAULT_WRITE_VERSION
    #: glTF output (.glb, .gltf): ``none`` (the extension's float attributes, read by any KHR_gaussian_splatting reader)
    #: or ``spz`` (KHR_gaussian_splatting_compression_spz_2, smaller; the form CesiumJS draws).
    gltf_compression: str = "none"
    #: The splat's frame (``--transform``, ``--from-frame``); the default keeps it as stored.
    frame: FrameConfig = FrameConfig()


class ConvertResult(NamedTuple):
    """What ``convert_splat`` wrote.

    Fields:
        source: the input file.
        out: the file written.
        in_format: the detected input format.
        out_format: the format written.
        num_gaussians: Gaussians written.
        sh_degree: SH degree written.
        dropped: what ``drop`` discarded (``{"sh_degree": [from, to], "extras": [...]}``; empty when nothing).
        report: the validation report of the input.
        frame: what ``frame_record`` says of the transform applied.
    """

    source: Path
    out: Path
    in_format: str
    out_format: str
    num_gaussians: int
    sh_degree: int
    dropped: dict
    report: ValidationReport
    frame: dict


def convert_splat(source: str | os.PathLike, out: str | os.PathLike, config: ConvertConfig = ConvertConfig()
                  ) -> ConvertResult:
    """Read ``source`` (validated with ``config.on_invalid``), move it by ``config.frame``, write ``out`` in the
    format its name asks for; ``ValueError`` when that format cannot hold it and ``config.drop`` is off."""
    source, out = Path(source), Path(out)
    out_format = format_for_output(out)
    if out.exists() and out.resolve() == source.resolve():
        raise ValueError(f"{out}: the output would overwrite the input; choose another name")
    gaussians, report, in_format = read_gaussians(source, on_invalid=config.on_invalid)
    gaussians, lost = check_writable(gaussians, out_format, drop=config.drop)
    gaussians, frame = to_scene_frame(gaussians, config.frame)
    legend = read_gltf(source).legend if in_format == "gltf" and out_format == "gltf" and gaussians.extras else None
    write_gaussians(out, gaussians, out_format, spz_version=config.spz_version, legend=legend,
                    gltf_compression=config.gltf_compression)
    dropped = {k: list(v) for k, v in lost.items()}
    return ConvertResult(source, out, in_format, out_format, len(gaussians), gaussians.sh_degree, dropped, report,
                         frame_record(frame))
