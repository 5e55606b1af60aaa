"""Ellipse culling of tile boxes against whole boxes, alternated in one run: tile pairs, binning, blending forward and
forward + backward, on real captures and on the rasterizer benchmark's synthetic scene.

Usage:
    .venv/bin/python benchmarks/bench_ellipse_cull.py [--repeats 9] [--threads 2] [--synthetic 1000000]
        [--out benchmarks/results/ellipse_cull.md]

Scenes: the PlayCanvas captures in ``$SEGGAUSSIAN_SHARED/realdata/web_splats`` (else ``../shared/...`` beside the
checkout; skipped with a note when absent), each viewed at 876x584 from outside its central 80 % (the same camera
rule for every file), and ``bench_render.make_scene`` with ``--synthetic`` Gaussians (0: none). Per scene the
projection is computed once; then, ``--repeats`` times, each mode in turn: ``bin_gaussians(...,
ellipse_cull=mode)``, the blending forward (``blend_fast``, no grad) and forward + backward on those bins (3 colour
channels + depth, loss = sum of colours and alpha). Medians of wall times; the first repeat is a warm-up. The two
modes give the same images (checked here on every scene; the tests check weights and gradients too).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

WIDTH, HEIGHT = 876, 584
CAPTURES = ("biker.compressed.ply", "guitar.compressed.ply")


def web_splats() -> Path:
    shared = os.environ.get("SEGGAUSSIAN_SHARED")
    return (Path(shared) if shared else REPO.parent / "shared") / "realdata" / "web_splats"


def capture_scene(path: Path):
    """(tensors dict, viewmat, K) of a capture seen from outside its central 80 % along a fixed direction."""
    import torch

    from seggaussian.core.cameras import intrinsics, look_at
    from seggaussian.io.formats import read_gaussians_raw

    gaussians, _ = read_gaussians_raw(path)
    t = gaussians.to_torch()
    centre = np.median(gaussians.means, 0)
    extent = np.percentile(gaussians.means, 90, 0) - np.percentile(gaussians.means, 10, 0)
    eye = centre + np.array([0.3, -1.0, 0.4]) * np.linalg.norm(extent) * 1.2
    scene = {k: t[k].float() for k in ("means", "quats", "log_scales", "opacity_logits")}
    scene["sh"] = t["sh"][:, :1].float()
    viewmat = torch.from_numpy(look_at(eye, centre))
    K = torch.from_numpy(intrinsics(0.9 * WIDTH, 0.9 * WIDTH, WIDTH / 2, HEIGHT / 2))
    return scene, viewmat, K


def bench_scene(name: str, scene, viewmat, K, repeats: int) -> dict:
    import torch

    from seggaussian.render.projection_numba import project_gaussians_fast
    from seggaussian.render.rasterize_numba import blend_fast
    from seggaussian.render.sh import sh_to_colors
    from seggaussian.render.tiles import bin_gaussians

    with torch.no_grad():
        proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, WIDTH, HEIGHT)
        opac = torch.sigmoid(scene["opacity_logits"].float())
        colors = torch.cat([sh_to_colors(scene["sh"], proj.view_dirs).float(), proj.depths.float()[:, None]], 1)
    times: dict = {}
    pairs, images = {}, {}
    for rep in range(repeats + 1):
        for cull in (False, True):
            t0 = time.perf_counter()
            bins = bin_gaussians(proj, WIDTH, HEIGHT, opac, ellipse_cull=cull)
            t1 = time.perf_counter()
            with torch.no_grad():
                out = blend_fast(proj.means2d, proj.conics, opac, colors, bins)
            t2 = time.perf_counter()
            leaves = [x.detach().clone().requires_grad_(True) for x in (proj.means2d, proj.conics, opac, colors)]
            t3 = time.perf_counter()
            accum, alpha = blend_fast(*leaves, bins)
            (accum.sum() + alpha.sum()).backward()
            t4 = time.perf_counter()
            pairs[cull], images[cull] = bins.num_intersections, out
            if rep:
                for key, value in (("binning", t1 - t0), ("blend", t2 - t1), ("blend_fwd_bwd", t4 - t3)):
                    times.setdefault((cull, key), []).append(value)
    same = all(torch.equal(a, b) for a, b in zip(images[False], images[True]))
    row = {"scene": name, "gaussians": int(opac.shape[0]), "pairs_box": pairs[False], "pairs_cull": pairs[True],
           "same_image": same}
    for (cull, key), values in times.items():
        row[f"{key}_{'cull' if cull else 'box'}_ms"] = statistics.median(values) * 1e3
    return row


def markdown(rows: list[dict], command: str, notes: list[str]) -> str:
    lines = ["# Ellipse culling of tile boxes against whole boxes", "", f"Command: `{command}`", "",
             f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {WIDTH}x{HEIGHT}, load average "
             f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end; medians of wall ms, the modes "
             "alternated.",
             "", *notes, "",
             "| scene | Gaussians | tile pairs (box -> cull) | binning | blend forward | blend forward + backward | "
             "bin + blend f+b | same image |",
             "|---|---:|---|---|---|---|---|---|"]
    for r in rows:
        def pair(key: str) -> str:
            return f"{r[key + '_box_ms']:.1f} -> {r[key + '_cull_ms']:.1f}"
        total_box = r["binning_box_ms"] + r["blend_fwd_bwd_box_ms"]
        total_cull = r["binning_cull_ms"] + r["blend_fwd_bwd_cull_ms"]
        lines.append(f"| {r['scene']} | {r['gaussians']:,} | {r['pairs_box']:,} -> {r['pairs_cull']:,} "
                     f"({r['pairs_cull'] / r['pairs_box'] - 1:+.0%}) | {pair('binning')} | {pair('blend')} | "
                     f"{pair('blend_fwd_bwd')} | {total_box:.1f} -> {total_cull:.1f} "
                     f"({total_cull / total_box - 1:+.0%}) | {'yes' if r['same_image'] else '**no**'} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--synthetic", type=int, default=1_000_000, help="Gaussians of the synthetic scene (0: none)")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown table here (atomically)")
    args = parser.parse_args()
    os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(args.threads)
    from bench_render import make_scene

    rows, notes = [], []
    folder = web_splats()
    for name in CAPTURES:
        if not (folder / name).is_file():
            notes.append(f"- {name}: not found under {folder} (set SEGGAUSSIAN_SHARED), skipped.")
            continue
        rows.append(bench_scene(name, *capture_scene(folder / name), args.repeats))
        print(rows[-1], flush=True)
    if args.synthetic:
        rows.append(bench_scene(f"synthetic ({args.synthetic:,}, bench_render)", *make_scene(args.synthetic, WIDTH,
                                HEIGHT), args.repeats))
        print(rows[-1], flush=True)
    text = markdown(rows, " ".join(["python", *sys.argv]), notes)
    print(text)
    if args.out:
        tmp = args.out.with_name(args.out.name + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, args.out)
    bad = [r["scene"] for r in rows if not r["same_image"]]
    print(f"ellipse cull: {len(rows)} scenes, images identical on {len(rows) - len(bad)}" + (
        f"; DIFFERENT on {', '.join(bad)}" if bad else ""))
    if bad:
        sys.exit(1)


if __name__ == "__main__":
    main()
