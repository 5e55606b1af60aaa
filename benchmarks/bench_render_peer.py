"""Our CPU rasterizer side by side with taichi-splatting 0.13.0 run on the CPU (image agreement and wall times).

Set-up (from the repository root; the peer lives in its own venv OUTSIDE the repository, never in .venv, whose
CPU torch pip could replace). The peer venv uses .venv's interpreter and sees .venv's packages (torch, numba,
numpy, tqdm, rich, dill, our editable install) through a .pth file; pip gets ``--no-deps`` so it never pulls a
torch (tensordict declares torch; taichi-splatting 0.13.0 declares taichi-nightly, not the taichi release):

    .venv/bin/python -m venv ../peer-venv
    echo "import site; site.addsitedir('$PWD/.venv/lib/python3.11/site-packages')" \\
        > ../peer-venv/lib/python3.11/site-packages/seggaussian-venv.pth
    ../peer-venv/bin/pip install --no-deps taichi==1.7.4 taichi-splatting==0.13.0 tensordict==0.15.3 \\
        pyvers==0.2.3 colorama==0.4.6 beartype==0.23.1

Run:

    ../peer-venv/bin/python benchmarks/bench_render_peer.py [--repeats 5] [--threads 2] [--skip-large] [--json]
    ../peer-venv/bin/python benchmarks/bench_render_peer.py --num 20000 --width 320 --height 240   # one case
    ../peer-venv/bin/python -m pytest tests/seggaussian/render/test_render_peer_bench.py

Without taichi / taichi_splatting the script exits with status 2 and a one-line message. It installs nothing.
The script turns off taichi's start-up version check (``TI_SKIP_VERSION_CHECK=ON``: it would contact taichi's
server) and its banner.

Cases: 20,000 Gaussians at 320x240 and 1,000,000 at 876x584, the scene of benchmarks/bench_render.py
(``make_scene``: N Gaussians in a 2 m cube seen from 3 m, SH degree 0); forward, and forward+backward of
``loss = sum(image * W)`` (W a fixed random [H, W, 3] weight) with gradients to means, scales, quaternions,
opacities and colours (SH) on both sides. Both sides run in this one process, alternated (ours, peer, ours,
peer, ...), each call on fresh leaf tensors; the table gives the medians of the wall times (and of the process
CPU times, summed over threads: under load, when the wall times mostly measure waiting for a core). Thread counts:
ours ``numba.set_num_threads(T)`` + ``torch.set_num_threads(T)``, the peer ``ti.init(cpu_max_num_threads=T)``
+ the same torch threads (its cumsum, sort and tensor glue run in torch).

What runs on the peer side: the peer's own code (frustum culling, SH, EWA projection and its autodiff backward,
depth keys, tile overlap counting with its oriented-box test, key generation, tile ranges, its autograd
function), except its two GPU-only pieces, ported here to the CPU:

- ``cuda_lib`` (CUB exclusive scan and CUB ``DeviceRadixSort::SortPairs`` on 48-bit keys
  ``tile_id << 32 | float32 depth bits``; the real module compiles CUDA sources when imported): a CPU stand-in
  module with ``torch.cumsum`` and ``torch.sort(keys, stable=True)`` (stable, as CUB's radix sort; torch's CPU
  builds with FBGEMM and OpenMP sort 1-D integer keys of >= 32k elements with a parallel LSD radix sort) plus a
  gather of the values. Its wall time is reported separately ("peer sort", part of the peer's forward time).
- the shared-memory tile kernels (forward: 256 threads a tile, batches of Gaussians loaded into shared memory;
  backward: 2x2 pixels a thread, warp and block reductions, one atomic add per Gaussian and tile): written
  anew in taichi on the CPU arch (this file, ``_port_forward_kernel`` / ``_port_backward_kernel``). Forward:
  one iteration per pixel (parallel over tiles x 256 pixels), each pixel walking its tile's list front to back
  and stopping when saturated. Backward: parallel over tiles; each tile walks its list back to front with a
  loop over its 256 pixels inside (per-pixel transmittance and colour-behind state in scratch arrays), sums
  the gradient of each (tile, Gaussian) pair in registers and adds it with one atomic add: the CPU
  counterpart of the peer's warp/block reductions. The blending and gradient formulas are the peer's (read
  from its source, re-implemented, not copied).

Conventions converted / differences removed so that both sides render the same image:

- quaternions: the peer's are (x, y, z, w) (its ``quat_to_mat``; its Gaussians3D comment says wxyz, the code
  reads xyzw), ours (w, x, y, z): reordered once before timing.
- opacity: both take logits (sigmoid); the peer's are [N, 1]. Scales: both take log-scales (exp).
- SH: the peer's layout is [N, 3, K], ours [N, K, 3] (transposed once); the peer clamps colours to [0, 1], ours
  only below at 0, so the DC coefficients are clipped to keep every colour <= 1 (a handful of Gaussians; the
  count is printed). Degree 0 only: for degree > 0 the peer's view direction is Gaussian -> camera, ours
  camera -> Gaussian, so odd bands would need their sign flipped.
- camera: both are OpenCV pinhole (x right, y down, z forward), pixel centres at +0.5; the peer's
  ``T_image_camera`` is our K, its ``T_camera_world`` our viewmat (float32 on its side). Near/far planes set to
  ours (0.01, 1e10); its ``blur_cov`` (0.3) equals our COV2D_DILATION.
- culling: the peer keeps Gaussians whose centre projects within a 48-pixel margin (``margin_tiles`` 3 x 16 px);
  ours keeps every Gaussian whose 3-sigma box reaches the image. The peer's margin is widened (per case) to the
  farthest off-image centre among the Gaussians ours keeps, so both blend the same Gaussians.
- per-pixel cut-off: ours skips a Gaussian at a pixel where its Mahalanobis^2 exceeds 3^2 (RADIUS_SIGMAS); the
  peer blends it over every pixel of every tile its 3-sigma oriented box touches. The ported kernels apply our
  per-pixel cut (``gaussian_scale``^2, its tiles cover the whole 3-sigma ellipse) and our gradient rule at the
  0.99 alpha clamp (no gradient to opacity / geometry where the alpha is clamped; the peer passes one). Cost:
  one compare per Gaussian-pixel pair. ``--peer-semantics`` times the peer's own rules instead (no per-pixel
  cut, 48 px margin); the PSNR under the peer's own rules is printed in any case.
- depth: ours always blends camera z as a 4th channel (for its depth output); the peer blends rgb + its camera z
  (``depth_vars[:, 0]``) as 4 features, the same work (its own ``render_depth`` would blend 3 extra channels).
- alpha: the peer's rasterizer passes no gradient through the accumulated alpha, so the loss uses the image only.

Residual differences: the peer projects in float32 with the world-to-camera matrix, ours in float64 on
recentred means; ours clamps the projection Jacobian at 1.3x the half field of view (3DGS), the peer does not
(matters only for Gaussians centred far outside the image); ours evaluates exp with a polynomial (rel. error
< 2e-6); ours orders by float64 depth, the peer by float32 depth (ties: index order on both sides). These
rounding differences flip a per-pixel test (3-sigma cut, alpha >= 1/255, transmittance >= 1e-4) now and then: at
20k Gaussians and 320x240, 2 of 76,800 pixels differ by more than 1e-4 (at most 6e-3), PSNR about 94 dB, gradients
within 4e-4 (relative L2); under the peer's own rules (no per-pixel cut) the PSNR is about 58 dB.
"""

