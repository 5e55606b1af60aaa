"""``seggaussian inspect PATH``: a splat file (format, layout, statistics, validation) or a dataset folder."""

from __future__ import annotations

import importlib
from pathlib import Path

import click

from cli._output import finish, guarded, json_option


def _inspect_dataset(path: Path, as_json: bool, verify: bool) -> None:
    """A dataset folder (``manifest.json``): delegated to ``seggaussian.shards.inspect_dataset``."""
    try:
        shards = importlib.import_module("seggaussian.shards")
        inspect_dataset = shards.inspect_dataset
    except (ImportError, AttributeError):
        raise click.ClickException(f"{path}: inspecting a dataset needs seggaussian.shards.inspect_dataset, "
                                   "which is not available in this installation") from None
    payload = inspect_dataset(path, verify=verify)
    problems = payload.get("problems", [])
    finish(str(payload["summary"]), payload, as_json, "\n".join(f"problem: {p}" for p in problems) or None)
    if problems:
        raise SystemExit(1)


def _format_ply(info: dict) -> str:
    def q(stats: dict) -> str:
        qs = stats["quantiles"]
        if stats["count"] == 0:
            return "no finite values"
        return f"min {qs['0.0']:.4g}  p5 {qs['0.05']:.4g}  median {qs['0.5']:.4g}  p95 {qs['0.95']:.4g}  max {qs['1.0']:.4g}"

    bounds = info["bounds"]
    lines = [
        f"file        {info['path']} ({info['format_title']}, {info['file_bytes']} bytes"
        + (f", {info['format']}, {info['num_properties']} properties" if info["file_format"] == "ply" else "")
        + f"{', normals' if info['has_normals'] else ''})",
        f"gaussians   {info['num_gaussians']}  SH degree {info['sh_degree']}"
        + (f"  extras {', '.join(f'{k}:{v}' for k, v in info['extras'].items())}" if info["extras"] else ""),
    ]
    if bounds["min"] is not None:
        lines.append("bounds      min " + " ".join(f"{v:.4g}" for v in bounds["min"])
                     + "   max " + " ".join(f"{v:.4g}" for v in bounds["max"]))
    lines += [f"scale       {q(info['scale'])}", f"opacity     {q(info['opacity'])}",
              f"quat norm   {q(info['quat_norm'])}"]
    colour = info["dc_color"]
    if colour["mean"] is not None:
        lines.append("dc colour   mean " + " ".join(f"{v:.3f}" for v in colour["mean"])
                     + f"   outside [0,1]: {100 * colour['share_outside_0_1']:.1f}%")
    return "\n".join(lines)


@click.command("inspect")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--verify", is_flag=True,
              help="Dataset folder: also check every shard's sha256 against the manifest (sizes are always checked).")
@json_option
@guarded
def command(path: Path, verify: bool, as_json: bool) -> None:
    """Summarize a splat file (3DGS PLY, compressed PLY, .splat, SPZ, .ksplat or glTF, detected by content: format,
    count, SH degree, bounds, scale/opacity/colour statistics, validation) or a dataset folder (exit 1 when a shard is
    missing, truncated or, with --verify, corrupted)."""
    if path.is_dir():
        if (path / "manifest.json").is_file():
            _inspect_dataset(path, as_json, verify)
            return
        raise click.ClickException(f"{path}: a folder without manifest.json is not a dataset")
    from seggaussian.io.inspection import inspect_scene
    from seggaussian.io.validate import ValidationReport

    info = inspect_scene(path)
    validation = info["validation"]
    report = ValidationReport(**{k: validation[k] for k in ValidationReport._fields})
    summary = (f"{path}: {info['format_title']}, {info['num_gaussians']} Gaussians, SH degree {info['sh_degree']}, "
               f"{'valid' if report.ok else 'INVALID: ' + report.describe_issues()}")
    finish(summary, info, as_json, _format_ply(info))
