"""``seggaussian import``: read any splat file (format detected by content), validate it, write a standard
3DGS PLY (Inria layout) plus a JSON report."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from seggaussian.frames.frame_config import FrameConfig, frame_record, to_scene_frame
from seggaussian.io.formats import read_gaussians, scene_stem
from seggaussian.io.ply.writer import write_atomic, write_gaussians_ply
from seggaussian.io.validate import ValidationReport


@dataclass(frozen=True)
class ImportConfig:
    """How ``import_ply`` reads and writes."""

    #: ``error`` (refuse invalid values), ``drop`` (remove those rows) or ``repair`` (documented fixes).
    on_invalid: str = "error"
    #: Write binary little endian (True) or ASCII (False).
    binary: bool = True
    #: Write zero normals ``nx, ny, nz`` as the Inria files do.
    normals: bool = True
    #: The splat's frame (``--transform``, ``--from-frame``); the default keeps it as stored.
    frame: FrameConfig = FrameConfig()


class ImportResult(NamedTuple):
    """What ``import_ply`` wrote.

    Fields:
        source: the input PLY.
        ply_path: the validated standard PLY written into the output folder.
        report_path: the JSON report next to it (``<stem>.import.json``).
        num_gaussians: Gaussians written.
        sh_degree: SH degree of the scene.
        report: the validation report.
        format: the detected input format (``ply``, ``compressed_ply``, ``splat``, ``spz``).
        frame: what ``frame_record`` says of the transform applied (``{"transform": None}`` when none).
    """

    source: Path
    ply_path: Path
    report_path: Path
    num_gaussians: int
    sh_degree: int
    report: ValidationReport
    format: str = "ply"
    frame: dict | None = None


def import_ply(source: str | os.PathLike, out_dir: str | os.PathLike, config: ImportConfig = ImportConfig()) -> ImportResult:
    """Read ``source``, validate with ``config.on_invalid``, write ``out_dir/<stem>.ply`` and its report."""
    source = Path(source)
    out_dir = Path(out_dir)
    gaussians, report, fmt = read_gaussians(source, on_invalid=config.on_invalid)
    gaussians, frame = to_scene_frame(gaussians, config.frame)
    stem = scene_stem(source)
    ply_path = out_dir / f"{stem}.ply"
    if ply_path.resolve() == source.resolve():
        raise ValueError(f"{ply_path}: the output would overwrite the input; choose another --out folder")
    report_path = out_dir / f"{stem}.import.json"
    write_gaussians_ply(ply_path, gaussians, binary=config.binary, normals=config.normals)
    payload = {
        "source": str(source),
        "format": fmt,
        "output": str(ply_path),
        "num_gaussians": len(gaussians),
        "sh_degree": gaussians.sh_degree,
        "extras": sorted(gaussians.extras),
        "validation": report.to_dict(),
        "frame": frame_record(frame),
    }
    write_atomic(report_path, [(json.dumps(payload, indent=2, sort_keys=True) + "\n").encode()])
    return ImportResult(source, ply_path, report_path, len(gaussians), gaussians.sh_degree, report, fmt,
                        payload["frame"])