# no "from __future__ import annotations": taichi reads the kernels' annotations as objects

import argparse
import contextlib
import dataclasses
import functools
import importlib
import json
import math
import os
import statistics
import sys
import sysconfig
import time
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

REPO = Path(__file__).resolve().parents[1]
SCRIPT = Path(__file__).resolve()
#: What the peer venv gets, all with ``pip install --no-deps`` (the rest comes from .venv through the .pth file).
PEER_VERSIONS = ("taichi==1.7.4 taichi-splatting==0.13.0 tensordict==0.15.3 pyvers==0.2.3 colorama==0.4.6 "
                 "beartype==0.23.1")
#: Exit status when the peer is not importable.
EXIT_NO_PEER = 2
#: Cases of the default run: (Gaussians, width, height).
SMALL_CASE = (20_000, 320, 240)
LARGE_CASE = (1_000_000, 876, 584)


# --------------------------------------------------------------------------------------------------------------
# the peer: import with the CPU stand-in for its CUDA library


class SortClock:
    """Wall time of every call of the stand-in sort (and the number of keys), reset by the caller."""

    def __init__(self) -> None:
        self.seconds: list[float] = []
        self.keys: list[int] = []

    def reset(self) -> None:
        self.seconds.clear()
        self.keys.clear()

    def total(self) -> float:
        return sum(self.seconds)


SORT_CLOCK = SortClock()


