"""``seggaussian inspect PATH``: a 3DGS PLY (layout, statistics, validation) or a dataset folder."""

from __future__ import annotations

import importlib
from pathlib import Path

import click

from cli._output import finish, json_option


def _inspect_dataset(path: Path, as_json: bool) -> None:
    """A dataset folder (``manifest.json``): delegated to ``seggaussian.shards.inspect_dataset``."""
    try:
        shards = importlib.import_module("seggaussian.shards")
        inspect_dataset = shards.inspect_dataset
    except (ImportError, AttributeError):
        raise click.ClickException(f"{path}: inspecting a dataset needs seggaussian.shards.inspect_dataset, "
                                   "which is not available in this installation") from None
    summary_payload = inspect_dataset(path)
    if isinstance(summary_payload, tuple) and len(summary_payload) == 2:
        summary, payload = summary_payload
    else:
        payload = summary_payload if isinstance(summary_payload, dict) else {"result": summary_payload}
        summary = payload.get("summary", f"dataset {path}")
    finish(str(summary), payload, as_json)


def _format_ply(info: dict) -> str:
    def q(stats: dict) -> str:
        qs = stats["quantiles"]
        if stats["count"] == 0:
            return "no finite values"
        return f"min {qs['0.0']:.4g}  p5 {qs['0.05']:.4g}  median {qs['0.5']:.4g}  p95 {qs['0.95']:.4g}  max {qs['1.0']:.4g}"

    bounds = info["bounds"]
    lines = [
        f"file        {info['path']} ({info['format']}, {info['file_bytes']} bytes, {info['num_properties']} properties"
        f"{', normals' if info['has_normals'] else ''})",
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
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@json_option
def command(path: Path, as_json: bool) -> None:
    """Summarize a 3DGS PLY (count, SH degree, bounds, scale/opacity/colour statistics, validation)."""
    if path.is_dir():
        if (path / "manifest.json").is_file():
            _inspect_dataset(path, as_json)
            return
        raise click.ClickException(f"{path}: a folder without manifest.json is not a dataset")
    from seggaussian.io.ply import PlyFormatError
    from seggaussian.io.ply_inspect import inspect_ply
    from seggaussian.io.validate import ValidationReport

    try:
        info = inspect_ply(path)
    except PlyFormatError as exc:
        raise click.ClickException(str(exc)) from None
    validation = info["validation"]
    report = ValidationReport(**{k: validation[k] for k in ValidationReport._fields})
    summary = (f"{path}: {info['num_gaussians']} Gaussians, SH degree {info['sh_degree']}, "
               f"{'valid' if report.ok else 'INVALID: ' + report.describe_issues()}")
    finish(summary, info, as_json, _format_ply(info))
