"""CPU seconds of the label-map vote (``seggaussian.render.render_label_maps``) against another commit's, alternated.

    .venv/bin/python benchmarks/bench_label_maps.py --against 84d110b --views 20

The blend weights of one 640 x 480 view with ``--top-k`` contributors a pixel, drawn as a real view's are: each
pixel's contributors are Gaussians near one another in id (a surface), their labels drawn per block of ids (a few
distinct labels a pixel), weights falling off front to back. The other commit's ``labelmaps.py`` is loaded from git
into this process under another name; both votes run on the same inputs, alternated view by view, and must give the
same maps.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from seggaussian.render import labelmaps  # noqa: E402
from seggaussian.render.results import BlendWeights  # noqa: E402


def other_labelmaps(commit: str, folder: Path):
    """``seggaussian/render/labelmaps.py`` of ``commit``, imported as a module of its own."""
    source = subprocess.run(["git", "show", f"{commit}:seggaussian/render/labelmaps.py"], cwd=REPO, check=True,
                            capture_output=True, text=True).stdout
    path = folder / f"labelmaps_{commit}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def view_blend(rng: np.random.Generator, gaussians: int, width: int, height: int, top_k: int) -> BlendWeights:
    base = rng.integers(0, gaussians - 64, size=(height, width, 1))
    ids = base + np.sort(rng.integers(0, 64, size=(height, width, top_k)), axis=-1)
    ids[rng.random((height, width, top_k)) < 0.05] = -1
    alpha = rng.uniform(0.2, 0.9, size=(height, width, top_k)).astype(np.float32)
    transmittance = np.cumprod(np.concatenate([np.ones((height, width, 1), np.float32), 1 - alpha[..., :-1]], -1), -1)
    weights = np.where(ids >= 0, alpha * transmittance, 0).astype(np.float32)
    residual = (1 - weights.sum(-1)).clip(0, 1).astype(np.float32)
    return BlendWeights(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(residual))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", required=True, help="the commit whose vote to compare with")
    parser.add_argument("--views", type=int, default=20)
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--classes", type=int, default=100)
    parser.add_argument("--top-k", type=int, default=16)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    block = rng.integers(0, args.classes, size=args.gaussians // 256 + 1)
    semantic = torch.from_numpy(block[np.arange(args.gaussians) // 256])
    instance = torch.from_numpy(np.arange(args.gaussians) // 1024)
    seconds = {"this": 0.0, args.against: 0.0}
    with tempfile.TemporaryDirectory() as folder:
        other = other_labelmaps(args.against, Path(folder))
        votes = {"this": labelmaps.render_label_maps, args.against: other.render_label_maps}
        for vote in votes.values():  # compile (or load) both kernels before timing
            vote(view_blend(rng, args.gaussians, 8, 8, args.top_k), semantic, instance, args.classes)
        for view in range(args.views):
            blend = view_blend(rng, args.gaussians, 640, 480, args.top_k)
            maps = {}
            order = list(votes) if view % 2 == 0 else list(votes)[::-1]
            for name in order:
                start = time.process_time()
                maps[name] = votes[name](blend, semantic, instance, args.classes)
                seconds[name] += time.process_time() - start
            a, b = maps.values()
            if not (torch.equal(a.semantic, b.semantic) and torch.equal(a.instance, b.instance)
                    and torch.equal(a.soft, b.soft)):
                raise SystemExit(f"view {view}: the two votes differ")
    for name, value in seconds.items():
        print(f"{name}: {value / args.views:.3f} CPU s a view")
    print(f"this / {args.against}: {seconds['this'] / seconds[args.against]:.2f}x (same maps on {args.views} views)")


if __name__ == "__main__":
    main()
