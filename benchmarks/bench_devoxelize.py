"""Benchmark: voxel features back to Gaussians, nearest voxel against trilinear blend
(``ovgaussian.sparse.devoxelize``).

Points on the faces of a 6 x 5 x 3 m box room with some clutter and floaters (a fitted splat's layout: most points
on surfaces), voxelized at ``--voxel`` metres. Timed round-robin in one process, one torch thread, median of
``--reps``: building the gather (the trilinear one: 8 corners per point from the 3^3 kernel map the backbone caches on
the sites; the map is built once, in the warm-up), ``gather`` of ``[M, 16]`` voxel features to the points, and
``scatter`` (its transpose, the backward). The voxelization itself is timed for
scale (both modes need it). Prints a markdown table.

    .venv/bin/python benchmarks/bench_devoxelize.py --points 150000 1000000 --voxel 0.1 0.05 --reps 5
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def room_points(n: int, seed: int) -> torch.Tensor:
    """``[n, 3]``: 80 % on the six faces of a 6 x 5 x 3 m box, 15 % in clutter boxes, 5 % floaters inside."""
    g = torch.Generator().manual_seed(seed)
    size = torch.tensor([6.0, 5.0, 3.0])
    faces = int(0.8 * n)
    pts = torch.rand(n, 3, generator=g) * size
    axis = torch.randint(0, 3, (faces,), generator=g)
    side = torch.randint(0, 2, (faces,), generator=g).float()
    pts[torch.arange(faces), axis] = side * size[axis]
    clutter = int(0.15 * n)
    centres = torch.rand(20, 3, generator=g) * size
    which = torch.randint(0, 20, (clutter,), generator=g)
    pts[faces:faces + clutter] = centres[which] + (torch.rand(clutter, 3, generator=g) - 0.5) * 0.6
    return pts + 0.003 * torch.randn(n, 3, generator=g)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[150_000, 1_000_000])
    parser.add_argument("--voxel", type=float, nargs="+", default=[0.1, 0.05])
    parser.add_argument("--channels", type=int, default=16)
    parser.add_argument("--reps", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)

    from bench_sparse import interleaved_medians
    from ovgaussian.sparse import voxelize_points
    from ovgaussian.sparse.devoxelize import PointGather, trilinear_gather

    print("| points | voxel | voxels | voxelize | nearest: build / gather / scatter | trilinear: build / gather / "
          "scatter | occupied corners per point |")
    print("|---:|---:|---:|---:|---|---|---:|")
    for n in args.points:
        pts = room_points(n, 0)
        batch = torch.zeros(n, dtype=torch.int64)
        for edge in args.voxel:
            vox = voxelize_points(pts, torch.zeros(n, 1), batch, edge, 4096)
            m = len(vox.voxels.sites)
            features = torch.randn(m, args.channels)
            grads = torch.randn(n, args.channels)
            nearest = PointGather.nearest(vox.point_to_voxel)
            tri = trilinear_gather(vox.voxels.sites, vox.point_to_voxel, vox.point_offsets)
            t = interleaved_medians({
                "voxelize": lambda: voxelize_points(pts, torch.zeros(n, 1), batch, edge, 4096),
                "n_build": lambda: PointGather.nearest(vox.point_to_voxel),
                "n_gather": lambda: nearest.gather(features),
                "n_scatter": lambda: nearest.scatter(grads, m),
                "t_build": lambda: trilinear_gather(vox.voxels.sites, vox.point_to_voxel, vox.point_offsets),
                "t_gather": lambda: tri.gather(features),
                "t_scatter": lambda: tri.scatter(grads, m),
            }, args.reps)
            occupied = float((tri.weights > 0).sum(1).float().mean())
            ms = {k: f"{1e3 * v:.0f}" if v >= 0.01 else f"{1e3 * v:.1f}" for k, v in t.items()}
            nearest_ms = f"{ms['n_build']} / {ms['n_gather']} / {ms['n_scatter']} ms"
            trilinear_ms = f"{ms['t_build']} / {ms['t_gather']} / {ms['t_scatter']} ms"
            cells = (f"{n:,}", f"{edge:g}", f"{m:,}", f"{ms['voxelize']} ms", nearest_ms, trilinear_ms,
                     f"{occupied:.2f}")
            print("| " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
