"""Fit 3D Gaussians to a scene's posed images on the CPU (3D Gaussian Splatting, Kerbl et al. 2023).

Data flow: ``validate_scene`` -> ``load_views`` (images as float tensors, optional downscale) ->
``initialize_gaussians`` (voxel-averaged points, scales from nearest neighbours) -> ``fit_scene``
(Adam with the 3DGS learning rates, L1 + D-SSIM loss, densification by the accumulated view-space
gradient, pruning, opacity resets, evaluation and early stop) -> ``FitResult``.

View-space gradient used for densification: the shared rasterizer returns no screen-space means, so
the gradient of the loss with respect to each Gaussian's projected centre is recovered from the
gradient with respect to its 3D mean: rotated into the camera frame, its x/y components times
``z / f`` give the derivative with respect to the pixel position of the centre (exact for the mean's
path through the projection; the small contribution of the mean through the projection Jacobian of the
covariance and the SH view direction is included, not removed), then scaled by ``W/2`` and ``H/2`` to
normalized device coordinates as in the 3DGS reference, whose threshold 2e-4 therefore applies.

Every per-Gaussian tensor (parameters, densification statistics) and the Adam state of each
parameter (``exp_avg``, ``exp_avg_sq``) live in one ``GaussianParameters`` object whose ``select``
and ``append`` keep them row-aligned.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.cameras import Camera
from seggaussian.constants import NEAR_PLANE, QUAT_NORM_EPS, RADIUS_SIGMAS, SH_C0
from seggaussian.fit_config import FitConfig
from seggaussian.gaussians import Gaussians
from seggaussian.rotations import quats_to_rotmats_torch
from seggaussian.scene import Scene
from seggaussian.sources._common import read_valid_mask
from seggaussian.sources.layout import find_scene_layout, reader
from seggaussian.transfer import nearest_neighbours

if TYPE_CHECKING:
    import torch

#: Smallest initial nearest-neighbour distance (metres): duplicate points would otherwise give
#: log(0) = -inf scales.
INIT_MIN_NN_DISTANCE = 1e-7
#: Scene extents below this (metres) are degenerate (one camera, or all cameras at one spot);
#: the extent then falls back to the initial points' bounding box.
MIN_SCENE_EXTENT = 1e-6
#: 3DGS scales the camera-centre radius by this factor to get the scene extent.
EXTENT_MARGIN = 1.1
#: Floor of an opacity before taking its logit (keeps the logit finite).
OPACITY_LOGIT_EPS = 1e-6

#: Adam's denominator epsilon (3DGS: 1e-15); the moments of Gaussians outside every view stay 0 and
#: their update 0/(0 + eps) = 0.
ADAM_EPS = 1e-15

#: Modes of the build stage's ``--fit`` option.
FIT_MODES = ("auto", "always", "never")

PARAMETER_NAMES = ("means", "quats", "log_scales", "opacity_logits", "f_dc", "f_rest")


class FitInputError(ValueError):
    """A scene that cannot be fitted; the message names the scene, the file or view, and the field."""


class FitResult(NamedTuple):
    """Result of ``fit_scene``.

    Fields:
        gaussians: the fitted Gaussians (SH degree ``config.sh_degree``).
        metrics: novel-view PSNR/SSIM/L1 (``None`` without novel views), iterations run, seconds,
            early-stop reason, Gaussian counts, scene extent, image size, seed.
        history: one dict per evaluation (iteration, seconds, mean training loss since the previous
            evaluation, held-out PSNR, Gaussians), starting with iteration 0 (the initialization).
    """

    gaussians: Gaussians
    metrics: dict
    history: list


class FitProgress(NamedTuple):
    """What ``fit_scene`` hands its ``on_iteration`` callback after every iteration.

    Fields:
        iteration: the iteration just finished (1-based).
        num_gaussians: current number of Gaussians.
        seconds: wall time since the fit started.
        evaluate_novel: renders the novel views now and returns their mean ``psnr``, ``ssim``, ``l1``
            (``None`` when the scene has no novel views).
    """

    iteration: int
    num_gaussians: int
    seconds: float
    evaluate_novel: Callable[[], "dict | None"]


class ViewData(NamedTuple):
    """A view ready for fitting: camera at the processed size and its image."""

    name: str
    camera: Camera
    image: "torch.Tensor"  # [H, W, 3] float32 in [0, 1]
    viewmat: "torch.Tensor"  # [4, 4] float32
    K: "torch.Tensor"  # [3, 3] float32
    valid: "torch.Tensor | None" = None  # [H, W] bool, False on anonymized pixels; None = all valid


def masked_render(image: "torch.Tensor", view: ViewData) -> "torch.Tensor":
    """The render ``[H, W, 3]`` with its anonymized pixels replaced by the target's: those pixels add
    nothing to L1, D-SSIM or PSNR and pass no gradient (the anonymization masks' pixels are ignored)."""
    import torch

    if view.valid is None:
        return image
    return torch.where(view.valid[..., None], image, view.image)


def needs_fit(mode: str, trained_ply_path: str | Path | None) -> bool:
    """Whether the build stage must fit Gaussians: ``always`` yes, ``never`` no, ``auto`` only when no
    trained PLY is given. A trained PLY that is given but missing is an error, not a silent refit."""
    if mode not in FIT_MODES:
        raise ValueError(f"fit mode must be one of {', '.join(FIT_MODES)}, got {mode!r}")
    if trained_ply_path is not None and mode != "always" and not Path(trained_ply_path).is_file():
        raise FileNotFoundError(f"trained PLY {trained_ply_path}: no such file")
    if mode == "always":
        return True
    if mode == "never":
        return False
    return trained_ply_path is None


# --- input ---------------------------------------------------------------------------------------


def validate_scene(scene: Scene) -> None:
    """Raise ``FitInputError`` for a scene that cannot be fitted (no views, no points, bad poses)."""
    sid = scene.scene_id
    if not scene.views_with_role("train"):
        raise FitInputError(f"scene {sid}: no train views to fit (views: {len(scene.views)})")
    if scene.points.shape[0] == 0:
        raise FitInputError(f"scene {sid}: no initial points (Scene.points is empty)")
    if not np.isfinite(scene.points).all():
        bad = int((~np.isfinite(scene.points).all(axis=1)).sum())
        raise FitInputError(f"scene {sid}: Scene.points has {bad} non-finite rows")
    for view in scene.views:
        cam = view.camera
        if not (np.isfinite(cam.viewmat).all() and np.isfinite(cam.K).all()):
            raise FitInputError(f"scene {sid}, view {view.name}: camera viewmat or K is not finite")
        if abs(np.linalg.det(cam.viewmat[:3, :3]) - 1.0) > 1e-3:
            raise FitInputError(f"scene {sid}, view {view.name}: camera viewmat rotation is not a rotation "
                                f"(det {np.linalg.det(cam.viewmat[:3, :3]):.4f})")
        if view.image_path is None:
            raise FitInputError(f"scene {sid}, view {view.name}: no image (View.image_path is None)")


def read_image(path: Path, camera: Camera) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB; the size must match the camera's."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FitInputError(f"{path}: image file not found")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FitInputError(f"{path}: not a readable image")
    h, w = bgr.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise FitInputError(f"{path}: image is {w}x{h} but the camera width/height is "
                            f"{camera.width}x{camera.height}")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def load_views(views: Sequence, downscale: float) -> list[ViewData]:
    """Read and (optionally) downscale the images of ``views`` (``scene.View``)."""
    import cv2
    import torch

    out = []
    for view in views:
        rgb = read_image(view.image_path, view.camera)
        camera = view.camera
        if downscale != 1.0:
            camera = camera.scaled(1.0 / downscale)
            rgb = cv2.resize(rgb, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        image = torch.from_numpy(rgb.astype(np.float32) / 255.0)
        valid = None
        if view.mask_path is not None:
            mask = read_valid_mask(view.mask_path, camera.width, camera.height)
            valid = None if mask.all() else torch.from_numpy(mask)
        out.append(ViewData(view.name, camera, image, torch.from_numpy(camera.viewmat.astype(np.float32)),
                            torch.from_numpy(camera.K.astype(np.float32)), valid))
    return out


def compute_scene_extent(cameras: Sequence[Camera], points: np.ndarray) -> float:
    """3DGS scene extent: 1.1 x the largest distance of a camera centre from their mean; the half
    diagonal of the points' bounding box when the cameras do not spread."""
    centres = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()) * EXTENT_MARGIN
    if radius < MIN_SCENE_EXTENT:
        radius = 0.5 * float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return max(radius, MIN_SCENE_EXTENT)


def voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points (float64) and colours (float64, 0..255) per occupied voxel, voxels in sorted key order."""
    points = np.asarray(points, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.float64)
    if voxel_size <= 0.0:
        return points, colors
    keys = np.floor((points - points.min(axis=0)) / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((counts.shape[0], 3))
    np.add.at(sums, inverse, points)
    csums = np.zeros((counts.shape[0], 3))
    np.add.at(csums, inverse, colors)
    return sums / counts[:, None], csums / counts[:, None]


def initialize_gaussians(points: np.ndarray, colors: np.ndarray, config: FitConfig,
                         rng: np.random.Generator) -> tuple[Gaussians, dict]:
    """Initial Gaussians at the voxel-averaged points: isotropic scales = mean distance to the
    ``init_knn`` nearest other points (log), identity rotations, opacity ``init_opacity`` (logit),
    SH DC from the point colours, higher SH zero. Returns the Gaussians and counts for the metrics."""
    pts, cols = voxel_downsample(points, colors, config.init_voxel_size)
    stats = {"input_points": int(points.shape[0]), "voxel_points": int(pts.shape[0]), "subsampled_away": 0}
    if pts.shape[0] > config.max_gaussians:
        keep = np.sort(rng.choice(pts.shape[0], size=config.max_gaussians, replace=False))
        stats["subsampled_away"] = int(pts.shape[0] - keep.shape[0])
        pts, cols = pts[keep], cols[keep]
    n = pts.shape[0]
    if n > 1:
        k = min(config.init_knn, n - 1)
        dist, _ = nearest_neighbours(pts, "scipy")(pts, k + 1)
        nn = dist[:, 1:].mean(axis=1)
    else:
        nn = np.full(n, 0.01)
    nn = np.maximum(nn, INIT_MIN_NN_DISTANCE)
    log_scales = np.repeat(np.log(nn)[:, None], 3, axis=1)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    opacity = np.full(n, math.log(config.init_opacity / (1.0 - config.init_opacity)))
    k_coeffs = (config.sh_degree + 1) ** 2
    sh = np.zeros((n, k_coeffs, 3))
    sh[:, 0] = (cols / 255.0 - 0.5) / SH_C0
    return Gaussians.from_arrays(pts, quats, log_scales, opacity, sh), stats


# --- parameters and optimizer state ----------------------------------------------------------------


class GaussianParameters:
    """The trainable per-Gaussian tensors, their Adam optimizer and the densification statistics,
    kept row-aligned by ``select`` and ``append``."""

    def __init__(self, gaussians: Gaussians, config: FitConfig, extent: float):
        import torch

        t = gaussians.to_torch()
        values = {
            "means": t["means"], "quats": t["quats"], "log_scales": t["log_scales"],
            "opacity_logits": t["opacity_logits"], "f_dc": t["sh"][:, :1], "f_rest": t["sh"][:, 1:],
        }
        lrs = {
            "means": config.lr_means_init * extent, "quats": config.lr_quats, "log_scales": config.lr_scales,
            "opacity_logits": config.lr_opacity, "f_dc": config.lr_f_dc, "f_rest": config.lr_f_rest,
        }
        self.params = {name: torch.nn.Parameter(values[name].clone().contiguous()) for name in PARAMETER_NAMES}
        self.optimizer = torch.optim.Adam(
            [{"params": [self.params[name]], "lr": lrs[name], "name": name} for name in PARAMETER_NAMES],
            lr=0.0, eps=ADAM_EPS, fused=True,
        )
        self.stats = {}
        self.reset_stats()

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def reset_stats(self) -> None:
        import torch

        n = len(self)
        self.stats = {
            "grad_accum": torch.zeros(n),  # summed view-space gradient norm
            "grad_count": torch.zeros(n),  # views in which the Gaussian was visible
            "max_radius": torch.zeros(n),  # largest screen radius in pixels
        }

    def sh(self) -> "torch.Tensor":
        import torch

        return torch.cat([self.params["f_dc"], self.params["f_rest"]], dim=1)

    def set_lr(self, name: str, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def _swap(self, name: str, new_value: "torch.Tensor", new_state: dict | None) -> None:
        import torch

        old = self.params[name]
        param = torch.nn.Parameter(new_value.contiguous())
        state = self.optimizer.state.pop(old, None)
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["params"][0] = param
        if state is not None and new_state is not None:
            state = dict(state)
            state.update(new_state)
            self.optimizer.state[param] = state
        self.params[name] = param

    def select(self, index: "torch.Tensor") -> None:
        """Keep the Gaussians ``index`` (bool mask or int64 rows) in every tensor and Adam state."""
        for name in PARAMETER_NAMES:
            old = self.params[name]
            state = self.optimizer.state.get(old)
            new_state = None
            if state:
                new_state = {key: state[key][index].clone() for key in ("exp_avg", "exp_avg_sq")}
            self._swap(name, old.detach()[index].clone(), new_state)
        self.stats = {key: value[index].clone() for key, value in self.stats.items()}

    def append(self, values: dict) -> None:
        """Add Gaussians (``values[name]`` rows for every parameter) with zero Adam moments and stats."""
        import torch

        count = int(values["means"].shape[0])
        for name in PARAMETER_NAMES:
            old = self.params[name]
            state = self.optimizer.state.get(old)
            new_state = None
            if state:
                new_state = {key: torch.cat([state[key], torch.zeros_like(values[name])], dim=0)
                             for key in ("exp_avg", "exp_avg_sq")}
            self._swap(name, torch.cat([old.detach(), values[name].detach()], dim=0), new_state)
        self.stats = {key: torch.cat([value, torch.zeros(count, dtype=value.dtype)]) for key, value in self.stats.items()}

    def replace(self, name: str, value: "torch.Tensor") -> None:
        """Set parameter ``name`` to ``value`` and zero its Adam moments (opacity reset)."""
        import torch

        old = self.params[name]
        state = self.optimizer.state.get(old)
        new_state = None
        if state:
            new_state = {key: torch.zeros_like(state[key]) for key in ("exp_avg", "exp_avg_sq")}
        self._swap(name, value.detach().clone(), new_state)

    def to_gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians.from_arrays(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], self.sh())


# --- one step ------------------------------------------------------------------------------------


def normalized(quats: "torch.Tensor") -> "torch.Tensor":
    return quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_NORM_EPS)


def render_view(params: GaussianParameters, view: ViewData, sh_degree: int, background: "torch.Tensor"):
    """RenderOutput of the current Gaussians in ``view`` (differentiable)."""
    from seggaussian import render

    p = params.params
    return render.rasterize(
        p["means"], normalized(p["quats"]), p["log_scales"], p["opacity_logits"].reshape(-1),
        view.viewmat, view.K, view.camera.width, view.camera.height,
        sh=params.sh(), sh_degree=sh_degree, background=background,
    )


def view_space_stats(means: "torch.Tensor", means_grad: "torch.Tensor", log_scales: "torch.Tensor",
                     view: ViewData) -> tuple["torch.Tensor", "torch.Tensor", "torch.Tensor"]:
    """Per Gaussian in one view: NDC gradient norm of the projected centre ``[N]``, visibility ``[N]``
    (in front of the camera, footprint touching the image) and screen radius in pixels ``[N]``."""
    import torch

    rot = view.viewmat[:3, :3]
    cam = means @ rot.T + view.viewmat[:3, 3]
    z = cam[:, 2]
    fx, fy, cx, cy = view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2]
    w, h = view.camera.width, view.camera.height
    in_front = z > NEAR_PLANE
    zc = torch.where(in_front, z, torch.ones_like(z))
    grad_cam = means_grad @ rot.T  # covector: dL/dp_cam = R dL/dp_world
    grad_ndc = torch.stack([grad_cam[:, 0] * zc / fx * (0.5 * w), grad_cam[:, 1] * zc / fy * (0.5 * h)], dim=1)
    radius = RADIUS_SIGMAS * log_scales.max(dim=1).values.exp() * torch.maximum(fx, fy) / zc
    u = fx * cam[:, 0] / zc + cx
    v = fy * cam[:, 1] / zc + cy
    visible = in_front & (u + radius > 0) & (u - radius < w) & (v + radius > 0) & (v - radius < h)
    return grad_ndc.norm(dim=1), visible, torch.where(visible, radius, torch.zeros_like(radius))


def densify_and_prune(params: GaussianParameters, config: FitConfig, extent: float, prune_large: bool,
                      generator: "torch.Generator") -> dict:
    """Clone small and split large Gaussians with a high mean view-space gradient (up to the cap),
    then prune transparent ones (and oversized ones when ``prune_large``). Returns the counts."""
    import torch

    n0 = len(params)
    grads = params.stats["grad_accum"] / params.stats["grad_count"].clamp_min(1.0)
    max_scale = params.params["log_scales"].detach().max(dim=1).values.exp()
    candidates = grads >= config.densify_grad_threshold
    # the cap: keep only the strongest candidates that fit (a split adds split_count - 1 net)
    budget = config.max_gaussians - n0
    idx = torch.nonzero(candidates).reshape(-1)
    if idx.numel() > 0:
        order = torch.sort(grads[idx], descending=True, stable=True).indices
        idx = idx[order]
        small = max_scale[idx] <= config.percent_dense * extent
        cost = torch.where(small, 1, config.split_count - 1)
        fits = torch.cumsum(cost, 0) <= max(budget, 0)
        idx = idx[fits]
    chosen = torch.zeros(n0, dtype=torch.bool)
    chosen[idx] = True
    clone = chosen & (max_scale <= config.percent_dense * extent)
    split = chosen & ~clone

    p = {name: value.detach() for name, value in params.params.items()}
    new = {name: p[name][clone] for name in PARAMETER_NAMES}
    # split: children sampled from the parent Gaussian, scales divided by split_scale_divisor
    k = config.split_count
    if int(split.sum()) > 0:
        scales = p["log_scales"][split].exp().repeat(k, 1)
        samples = torch.randn(scales.shape, generator=generator) * scales
        q = normalized(p["quats"][split]).repeat(k, 1)
        children = {
            "means": torch.einsum("nij,nj->ni", quats_to_rotmats_torch(q), samples) + p["means"][split].repeat(k, 1),
            "log_scales": (scales / config.split_scale_divisor).log(),
            "quats": p["quats"][split].repeat(k, 1),
            "opacity_logits": p["opacity_logits"][split].repeat(k),
            "f_dc": p["f_dc"][split].repeat(k, 1, 1),
            "f_rest": p["f_rest"][split].repeat(k, 1, 1),
        }
        new = {name: torch.cat([new[name], children[name]], dim=0) for name in PARAMETER_NAMES}
    num_new = int(new["means"].shape[0])
    if num_new:
        params.append(new)
    # prune: the split parents, transparent Gaussians, oversized ones
    remove = torch.cat([split, torch.zeros(num_new, dtype=torch.bool)])
    opacity = torch.sigmoid(params.params["opacity_logits"].detach())
    transparent = opacity < config.prune_opacity
    remove |= transparent
    large = torch.zeros_like(remove)
    if prune_large:
        world = params.params["log_scales"].detach().max(dim=1).values.exp() > config.prune_world_scale * extent
        screen = params.stats["max_radius"] > config.prune_screen_size
        large = (world | screen) & ~remove
        remove |= large
    if bool(remove.all()):  # never prune everything: keep the most opaque Gaussian
        remove[torch.argmax(opacity)] = False
    params.select(~remove)
    params.reset_stats()
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned_transparent": int(transparent.sum()),
            "pruned_large": int(large.sum()), "gaussians": len(params)}


def reset_opacity(params: GaussianParameters, ceiling: float) -> None:
    """Clamp every opacity to at most ``ceiling`` and zero the opacity's Adam moments."""
    import torch

    logit = math.log(ceiling / (1.0 - ceiling))
    params.replace("opacity_logits", torch.minimum(params.params["opacity_logits"].detach(),
                                                    torch.tensor(logit)))


def means_lr(iteration: int, config: FitConfig, extent: float) -> float:
    """Exponential (log-linear) decay of the means' learning rate from init to final, times the extent."""
    t = min(max(iteration / max(config.iterations, 1), 0.0), 1.0)
    log_lr = (1 - t) * math.log(config.lr_means_init) + t * math.log(config.lr_means_final)
    return math.exp(log_lr) * extent


def evaluate(params: GaussianParameters, views: Sequence[ViewData], sh_degree: int,
             background: "torch.Tensor") -> dict:
    """Mean PSNR, SSIM and L1 over ``views`` (renders clamped to [0, 1])."""
    import torch

    from seggaussian.losses import l1_loss, psnr, ssim

    psnrs, ssims, l1s = [], [], []
    with torch.no_grad():
        for view in views:
            image = masked_render(render_view(params, view, sh_degree, background).image.clamp(0.0, 1.0), view)
            psnrs.append(float(psnr(image, view.image)))
            ssims.append(float(ssim(image, view.image)))
            l1s.append(float(l1_loss(image, view.image)))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "l1": float(np.mean(l1s)),
            "views": len(views)}


