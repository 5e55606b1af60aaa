"""``seggaussian align`` on a large splat: time, residual and the error of the recovered transform.

    .venv/bin/python benchmarks/bench_align.py --gaussians 1000000 [--work DIR] [--json]

Builds one synthetic ScanNet++ room, samples ``--gaussians`` oracle Gaussians on its visible surfaces, moves them by a
known gsplat-like similarity (recentred, scale 0.33, turned 90 degrees about (1, 2, 3) then 37 about y), writes the
splat as a 3DGS PLY and runs the command as a user would (``python -m cli.seggaussian_cli align SPLAT --to RAW
--scene ID --out T.json --json``, a fresh process: reading the PLY and the scene included). Reports the wall time of
the command, the registration time it reports, the residual, and the error of the recovered transform: the
distance between each Gaussian's original centre and where the transform puts its moved centre (median, max),
the relative scale error and the rotation error in degrees.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: The known similarity: scale, and the two turns (axis, degrees) applied after recentring (gsplat-like).
SCALE = 0.33
TURNS = (((1.0, 2.0, 3.0), 90.0), ((0.0, 1.0, 0.0), 37.0))


def _rotation(axis, degrees: float) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--work", type=Path, default=None, help="Folder for the room and the splat (default: temp).")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    from seggaussian.labels.config import OracleConfig
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.io.ply.writer import write_gaussians_ply
    from seggaussian.labels.oracle import sample_oracle_gaussians
    from seggaussian.sources.layout import find_scene_layout, reader
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    work = args.work or Path(tempfile.mkdtemp(prefix="bench_align_"))
    raw = work / "raw"
    if not (raw / "scannetpp" / "data").is_dir():
        synthesize(raw / "scannetpp", 1, 0, "scannetpp", SynthConfig(width=96, num_views=8))
    scene_id = sorted(p.name for p in (raw / "scannetpp" / "data").iterdir() if p.is_dir())[0]
    domain, layout_root = find_scene_layout(raw, scene_id)
    scene = reader(domain).read_scene(layout_root, scene_id)
    g, _ = sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces,
                                   OracleConfig(num_gaussians=args.gaussians), np.random.default_rng(0),
                                   tuple(v.camera for v in scene.views))
    original = g.means.astype(np.float64)
    rotation = _rotation(*TURNS[1]) @ _rotation(*TURNS[0])
    centre = original.mean(axis=0)
    moved = SCALE * (original - centre) @ rotation.T
    splat = work / f"splat_{len(g)}.ply"
    write_gaussians_ply(splat, Gaussians(moved.astype(np.float32), g.quats, g.log_scales, g.opacity_logits, g.sh))
    moved = moved.astype(np.float32).astype(np.float64)  # what the file holds

    out = work / "transform.json"
    command = [sys.executable, "-m", "cli.seggaussian_cli", "align", str(splat), "--to", str(raw), "--scene",
               scene_id, "--out", str(out), "--json"]
    start = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - start
    if run.returncode != 0:
        raise SystemExit(f"align failed ({run.returncode}): {run.stdout}{run.stderr}")
    result = json.loads(run.stdout)
    m = np.array(result["world_from_splat"])
    error = np.linalg.norm(moved @ m[:3, :3].T + m[:3, 3] - original, axis=1)
    true_rotation = rotation.T  # world_from_splat turns back
    r = np.array(result["rotation"])
    angle = float(np.degrees(np.arccos(np.clip((np.trace(r @ true_rotation.T) - 1) / 2, -1.0, 1.0))))
    report = {
        "command": " ".join(["seggaussian"] + command[3:]),
        "gaussians": len(g),
        "splat_mb": round(splat.stat().st_size / 2**20, 1),
        "wall_s": round(wall, 2),
        "registration_s": round(result["seconds"], 2),
        "registered_points": result["num_registered"],
        "residual_m": result["residual_m"],
        "fitness": result["fitness"],
        "on_mesh_share": result["on_mesh_share"],
        "surface_covered_share": result["surface_covered_share"],
        "centre_error_median_m": float(np.median(error)),
        "centre_error_max_m": float(error.max()),
        "scale_error": float(result["scale"] * SCALE - 1.0),
        "rotation_error_deg": angle,
        "coarse": result["coarse"]["origin"],
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key:24s} {value}")


if __name__ == "__main__":
    main()
