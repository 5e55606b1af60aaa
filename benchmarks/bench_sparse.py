"""Benchmark: sparse voxel convolution (ours vs spconv 2.3.8) and the full OVGaussian net.

Part 1 (``conv``): 100,000 active voxels in a 256^3 grid, 32 channels, three submanifold 3^3
layers, forward + backward, one torch thread. Two site distributions: ``uniform`` (random voxels,
about 1 neighbour per site) and ``surface`` (voxels on box faces, like a scanned room, about 9).
Compared in one run, round-robin: ours with the implicit-GEMM method (default) and with the
per-offset gather/matmul/scatter method, each with the kernel map (and GEMM plan) built in the call
and cached, and spconv 2.3.8 (CPU, single-threaded; its backward needs its CUDA-stream lookup
patched to 0 at run time, done here without touching the installed package). Kernel-map and plan
building are also timed separately.
Outputs and gradients of ours and spconv are compared (max abs difference).

Part 2 (``net``): forward + backward of ``OVGaussianNet`` on 3 synthetic rooms x 50,000 Gaussians
at the default MinkUNet34C widths and at the slim widths; time and peak RSS, each configuration
in its own subprocess so that peak memory is not shared.

Usage::

    .venv/bin/python benchmarks/bench_sparse.py [conv|net|net-interleaved|all] [--reps 5] [--threads 1]
        [--widths slim,default] [--methods gemm,scatter]

``net-interleaved``: the semantic-phase step with the conv methods run round-robin in one process
(``--reps`` timed steps each after one warm-up), the fairer method comparison on a loaded machine.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def median_time(fn, reps: int) -> tuple[float, list[float]]:
    fn()  # warm-up
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times


def interleaved_medians(fns: dict, reps: int) -> dict:
    """Median seconds of each callable, run round-robin (load changes hit all of them alike)."""
    for fn in fns.values():
        fn()  # warm-up
    times: dict = {name: [] for name in fns}
    for _ in range(reps):
        for name, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    return {name: statistics.median(ts) for name, ts in times.items()}


def random_sites_256(num_voxels: int, seed: int):
    from ovgaussian.sparse import VoxelSites

    g = torch.Generator().manual_seed(seed)
    flat = torch.randperm(256**3, generator=g)[:num_voxels]
    coords = torch.stack([flat // 65536, (flat // 256) % 256, flat % 256], dim=1)
    sites, _ = VoxelSites.from_coords(torch.zeros(num_voxels, dtype=torch.long), coords)
    return sites


def surface_sites_256(num_voxels: int, seed: int):
    """The first ``num_voxels`` (in key order) voxels on the faces of a room-sized box (200 x 160 x 80
    voxels) and 40 smaller boxes inside a 256^3 grid: one-voxel-thick surfaces, like a scanned room."""
    from ovgaussian.sparse import VoxelSites

    g = torch.Generator().manual_seed(seed)
    boxes = [(torch.tensor([8.0, 8.0, 8.0]), torch.tensor([208.0, 168.0, 88.0]))]
    for _ in range(40):
        lo = torch.rand(3, generator=g) * torch.tensor([180.0, 140.0, 60.0]) + 10
        boxes.append((lo, lo + 6 + torch.rand(3, generator=g) * 30))
    points = []
    for lo, hi in boxes:
        n = 1_500_000 if not points else 30_000
        u = torch.rand(n, 3, generator=g)
        axis = torch.randint(0, 3, (n,), generator=g)
        u[torch.arange(n), axis] = torch.randint(0, 2, (n,), generator=g).float()
        points.append(lo + u * (hi - lo))
    coords = torch.cat(points).floor().long()
    sites, _ = VoxelSites.from_coords(torch.zeros(coords.shape[0], dtype=torch.long), coords)
    if len(sites) < num_voxels:
        raise RuntimeError(f"only {len(sites)} surface voxels")
    return VoxelSites(sites.keys[:num_voxels])


def bench_conv(reps: int, distribution: str, num_voxels: int = 100_000, channels: int = 32, layers: int = 3) -> dict:
    from ovgaussian.sparse import VoxelSites, sparse_conv
    from ovgaussian.sparse.gather_plan import build_gather_plan, gather_plans
    from ovgaussian.sparse.kernel_map import build_submanifold_map

    sites = (random_sites_256 if distribution == "uniform" else surface_sites_256)(num_voxels, 0)
    g = torch.Generator().manual_seed(1)
    features = torch.randn(num_voxels, channels, generator=g)
    weights = [torch.randn(27, channels, channels, generator=g) / (27 * channels) ** 0.5 for _ in range(layers)]
    upstream = torch.randn(num_voxels, channels, generator=g)
    result: dict = {"distribution": distribution, "num_voxels": num_voxels, "channels": channels, "layers": layers, "grid": 256,
                    "threads": torch.get_num_threads()}

    def build_map():
        return VoxelSites(sites.keys).submanifold_map(3)

    result["ours_map_build_s"], _ = median_time(build_map, reps)
    result["ours_map_build_search_s"], _ = median_time(
        lambda: build_submanifold_map(sites.keys, 3, method="search"), reps)
    kmap = build_map()
    result["ours_gemm_plan_build_s"], _ = median_time(lambda: build_gather_plan(kmap), reps)
    plan, _ = gather_plans(kmap)
    pairs = sum(int(t.numel()) for t in kmap.in_indices)
    result["kernel_map_pairs"] = pairs
    result["gemm_groups"] = len(plan.groups)
    result["gemm_offsets_per_row"] = sum(gr.neighbours.numel() for gr in plan.groups) / num_voxels

    def run(method, kernel_map):
        f = features.clone().requires_grad_(True)
        ws = [w.clone().requires_grad_(True) for w in weights]
        x = f
        for w in ws:
            x = sparse_conv(x, w, kernel_map, method=method)
        (x * upstream).sum().backward()
        return x.detach(), f.grad, [w.grad for w in ws]

    ours = run("gemm", kmap)
    scatter = run("scatter", kmap)
    result["gemm_vs_scatter_max_abs_out"] = float((ours[0] - scatter[0]).abs().max())
    result["gemm_vs_scatter_max_abs_grad_features"] = float((ours[1] - scatter[1]).abs().max())
    result["gemm_vs_scatter_max_abs_grad_weight"] = max(float((a - b).abs().max()) for a, b in zip(ours[2], scatter[2]))
    fns = {
        "ours_gemm_total_s": lambda: run("gemm", build_map()),
        "ours_gemm_fwd_bwd_s": lambda: run("gemm", kmap),
        "ours_scatter_total_s": lambda: run("scatter", build_map()),
        "ours_scatter_fwd_bwd_s": lambda: run("scatter", kmap),
    }
    try:
        spconv_run, info = make_spconv(sites, features, weights, upstream, ours)
        fns["spconv_total_fwd_bwd_s"] = spconv_run
        result.update(info)
    except Exception as exc:  # report exactly why spconv could not run
        result["spconv_error"] = f"{type(exc).__name__}: {exc}"
    result.update(interleaved_medians(fns, reps))
    return result


def make_spconv(sites, features, weights, upstream, ours):
    """spconv 2.3.8 version of the three layers (index building included in every call) and its errors."""
    import spconv
    import spconv.pytorch as sp
    import spconv.pytorch.cppcore as cppcore
    import spconv.pytorch.ops as ops

    # spconv 2.3.8 CPU: backward asks torch.cuda for the current stream; 0 is the CPU "stream".
    ops.get_current_stream = lambda: 0
    cppcore.get_current_stream = lambda: 0
    indices = torch.cat([sites.batch_index[:, None], sites.coords], dim=1).int()
    channels = features.shape[1]
    convs = [sp.SubMConv3d(channels, channels, 3, bias=False, indice_key="subm") for _ in weights]
    with torch.no_grad():
        for conv, w in zip(convs, weights):  # ours [27, Cin, Cout] -> spconv [Cout, 3, 3, 3, Cin]
            conv.weight.copy_(w.reshape(3, 3, 3, channels, channels).permute(4, 0, 1, 2, 3))

    def run_once():
        f = features.clone().requires_grad_(True)
        x = sp.SparseConvTensor(f, indices, [256, 256, 256], 1)
        for conv in convs:
            x = conv(x)
        (x.features * upstream).sum().backward()
        return x.features.detach(), f.grad, [c.weight.grad.permute(1, 2, 3, 4, 0).reshape(27, channels, channels)
                                             for c in convs]

    def run():
        for c in convs:
            c.weight.grad = None
        return run_once()

    out, grad_f, grad_w = run()
    errors = {
        "spconv_vs_ours_max_abs_out": float((out - ours[0]).abs().max()),
        "spconv_vs_ours_max_abs_grad_features": float((grad_f - ours[1]).abs().max()),
        "spconv_vs_ours_max_abs_grad_weight": max(float((a - b).abs().max()) for a, b in zip(grad_w, ours[2])),
    }
    return run, {"spconv_version": spconv.__version__, **errors}


def room_gaussians(num_scenes: int, per_scene: int, seed: int):
    """Synthetic rooms: Gaussians on the six faces of a 6 x 5 x 3 m box plus 12 random boxes."""
    from ovgaussian.model.network import gaussian_attributes

    g = torch.Generator().manual_seed(seed)
    means, batch = [], []
    for b in range(num_scenes):
        boxes = [(torch.zeros(3), torch.tensor([6.0, 5.0, 3.0]))]
        for _ in range(12):
            lo = torch.rand(3, generator=g) * torch.tensor([5.0, 4.0, 1.5])
            boxes.append((lo, lo + 0.3 + torch.rand(3, generator=g)))
        per_box = [per_scene // 2] + [per_scene - per_scene // 2 - (len(boxes) - 2) * (per_scene // 24)] + \
            [per_scene // 24] * (len(boxes) - 2)
        for (lo, hi), n in zip(boxes, per_box):
            u = torch.rand(n, 3, generator=g)
            axis = torch.randint(0, 3, (n,), generator=g)
            side = torch.randint(0, 2, (n,), generator=g).float()
            u[torch.arange(n), axis] = side  # a point on one of the six faces
            noise = 0.01 * torch.randn(n, 3, generator=g)
            means.append(lo + u * (hi - lo) + noise)
        batch.append(torch.full((per_scene,), b, dtype=torch.long))
    n = num_scenes * per_scene
    raw = {"quats": torch.randn(n, 4, generator=g), "log_scales": torch.randn(n, 3, generator=g) * 0.5 - 4.0,
           "opacity_logits": torch.randn(n, generator=g), "sh": torch.randn(n, 1, 3, generator=g)}
    return torch.cat(means), gaussian_attributes(raw), torch.cat(batch)


def bench_net_one(width: str, reps: int, method: str) -> dict:
    """Runs in a subprocess: forward + backward of the full net at ``default`` or ``slim`` widths.

    ``method``: the sparse conv method of every layer ("gemm", the default, or "scatter"); the
    modules call ``ovgaussian.sparse.conv.sparse_conv``, rebound here for this process only.
    """
    import functools

    import ovgaussian.sparse.conv as conv_module
    from ovgaussian.model.network import OVGaussianNet
    from ovgaussian.model.config import OVGaussianNetConfig
    from ovgaussian.sparse import voxelize_points

    conv_module.sparse_conv = functools.partial(conv_module.sparse_conv, method=method)
    config = OVGaussianNetConfig() if width == "default" else OVGaussianNetConfig.slim()
    net = OVGaussianNet(config)
    means, attrs, batch = room_gaussians(3, 50_000, seed=2)
    vox = voxelize_points(means, attrs, batch, config.voxel_size, config.max_grid_extent)
    g = torch.Generator().manual_seed(3)
    targets = torch.randn(config.embedding_width, 20, generator=g)
    labels = torch.randint(0, 20, (means.shape[0],), generator=g)

    upstream = torch.randn(means.shape[0], config.semantic_width, generator=g)

    def step_semantic():
        """Backbone + adapter: forward to s [N, 16], backward from a linear loss on s."""
        net.zero_grad(set_to_none=True)
        (net(means, attrs, batch) * upstream).sum().backward()

    def step_with_decoders():
        """Plus phi (3D-to-text cross-entropy over all N Gaussians, D = 512) and psi on all N."""
        net.zero_grad(set_to_none=True)
        s = net(means, attrs, batch)
        loss = torch.nn.functional.cross_entropy(net.phi(s) @ targets, labels) + net.psi(s).square().mean()
        loss.backward()

    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t_sem, times_sem = median_time(step_semantic, reps)
    rss_semantic = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t_dec, times_dec = median_time(step_with_decoders, reps)
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "method": method,
        "widths": list(config.widths), "stem": f"{config.stem_width} ch, {config.stem_kernel_size}^3",
        "parameters": sum(p.numel() for p in net.parameters()), "gaussians": int(means.shape[0]),
        "voxels_finest": len(vox.voxels.sites),
        "semantic_fwd_bwd_median_s": t_sem, "semantic_fwd_bwd_all_s": times_sem,
        "peak_rss_semantic_mb": rss_semantic / 1024, "rss_before_mb": rss_before / 1024,
        "with_decoders_fwd_bwd_median_s": t_dec, "with_decoders_fwd_bwd_all_s": times_dec,
        "peak_rss_with_decoders_mb": rss_after / 1024,
        "threads": torch.get_num_threads(),
    }


def bench_net_interleaved(width: str, reps: int, methods: list[str]) -> dict:
    """Semantic-phase step (backbone + adapter, fwd + bwd) of one net, conv methods run round-robin in
    one process (the load hits them alike; peak memory is not separated here)."""
    import functools

    import ovgaussian.sparse.conv as conv_module
    from ovgaussian.model.network import OVGaussianNet
    from ovgaussian.model.config import OVGaussianNetConfig

    original = conv_module.sparse_conv
    config = OVGaussianNetConfig() if width == "default" else OVGaussianNetConfig.slim()
    net = OVGaussianNet(config)
    means, attrs, batch = room_gaussians(3, 50_000, seed=2)
    upstream = torch.randn(means.shape[0], config.semantic_width, generator=torch.Generator().manual_seed(3))

    def step(method):
        conv_module.sparse_conv = functools.partial(original, method=method)
        net.zero_grad(set_to_none=True)
        (net(means, attrs, batch) * upstream).sum().backward()

    try:
        medians = interleaved_medians({f"{m}_semantic_fwd_bwd_s": functools.partial(step, m) for m in methods}, reps)
    finally:
        conv_module.sparse_conv = original
    return {"widths": list(config.widths), "reps": reps, **medians}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("part", nargs="?", default="all", choices=["conv", "net", "net-interleaved", "all", "_net_one"])
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--width", default="slim")
    parser.add_argument("--widths", default="slim,default", help="net: comma-separated widths to run")
    parser.add_argument("--methods", default="gemm,scatter", help="net: comma-separated conv methods")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.part == "_net_one":
        print(json.dumps(bench_net_one(args.width, args.reps, args.methods.split(",")[0])))
        return
    results = {}
    if args.part == "net-interleaved":
        for width in args.widths.split(","):
            result = bench_net_interleaved(width, args.reps, args.methods.split(","))
            print(json.dumps({f"net_interleaved_{width}": result}, indent=1), flush=True)
        return
    if args.part in ("conv", "all"):
        for distribution in ("uniform", "surface"):
            results[f"conv_{distribution}"] = bench_conv(args.reps, distribution)
            print(json.dumps({f"conv_{distribution}": results[f"conv_{distribution}"]}, indent=1), flush=True)
    if args.part in ("net", "all"):
        for width in args.widths.split(","):
            for method in args.methods.split(","):  # alternate methods per width (load drifts)
                proc = subprocess.run(
                    [sys.executable, __file__, "_net_one", "--width", width, "--reps", str(max(1, args.reps // 2)),
                     "--threads", str(args.threads), "--methods", method], capture_output=True, text=True, cwd=REPO,
                )
                name = f"net_{width}_{method}"
                if proc.returncode:
                    results[name] = {"error": proc.stderr.strip().splitlines()[-1]}
                else:
                    results[name] = json.loads(proc.stdout.strip().splitlines()[-1])
                print(json.dumps({name: results[name]}, indent=1), flush=True)


if __name__ == "__main__":
    main()