def evenly_spaced(items: Sequence, count: int) -> list:
    if count >= len(items):
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


# --- the fit ---------------------------------------------------------------------------------------


def fit_scene(scene: Scene, config: FitConfig, *, seed: int, progress: bool = True,
              on_iteration: Callable[[FitProgress], None] | None = None) -> FitResult:
    """Fit Gaussians to the scene's train views; report PSNR/SSIM on its novel views.

    ``seed`` drives every random choice (view order, initial subsampling, split samples) through an
    explicit numpy Generator and torch Generator: the same scene, config and seed give the same
    Gaussians. ``on_iteration`` (benchmarks) is called after every iteration with a ``FitProgress``.
    """
    import torch
    from tqdm import tqdm

    from seggaussian.losses import fitting_loss, psnr

    start = time.perf_counter()
    validate_scene(scene)
    rng = np.random.default_rng(seed)
    generator = torch.Generator().manual_seed(int(seed))

    train_all = list(scene.views_with_role("train"))
    holdout = evenly_spaced(train_all, config.holdout_views) if 0 < config.holdout_views < len(train_all) else []
    held_ids = {id(v) for v in holdout}
    train_views = load_views([v for v in train_all if id(v) not in held_ids], config.downscale)
    novel_views = load_views(scene.views_with_role("novel"), config.downscale)
    holdout_views = load_views(holdout, config.downscale)
    early_stop_views = evenly_spaced(holdout_views or novel_views, config.eval_max_views)

    extent = compute_scene_extent([v.camera for v in train_views], scene.points)
    initial, init_stats = initialize_gaussians(scene.points, scene.colors, config, rng)
    params = GaussianParameters(initial, config, extent)
    background = torch.tensor(config.background, dtype=torch.float32)

    history: list[dict] = []
    best_psnr, best_iteration, evals_since_best = -math.inf, 0, 0
    stop_reason = "completed all iterations"
    densify_log: list[dict] = []
    order: list[int] = []
    iteration = 0
    window_losses: list[float] = []  # training losses since the last evaluation
    if config.eval_every and early_stop_views:  # the starting point of the curve
        held = evaluate(params, early_stop_views, 0, background)
        history.append({"iteration": 0, "seconds": time.perf_counter() - start, "loss": None,
                        "heldout_psnr": held["psnr"], "gaussians": len(params)})
    bar = tqdm(total=config.iterations, disable=not progress, desc=f"fit {scene.scene_id}", unit="it")
    for iteration in range(1, config.iterations + 1):
        if not order:
            order = rng.permutation(len(train_views)).tolist()
        view = train_views[order.pop()]
        sh_degree = min(config.sh_degree, (iteration - 1) // config.sh_increase_every)
        params.set_lr("means", means_lr(iteration - 1, config, extent))

        out = render_view(params, view, sh_degree, background)
        loss = fitting_loss(masked_render(out.image, view), view.image, config.lambda_dssim)
        loss.backward()
        loss_value = float(loss.detach())
        if not math.isfinite(loss_value):
            raise FloatingPointError(f"scene {scene.scene_id}: loss became {loss_value} at iteration {iteration}")
        window_losses.append(loss_value)

        with torch.no_grad():
            if iteration <= config.densify_until:
                means = params.params["means"]
                grad = means.grad if means.grad is not None else torch.zeros_like(means)
                gnorm, visible, radius = view_space_stats(means.detach(), grad, params.params["log_scales"].detach(),
                                                          view)
                params.stats["grad_accum"] += torch.where(visible, gnorm, torch.zeros_like(gnorm))
                params.stats["grad_count"] += visible.float()
                params.stats["max_radius"] = torch.maximum(params.stats["max_radius"], radius)
            params.optimizer.step()
            params.optimizer.zero_grad(set_to_none=True)

            if config.densify_from <= iteration <= config.densify_until and iteration % config.densify_every == 0:
                counts = densify_and_prune(params, config, extent, iteration > config.opacity_reset_every, generator)
                densify_log.append(dict(counts, iteration=iteration))
            if iteration < config.densify_until and iteration % config.opacity_reset_every == 0:
                reset_opacity(params, config.opacity_reset_value)

        if progress and (iteration % 10 == 0 or iteration == 1):
            bar.set_postfix(psnr=f"{float(psnr(out.image.detach().clamp(0, 1), view.image)):.2f}", n=len(params))
        bar.update(1)

        if config.eval_every and iteration % config.eval_every == 0 and early_stop_views:
            held = evaluate(params, early_stop_views, sh_degree, background)
            history.append({"iteration": iteration, "seconds": time.perf_counter() - start, "loss": float(np.mean(window_losses)),
                            "heldout_psnr": held["psnr"], "gaussians": len(params)})
            window_losses = []
            if held["psnr"] > best_psnr + config.min_psnr_gain:
                best_psnr, best_iteration, evals_since_best = held["psnr"], iteration, 0
            else:
                evals_since_best += 1
            # opacity resets and densification make the PSNR jump: the rule applies after densification
            if config.patience and iteration > config.densify_until and evals_since_best >= config.patience:
                stop_reason = (f"early stop: held-out PSNR gained < {config.min_psnr_gain} dB in "
                               f"{config.patience} evaluations (best {best_psnr:.2f} dB at iteration {best_iteration})")
                break
        if on_iteration is not None:
            degree = sh_degree
            on_iteration(FitProgress(
                iteration, len(params), time.perf_counter() - start,
                lambda: evaluate(params, novel_views, degree, background) if novel_views else None))
        if config.time_budget_seconds and time.perf_counter() - start > config.time_budget_seconds:
            stop_reason = f"time budget of {config.time_budget_seconds:g} s reached"
            break
    bar.close()
    if not early_stop_views and stop_reason == "completed all iterations":
        stop_reason += " (no held-out or novel views: early stop off)"

    final_degree = min(config.sh_degree, (iteration - 1) // config.sh_increase_every)
    novel = evaluate(params, novel_views, final_degree, background) if novel_views else None
    gaussians = params.to_gaussians()
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        if not np.isfinite(getattr(gaussians, name)).all():  # never write NaN into an output
            raise FloatingPointError(f"scene {scene.scene_id}: fitted {name} holds NaN/Inf after {iteration} iterations")
    metrics = {
        "scene_id": scene.scene_id,
        "novel_psnr": novel["psnr"] if novel else None,
        "novel_ssim": novel["ssim"] if novel else None,
        "novel_l1": novel["l1"] if novel else None,
        "novel_views": len(novel_views),
        "train_views": len(train_views),
        "holdout_views": len(holdout_views),
        "iterations": iteration,
        "seconds": time.perf_counter() - start,
        "early_stop_reason": stop_reason,
        "gaussians": len(gaussians),
        "initial_gaussians": len(initial),
        "init": init_stats,
        "active_sh_degree": final_degree,
        "scene_extent": extent,
        "image_size": [train_views[0].camera.width, train_views[0].camera.height],
        "seed": int(seed),
        "densification": densify_log,
    }
    return FitResult(gaussians, metrics, history)


# --- sources and files -----------------------------------------------------------------------------

SOURCES = ("synthetic", "scannetpp", "replica")


def read_source_scene(source: str, root: str | Path, scene_id: str) -> Scene:
    """Read one scene. ``synthetic`` accepts what ``seggaussian synth`` writes (``ROOT/scannetpp``,
    ``ROOT/replica``) or a single layout root; the layout is found from where ``scene_id`` lives."""
    root = Path(root)
    if source not in SOURCES:
        raise ValueError(f"source must be one of {', '.join(SOURCES)}, got {source!r}")
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: raw tree does not exist")
    if source == "synthetic":
        source, root = find_scene_layout(root, scene_id)
    return reader(source).read_scene(root, scene_id)


def metrics_path(ply_path: str | Path) -> Path:
    """``SCENE.fit.json`` next to ``SCENE.ply``."""
    ply_path = Path(ply_path)
    return ply_path.with_name(ply_path.stem + ".fit.json")


def write_fit_outputs(result: FitResult, config: FitConfig, ply_path: str | Path) -> Path:
    """Write the PLY and ``SCENE.fit.json`` (metrics, config, history), both atomically; returns the JSON path."""
    from seggaussian.io.ply import write_gaussians_ply
    from seggaussian.atomic import write_json_atomic

    ply_path = Path(ply_path)
    write_gaussians_ply(ply_path, result.gaussians)
    json_path = metrics_path(ply_path)
    payload = {"metrics": result.metrics, "config": config.to_dict(), "history": result.history,
               "ply": ply_path.name}

    write_json_atomic(json_path, payload)
    return json_path


def fit_to_ply(source: str, root: str | Path, scene_id: str, out: str | Path, config: FitConfig, *, seed: int,
               progress: bool = True) -> FitResult:
    """Read a scene, fit it and write ``out`` (PLY) plus ``out.fit.json``: what ``seggaussian fit`` does."""
    from seggaussian.atomic import ensure_writable_dir

    ensure_writable_dir(Path(out).parent)  # fail before the fit, not after it
    scene = read_source_scene(source, root, scene_id)
    result = fit_scene(scene, config, seed=seed, progress=progress)
    write_fit_outputs(result, config, out)
    return result