def _cpu_cuda_lib() -> types.ModuleType:
    """A module with the interface of ``taichi_splatting.cuda_lib``, computed on the CPU with torch."""
    import torch

    module = types.ModuleType("taichi_splatting.cuda_lib")

    def full_cumsum(x: torch.Tensor) -> tuple[torch.Tensor, int]:
        """Exclusive prefix sum with the total appended (CUB ExclusiveSum + the last element), and the total."""
        out = x.new_zeros((x.shape[0] + 1, *x.shape[1:]))
        if x.shape[0]:
            torch.cumsum(x, 0, dtype=x.dtype, out=out[1:])
        return out, int(out[-1])

    def radix_sort_pairs(keys: torch.Tensor, values: torch.Tensor, start_bit: int = 0, end_bit: int | None = None,
                         unsigned: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Stable sort of (keys, values) by keys (the peer's keys are non-negative and < 2^end_bit)."""
        t0 = time.perf_counter()
        sorted_keys, order = torch.sort(keys, stable=True)
        sorted_values = values[order]
        SORT_CLOCK.seconds.append(time.perf_counter() - t0)
        SORT_CLOCK.keys.append(int(keys.shape[0]))
        return sorted_keys, sorted_values

    def segmented_sort_pairs(*args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError("segmented_sort_pairs is not ported (the tile mapper used here does not call it)")

    module.full_cumsum = full_cumsum
    module.radix_sort_pairs = radix_sort_pairs
    module.segmented_sort_pairs = segmented_sort_pairs
    module.__file__ = __file__
    return module


def no_peer_message(reason: str) -> str:
    """The one-line message printed when taichi / taichi_splatting cannot be imported."""
    site = sysconfig.get_path("purelib")
    ver = f"python{sys.version_info[0]}.{sys.version_info[1]}"
    return (f"bench_render_peer: needs taichi and taichi_splatting ({reason}); run it from a separate venv that sees "
            f"this interpreter's packages (never pip-install them into .venv): {sys.executable} -m venv ../peer-venv"
            f" && echo \"import site; site.addsitedir('{site}')\" > ../peer-venv/lib/{ver}/site-packages/"
            f"seggaussian-venv.pth && ../peer-venv/bin/pip install --no-deps {PEER_VERSIONS}"
            f" && ../peer-venv/bin/python benchmarks/bench_render_peer.py (see the script's docstring)")


def load_peer(threads: int) -> types.SimpleNamespace:
    """Import taichi (CPU arch, ``threads`` threads) and taichi_splatting with the CPU ``cuda_lib``; exit with a
    one-line message when either is missing."""
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
    os.environ["TI_SKIP_VERSION_CHECK"] = "ON"  # no network call at ti.init
    try:
        ti = importlib.import_module("taichi")
    except ImportError as exc:
        raise SystemExit(_fail(f"cannot import taichi: {exc}"))
    # the real cuda_lib compiles CUDA sources at import time; the stand-in must be in place first
    sys.modules["taichi_splatting.cuda_lib"] = _cpu_cuda_lib()
    with contextlib.redirect_stdout(sys.stderr):  # ti.init prints its arch to stdout (kept clean for --json)
        ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f32, log_level=ti.ERROR)
    try:
        ts = importlib.import_module("taichi_splatting")
        from taichi_splatting.perspective import CameraParams, project_to_image
        from taichi_splatting.rasterizer import function as raster_function
        from taichi_splatting.renderer import gaussians_in_view
        from taichi_splatting.misc.encode_depth import encode_depth
    except ImportError as exc:
        raise SystemExit(_fail(f"cannot import taichi_splatting: {exc}"))
    raster_function.forward_kernel = _port_forward_kernel
    raster_function.backward_kernel = _port_backward_kernel
    return types.SimpleNamespace(ti=ti, ts=ts, CameraParams=CameraParams, project_to_image=project_to_image,
                                 gaussians_in_view=gaussians_in_view, encode_depth=encode_depth,
                                 PortConfig=_port_config_class(ts.RasterConfig))


def _fail(reason: str) -> int:
    print(no_peer_message(reason), file=sys.stderr)
    return EXIT_NO_PEER


def _port_config_class(raster_config: type) -> type:
    @dataclasses.dataclass(frozen=True, eq=True)
    class PortConfig(raster_config):
        """The peer's RasterConfig plus the choice of blending rule in the ported kernels.

        ``ours_rule``: our per-pixel 3-sigma cut (Mahalanobis^2 <= gaussian_scale^2) and no gradient to opacity /
        geometry where alpha is clamped; False: the peer's rules (no per-pixel cut, gradient through the clamp).
        """

        ours_rule: bool = True

    return PortConfig


# --------------------------------------------------------------------------------------------------------------
# the port of the peer's shared-memory tile kernels: plain taichi loops on the CPU arch


@functools.cache
class _KernelConstants(NamedTuple):
    """The compile-time constants both ported kernels read from the peer's config."""

    size: int          # tile edge (pixels)
    area: int          # pixels per tile
    ours: bool         # our 3-sigma per-pixel cut-off and no-gradient rule at the alpha clamp
    cut2: float        # squared Mahalanobis cut-off
    a_min: float       # alpha below this is skipped
    a_max: float       # alpha clamp
    t_min: float       # transmittance at which a pixel saturates


def _kernel_constants(config: Any) -> _KernelConstants:
    size = int(config.tile_size)
    return _KernelConstants(size, size * size, bool(getattr(config, "ours_rule", False)),
                            float(config.gaussian_scale) ** 2, float(config.alpha_threshold),
                            float(config.clamp_max_alpha), 1.0 - float(config.saturate_threshold))


def _port_forward_kernel(config: Any, feature_size: int, dtype: Any = None) -> Callable[..., None]:
    """Same arguments as the peer's ``forward_kernel(config, feature_size, dtype)`` result:
    (points [M, 6] = (u, v, conic a, b, c, opacity), features [M, F], tile_ranges [T, 2], overlap_to_point [K],
    out image [H, W, F], out alpha [H, W], out last [H, W]: one past the last blended list position)."""
    import taichi as ti

    dtype = dtype or ti.f32
    size, area, ours, cut2, a_min, a_max, t_min = _kernel_constants(config)
    fvec = ti.types.vector(feature_size, dtype)
    pvec = ti.types.vector(6, dtype)

    @ti.kernel
    def forward(points: ti.types.ndarray(pvec, ndim=1), features: ti.types.ndarray(fvec, ndim=1),
                tile_ranges: ti.types.ndarray(ti.math.ivec2, ndim=1),
                overlap_to_point: ti.types.ndarray(ti.i32, ndim=1),
                image: ti.types.ndarray(fvec, ndim=2), image_alpha: ti.types.ndarray(dtype, ndim=2),
                image_last: ti.types.ndarray(ti.i32, ndim=2)):
        height, width = image_alpha.shape[0], image_alpha.shape[1]
        tiles_x = (width + size - 1) // size
        tiles_y = (height + size - 1) // size
        ti.loop_config(block_dim=area)
        for tile, i in ti.ndrange(tiles_x * tiles_y, area):
            x = (tile % tiles_x) * size + i % size
            y = (tile // tiles_x) * size + i // size
            if x < width and y < height:
                px = ti.cast(x, dtype) + 0.5
                py = ti.cast(y, dtype) + 0.5
                start, end = tile_ranges[tile][0], tile_ranges[tile][1]
                trans = dtype(1.0)
                acc = fvec(0.0)
                last = start
                for k in range(start, end):
                    p = points[overlap_to_point[k]]
                    dx, dy = px - p[0], py - p[1]
                    s = p[2] * dx * dx + 2.0 * p[3] * dx * dy + p[4] * dy * dy
                    skip = False
                    if ti.static(ours):
                        skip = s > cut2
                    raw = p[5] * ti.exp(-0.5 * s)
                    if not skip and raw >= a_min:
                        alpha = ti.min(raw, a_max)
                        after = trans * (1.0 - alpha)
                        if after < t_min:
                            break
                        acc += features[overlap_to_point[k]] * (alpha * trans)
                        trans = after
                        last = k + 1
                image[y, x] = acc
                image_alpha[y, x] = 1.0 - trans
                image_last[y, x] = last

    return forward


@functools.cache
def _port_backward_kernel(config: Any, points_requires_grad: bool, features_requires_grad: bool,
                          compute_split_heuristics: bool, feature_size: int, dtype: Any = None) -> Callable[..., None]:
    """Same call as the peer's ``backward_kernel(...)`` result: (points, features, tile_ranges, overlap_to_point,
    image_alpha, image_last, grad_image [H, W, F], out grad_points [M, 6], out grad_features [M, F],
    split_heuristics (unused)). The returned function allocates the per-pixel scratch state and runs the kernel."""
    import taichi as ti
    import torch

    if compute_split_heuristics:
        raise NotImplementedError("the ported backward does not compute the peer's split heuristics")
    dtype = dtype or ti.f32
    size, area, ours, cut2, a_min, a_max, _ = _kernel_constants(config)
    fvec = ti.types.vector(feature_size, dtype)
    pvec = ti.types.vector(6, dtype)
    grad_points_on, grad_features_on = bool(points_requires_grad), bool(features_requires_grad)

    @ti.kernel
    def backward(points: ti.types.ndarray(pvec, ndim=1), features: ti.types.ndarray(fvec, ndim=1),
                 tile_ranges: ti.types.ndarray(ti.math.ivec2, ndim=1),
                 overlap_to_point: ti.types.ndarray(ti.i32, ndim=1),
                 image_alpha: ti.types.ndarray(dtype, ndim=2), image_last: ti.types.ndarray(ti.i32, ndim=2),
                 grad_image: ti.types.ndarray(fvec, ndim=2),
                 grad_points: ti.types.ndarray(pvec, ndim=1), grad_features: ti.types.ndarray(fvec, ndim=1),
                 trans: ti.types.ndarray(dtype, ndim=2), behind: ti.types.ndarray(fvec, ndim=2)):
        height, width = image_alpha.shape[0], image_alpha.shape[1]
        tiles_x = (width + size - 1) // size
        tiles_y = (height + size - 1) // size
        ti.loop_config(block_dim=1)
        for tile in range(tiles_x * tiles_y):
            x0 = (tile % tiles_x) * size
            y0 = (tile // tiles_x) * size
            start = tile_ranges[tile][0]
            end = start
            for i in range(area):
                x, y = x0 + i % size, y0 + i // size
                if x < width and y < height:
                    end = ti.max(end, image_last[y, x])
                    trans[y, x] = 1.0 - image_alpha[y, x]  # transmittance behind everything blended
                    behind[y, x] = fvec(0.0)  # sum of weight * feature of the Gaussians behind
            for j in range(end - start):
                k = end - 1 - j
                g = overlap_to_point[k]
                p = points[g]
                f = features[g]
                d_point = pvec(0.0)
                d_feature = fvec(0.0)
                hit = False
                for i in range(area):
                    x, y = x0 + i % size, y0 + i // size
                    if x < width and y < height:
                        if k < image_last[y, x]:
                            dx = ti.cast(x, dtype) + 0.5 - p[0]
                            dy = ti.cast(y, dtype) + 0.5 - p[1]
                            s = p[2] * dx * dx + 2.0 * p[3] * dx * dy + p[4] * dy * dy
                            skip = False
                            if ti.static(ours):
                                skip = s > cut2
                            gauss = ti.exp(-0.5 * s)
                            raw = p[5] * gauss
                            if not skip and raw >= a_min:
                                hit = True
                                alpha = ti.min(raw, a_max)
                                keep = 1.0 - alpha
                                t_front = trans[y, x] / keep  # transmittance in front of this Gaussian
                                trans[y, x] = t_front
                                weight = alpha * t_front
                                d_pixel = grad_image[y, x]
                                d_feature += weight * d_pixel
                                d_alpha = ((f * t_front - behind[y, x] / keep) * d_pixel).sum()
                                behind[y, x] += f * weight
                                if ti.static(ours):
                                    if raw > a_max:
                                        d_alpha = 0.0
                                # alpha = opacity * exp(-s / 2), s = a dx^2 + 2 b dx dy + c dy^2, dx = px - u
                                d_s = -0.5 * d_alpha * raw
                                d_point += pvec(-d_s * 2.0 * (p[2] * dx + p[3] * dy),
                                                -d_s * 2.0 * (p[3] * dx + p[4] * dy),
                                                d_s * dx * dx, d_s * 2.0 * dx * dy, d_s * dy * dy,
                                                d_alpha * gauss)
                if hit:
                    if ti.static(grad_points_on):
                        ti.atomic_add(grad_points[g], d_point)
                    if ti.static(grad_features_on):
                        ti.atomic_add(grad_features[g], d_feature)

    def run(points: torch.Tensor, features: torch.Tensor, tile_ranges: torch.Tensor, overlap_to_point: torch.Tensor,
            image_alpha: torch.Tensor, image_last: torch.Tensor, grad_image: torch.Tensor, grad_points: torch.Tensor,
            grad_features: torch.Tensor, split_heuristics: torch.Tensor) -> None:
        h, w = image_alpha.shape
        trans = torch.empty((h, w), dtype=image_alpha.dtype)
        behind = torch.empty((h, w, feature_size), dtype=image_alpha.dtype)
        backward(points, features, tile_ranges, overlap_to_point, image_alpha, image_last, grad_image,
                 grad_points, grad_features, trans, behind)

    return run


# --------------------------------------------------------------------------------------------------------------
# the two renderers on one scene


@dataclasses.dataclass
class Case:
    """One scene in both layouts, the camera of both sides and the loss weights."""

    num: int
    width: int
    height: int
    ours: dict  # means, quats (w, x, y, z), log_scales, opacity_logits [N], sh [N, K, 3]
    peer: dict  # position, rotation (x, y, z, w), log_scaling, alpha_logit [N, 1], feature [N, 3, K]
    viewmat: Any
    K: Any
    camera: Any  # taichi_splatting CameraParams
    loss_weights: Any  # [H, W, 3]
    sh_clipped: int
    margin_tiles: int


def make_case(peer: types.SimpleNamespace, num: int, width: int, height: int) -> Case:
    """The benchmark scene of bench_render.py converted to the peer's conventions (see the module docstring)."""
    import torch

    if str(SCRIPT.parent) not in sys.path:
        sys.path.insert(0, str(SCRIPT.parent))
    from bench_render import make_scene  # the scene of benchmarks/bench_render.py

    from seggaussian.render import projection as ours_projection
    from seggaussian.core.constants import SH_C0
    from seggaussian.render.projection_numba import project_gaussians_fast

    scene, viewmat, K = make_scene(num, width, height)
    sh = scene["sh"]
    if sh.shape[1] != 1:
        raise ValueError("bench_render_peer: SH degree 0 only (the peer's view direction is reversed)")
    top = (1.0 - 0.5) / SH_C0 * (1.0 - 1e-6)  # colour = SH_C0 * sh + 0.5 stays <= 1 (the peer's clamp)
    clipped = int((sh > top).any(-1).sum())  # Gaussians with a clipped channel
    scene["sh"] = sh.clamp(max=top)
    if abs(peer.CameraParams.blur_cov - ours_projection.COV2D_DILATION) > 0:
        raise ValueError("bench_render_peer: the peer's blur_cov differs from our COV2D_DILATION")

    # widen the peer's centre-based culling margin to everything ours keeps (ours culls by the 3-sigma box)
    with torch.no_grad():
        proj = project_gaussians_fast(scene["means"], scene["quats"], scene["log_scales"], viewmat, K, width, height)
        m2 = proj.means2d[proj.valid]
        off = torch.cat([-m2[:, 0], m2[:, 0] - width, -m2[:, 1], m2[:, 1] - height, torch.zeros(1, dtype=m2.dtype)])
    tile = int(peer.ts.RasterConfig().tile_size)
    margin_tiles = max(3, int(math.ceil((float(off.max()) + 1.0) / tile)))

    peer_params = {
        "position": scene["means"].clone(),
        "rotation": scene["quats"][:, [1, 2, 3, 0]].contiguous(),
        "log_scaling": scene["log_scales"].clone(),
        "alpha_logit": scene["opacity_logits"][:, None].contiguous(),
        "feature": scene["sh"].transpose(1, 2).contiguous(),
    }
    camera = peer.CameraParams(T_image_camera=K.float(), T_camera_world=viewmat.float(),
                               near_plane=float(ours_projection.NEAR_PLANE), far_plane=float(ours_projection.FAR_PLANE),
                               image_size=(width, height))
    gen = torch.Generator().manual_seed(1)
    weights = torch.rand((height, width, 3), generator=gen)
    return Case(num, width, height, scene, peer_params, viewmat, K, camera, weights, clipped, margin_tiles)


def ours_render(case: Case, leaves: dict) -> tuple[Any, Any]:
    """Our full pipeline (projection, SH, binning, blending): (image [H, W, 3], alpha [H, W])."""
    from seggaussian.render import rasterize

    out = rasterize(leaves["means"], leaves["quats"], leaves["log_scales"], leaves["opacity_logits"], case.viewmat,
                    case.K, case.width, case.height, sh=leaves["sh"], backend="fast")
    return out.image, out.alpha


def peer_render(peer: types.SimpleNamespace, case: Case, leaves: dict, config: Any) -> tuple[Any, Any]:
    """The peer's ``render_gaussians`` sequence (culling, SH, projection, depth keys, tile mapping, blending) with
    4 features (rgb + camera z, as ours blends): (image [H, W, 3], alpha [H, W])."""
    import torch

    gaussians = peer.ts.Gaussians3D(batch_size=(case.num,), **leaves)
    cam = case.camera
    indexes = peer.gaussians_in_view(leaves["position"], cam, config.tile_size, config.margin_tiles)
    colours = peer.ts.evaluate_sh_at(leaves["feature"], leaves["position"].detach(), indexes, cam.camera_position)
    gaussians2d, depth_vars = peer.project_to_image(gaussians, indexes, cam)
    depth_key = peer.encode_depth(depth_vars, depth_range=(cam.near_plane, cam.far_plane))
    features = torch.cat([colours, depth_vars[:, :1]], 1).contiguous()
    raster = peer.ts.rasterize(gaussians2d, depth_key, features, image_size=cam.image_size, config=config)
    return raster.image[..., :3], raster.image_weight


def leaves_of(params: dict, grad: bool) -> dict:
    return {k: v.clone().requires_grad_(grad) for k, v in params.items()}


def psnr(a: Any, b: Any) -> float:
    """PSNR (dB, peak 1) of image ``a`` against ``b``."""
    mse = float(((a.double() - b.double()) ** 2).mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def gradient_agreement(peer: types.SimpleNamespace, case: Case, config: Any) -> dict:
    """Relative L2 difference ||g_peer - g_ours|| / ||g_ours|| of the gradient of the loss per parameter."""
    ours = leaves_of(case.ours, True)
    image, _ = ours_render(case, ours)
    (image * case.loss_weights).sum().backward()
    theirs = leaves_of(case.peer, True)
    image, _ = peer_render(peer, case, theirs, config)
    (image * case.loss_weights).sum().backward()
    pairs = {
        "means": (theirs["position"].grad, ours["means"].grad),
        "log_scales": (theirs["log_scaling"].grad, ours["log_scales"].grad),
        "quats": (theirs["rotation"].grad[:, [3, 0, 1, 2]], ours["quats"].grad),
        "opacity_logits": (theirs["alpha_logit"].grad[:, 0], ours["opacity_logits"].grad),
        "sh": (theirs["feature"].grad.transpose(1, 2), ours["sh"].grad),
    }
    return {k: float((p.double() - o.double()).norm() / o.double().norm().clamp_min(1e-30))
            for k, (p, o) in pairs.items()}


def alternate(fns: dict[str, Callable[[], None]], repeats: int, after: Callable[[str], None] | None = None
              ) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """(wall times, process CPU times) of ``repeats`` calls of each function, interleaved (A B A B ...), after one
    warm-up call each. The CPU time sums every thread of the process (insensitive to waiting for a core)."""
    for fn in fns.values():
        fn()
    walls: dict[str, list[float]] = {k: [] for k in fns}
    cpus: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            SORT_CLOCK.reset()
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            walls[name].append(time.perf_counter() - t0)
            cpus[name].append(time.process_time() - c0)
            if after is not None:
                after(name)
    return walls, cpus


def run_case(peer: types.SimpleNamespace, num: int, width: int, height: int, repeats: int, peer_semantics: bool
             ) -> dict:
    import torch

    from seggaussian.render.projection_numba import project_gaussians_fast
    from seggaussian.render.tiles import bin_gaussians

    case = make_case(peer, num, width, height)
    matched = peer.PortConfig(margin_tiles=case.margin_tiles, ours_rule=True)
    published = peer.PortConfig(ours_rule=False)  # the peer's own rules and 48 px margin
    timed = "peer" if peer_semantics else "ours"
    config = published if peer_semantics else matched

    with torch.no_grad():
        ours_image, ours_alpha = ours_render(case, case.ours)
        images = {rules: peer_render(peer, case, case.peer, cfg) for rules, cfg in (("ours", matched),
                                                                                     ("peer", published))}
        proj = project_gaussians_fast(case.ours["means"], case.ours["quats"], case.ours["log_scales"], case.viewmat,
                                      case.K, width, height)
        ours_isect = bin_gaussians(proj, width, height, torch.sigmoid(case.ours["opacity_logits"])).num_intersections
    SORT_CLOCK.reset()
    with torch.no_grad():
        peer_render(peer, case, case.peer, config)
    peer_isect = sum(SORT_CLOCK.keys)
    grads = gradient_agreement(peer, case, config)

    def forward(side: str) -> Callable[[], None]:
        def run() -> None:
            with torch.no_grad():
                if side == "ours":
                    ours_render(case, leaves_of(case.ours, False))
                else:
                    peer_render(peer, case, leaves_of(case.peer, False), config)
        return run

    def forward_backward(side: str) -> Callable[[], None]:
        def run() -> None:
            if side == "ours":
                image, _ = ours_render(case, leaves_of(case.ours, True))
            else:
                image, _ = peer_render(peer, case, leaves_of(case.peer, True), config)
            (image * case.loss_weights).sum().backward()
        return run

    sort_s: list[float] = []

    def record_sort(name: str) -> None:
        if name == "peer":
            sort_s.append(SORT_CLOCK.total())

    fwd, fwd_cpu = alternate({"ours": forward("ours"), "peer": forward("peer")}, repeats, record_sort)
    sort_fwd = list(sort_s)
    fwdbwd, fwdbwd_cpu = alternate({"ours": forward_backward("ours"), "peer": forward_backward("peer")}, repeats)
    med = {k: statistics.median(v) for k, v in fwd.items()}
    med_b = {k: statistics.median(v) for k, v in fwdbwd.items()}
    return {
        "num_gaussians": num, "width": width, "height": height,
        "forward_ours_s": med["ours"], "forward_peer_s": med["peer"],
        "forward_backward_ours_s": med_b["ours"], "forward_backward_peer_s": med_b["peer"],
        "forward_ours_cpu_s": statistics.median(fwd_cpu["ours"]),
        "forward_peer_cpu_s": statistics.median(fwd_cpu["peer"]),
        "forward_backward_ours_cpu_s": statistics.median(fwdbwd_cpu["ours"]),
        "forward_backward_peer_cpu_s": statistics.median(fwdbwd_cpu["peer"]),
        "forward_ours_all_s": fwd["ours"], "forward_peer_all_s": fwd["peer"],
        "forward_backward_ours_all_s": fwdbwd["ours"], "forward_backward_peer_all_s": fwdbwd["peer"],
        "peer_sort_s": statistics.median(sort_fwd),
        # image agreement of the timed peer configuration, then of both rule sets
        "psnr_db": psnr(images[timed][0], ours_image),
        "psnr_alpha_db": psnr(images[timed][1], ours_alpha),
        "max_abs_diff": float((images[timed][0] - ours_image).abs().max()),
        "psnr_ours_rules_db": psnr(images["ours"][0], ours_image),
        "psnr_peer_own_rules_db": psnr(images["peer"][0], ours_image),
        "gradient_relative_l2": grads,
        "intersections_ours": ours_isect, "intersections_peer": peer_isect,
        "peer_margin_px": case.margin_tiles * 16, "sh_clipped": case.sh_clipped,
        "peer_rules_timed": timed,
    }


def markdown(results: dict) -> str:
    lines = [
        "| case | ours ms | peer ms | ratio (peer / ours) | PSNR dB | ours CPU ms | peer CPU ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results["cases"]:
        name = f"{r['num_gaussians']:,} Gaussians at {r['width']}x{r['height']}"
        for label, key in (("forward", "forward"), ("forward+backward", "forward_backward")):
            a, b = r[f"{key}_ours_s"], r[f"{key}_peer_s"]
            lines.append(f"| {name}, {label} | {a * 1e3:.1f} | {b * 1e3:.1f} | {b / a:.2f} | {r['psnr_db']:.1f} "
                         f"| {r[f'{key}_ours_cpu_s'] * 1e3:.1f} | {r[f'{key}_peer_cpu_s'] * 1e3:.1f} |")
    lines.append("")
    for r in results["cases"]:
        grads = ", ".join(f"{k} {v:.1e}" for k, v in r["gradient_relative_l2"].items())
        lines += [
            f"- {r['num_gaussians']:,} at {r['width']}x{r['height']}: peer sort (torch.sort stable, "
            f"{r['intersections_peer']:,} keys) {r['peer_sort_s'] * 1e3:.1f} ms of the peer's forward "
            f"(median); tile intersections ours {r['intersections_ours']:,}, peer {r['intersections_peer']:,}; "
            f"PSNR alpha {r['psnr_alpha_db']:.1f} dB, max |diff| {r['max_abs_diff']:.2e}; PSNR with our rules in the "
            f"port {r['psnr_ours_rules_db']:.1f} dB, with the peer's own rules (no per-pixel cut-off, 48 px margin) "
            f"{r['psnr_peer_own_rules_db']:.1f} dB; gradient "
            f"relative L2 difference: {grads}; peer margin {r['peer_margin_px']} px; SH clipped: {r['sh_clipped']}; "
            f"peer timed with {r['peer_rules_timed']} rules",
        ]
    lines += [
        "",
        f"Command: `{results['command']}`; {results['threads']} threads each side; load average "
        f"{results['load_average'][0]:.2f} {results['load_average'][1]:.2f} {results['load_average'][2]:.2f} "
        f"on {results['cpu_count']} cores at the end; repeats {results['repeats']} (alternated, medians).",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--skip-large", action="store_true", help="only the 20k case")
    parser.add_argument("--num", type=int, help="one case of this many Gaussians (with --width, --height)")
    parser.add_argument("--width", type=int, default=SMALL_CASE[1])
    parser.add_argument("--height", type=int, default=SMALL_CASE[2])
    parser.add_argument("--peer-semantics", action="store_true",
                        help="time the peer with its own rules (no per-pixel cut-off, 48 px margin)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON instead of markdown")
    parser.add_argument("--out", type=Path, help="also write the markdown to this file")
    args = parser.parse_args(argv)

    # our package first, as every seggaussian command does: before torch starts its OpenMP pool it sets
    # OMP_WAIT_POLICY=PASSIVE, numba's threading layer and numba's kernel cache folder (seggaussian/__init__.py);
    # the peer's torch calls share that pool
    importlib.import_module("seggaussian")
    peer = load_peer(args.threads)
    import numba
    import torch

    if args.threads > numba.config.NUMBA_NUM_THREADS:
        print(f"bench_render_peer: --threads {args.threads} exceeds NUMBA_NUM_THREADS={numba.config.NUMBA_NUM_THREADS}",
              file=sys.stderr)
        return 1
    numba.set_num_threads(args.threads)
    torch.set_num_threads(args.threads)

    cases = [(args.num, args.width, args.height)] if args.num else [SMALL_CASE] + ([] if args.skip_large else
                                                                                   [LARGE_CASE])
    results: dict = {"cases": [run_case(peer, n, w, h, args.repeats, args.peer_semantics) for n, w, h in cases]}
    python = os.path.relpath(sys.executable, REPO) if Path(sys.executable).is_absolute() else sys.executable
    results.update(command=" ".join([python, "benchmarks/bench_render_peer.py", *sys.argv[1:]]),
                   threads=args.threads, load_average=list(os.getloadavg()), cpu_count=os.cpu_count(),
                   repeats=args.repeats, taichi=peer.ti.__version__, torch=torch.__version__)
    text = markdown(results)
    print(json.dumps(results, indent=1) if args.json else text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
