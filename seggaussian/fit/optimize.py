"""Fit 3D Gaussians to a scene's posed images on the CPU (3D Gaussian Splatting, Kerbl et al. 2023).

Data flow: ``validate_scene`` -> ``load_views`` (images as float tensors, optional downscale) ->
``initialize_gaussians`` (voxel-averaged points, scales from nearest neighbours) -> ``fit_scene``
(Adam with the 3DGS learning rates, L1 + D-SSIM loss plus an optional depth term against the scene mesh's
raycast depth, densification by the accumulated view-space gradient, pruning, optional opacity resets,
evaluation and early stop) -> ``FitResult``. With ``keep_best`` (default) the parameters are snapshotted
whenever the held-out PSNR improves and the best evaluated state is returned, whatever ended the run
(completion, early stop, time budget); ``metrics["returned_iteration"]`` names it and the novel-view
metrics are those of the returned state.

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


Modules: ``fit_views`` (input), ``fit_init`` (initial Gaussians), ``fit_params`` (parameters, Adam, render),
``fit_densify`` (densification), this module (the loop, evaluation, files).
"""

from __future__ import annotations

import math
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.util.atomic import ensure_writable_dir, write_json_atomic
from seggaussian.fit.config import FitConfig
from seggaussian.fit.densify import densify_and_prune, reset_opacity, view_space_stats
from seggaussian.fit.initialize import compute_scene_extent, initialize_gaussians
from seggaussian.fit.params import GaussianParameters, render_view
from seggaussian.fit.views import (ViewData, evenly_spaced, load_views, masked_render, validate_scene,
                                   with_mesh_depth)
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.fit.losses import depth_loss, fitting_loss, l1_loss, psnr, ssim
from seggaussian.core.scene import Scene
from seggaussian.sources.layout import find_scene_layout, reader

if TYPE_CHECKING:
    import torch

#: Modes of the build stage's ``--fit`` option.
FIT_MODES = ("auto", "always", "never")
#: Iterations whose pace projects, under a time budget, how many iterations the run has left (``iterations_left``).
RATE_WINDOW = 50
#: Shortest pace (seconds per iteration) the projection divides by: a clock that did not advance is not infinite speed.
MIN_PACE_SECONDS = 1e-9
SOURCES = ("synthetic", "scannetpp", "replica")


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


def means_lr(iteration: int, config: FitConfig, extent: float) -> float:
    """Exponential (log-linear) decay of the means' learning rate from init to final, times the extent."""
    t = min(max(iteration / max(config.iterations, 1), 0.0), 1.0)
    log_lr = (1 - t) * math.log(config.lr_means_init) + t * math.log(config.lr_means_final)
    return math.exp(log_lr) * extent


def evaluate(params: GaussianParameters, views: Sequence[ViewData], sh_degree: int,
             background: "torch.Tensor") -> dict:
    """Mean PSNR, SSIM and L1 over ``views`` (renders clamped to [0, 1])."""
    import torch

    psnrs, ssims, l1s = [], [], []
    with torch.no_grad():
        for view in views:
            image = masked_render(render_view(params, view, sh_degree, background).image.clamp(0.0, 1.0), view)
            psnrs.append(float(psnr(image, view.image)))
            ssims.append(float(ssim(image, view.image)))
            l1s.append(float(l1_loss(image, view.image)))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "l1": float(np.mean(l1s)),
            "views": len(views)}


def iterations_left(iteration: int, config: FitConfig, elapsed: float, step_times: Sequence[float]) -> float:
    """Iterations the run has left after ``iteration``: to ``config.iterations``, and under a time budget no more than
    the budget's remaining seconds at the pace of the latest iterations (``step_times``: their end times, oldest
    first; the pace only slows as densification adds Gaussians, so this is an upper bound)."""
    left = float(config.iterations - iteration)
    if config.time_budget_seconds and len(step_times) >= 2:
        pace = (step_times[-1] - step_times[0]) / (len(step_times) - 1)
        left = min(left, max(0.0, config.time_budget_seconds - elapsed) / max(pace, MIN_PACE_SECONDS))
    return left


def fit_scene(scene: Scene, config: FitConfig, *, seed: int, progress: bool = True,
              on_iteration: Callable[[FitProgress], None] | None = None) -> FitResult:
    """Fit Gaussians to the scene's train views; report PSNR/SSIM on its novel views.

    ``seed`` drives every random choice (view order, initial subsampling, split samples) through an
    explicit numpy Generator and torch Generator: the same scene, config and seed give the same
    Gaussians. ``on_iteration`` (benchmarks) is called after every iteration with a ``FitProgress``.
    """
    import torch
    from tqdm import tqdm

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
    if config.lambda_depth > 0.0:  # exact depth of the scene's mesh, where it has one
        train_views = with_mesh_depth(train_views, scene.points, scene.faces)
    depth_views = sum(v.depth is not None for v in train_views)

    extent = compute_scene_extent([v.camera for v in train_views], scene.points)
    initial, init_stats = initialize_gaussians(scene.points, scene.colors, config, rng)
    params = GaussianParameters(initial, config, extent)
    background = torch.tensor(config.background, dtype=torch.float32)

    history: list[dict] = []
    best_psnr, best_iteration, evals_since_best = -math.inf, 0, 0
    best_state: dict | None = None  # parameters and SH degree at the best held-out evaluation
    last_eval_iteration = -1
    stop_reason = "completed all iterations"
    densify_log: list[dict] = []
    order: list[int] = []
    iteration = 0
    window_losses: list[float] = []  # training losses since the last evaluation
    step_times: deque[float] = deque([time.perf_counter()], maxlen=RATE_WINDOW + 1)  # ends of the latest iterations
    opacity_resets: list[int] = []
    skipped_resets: list[int] = []
    if config.eval_every and early_stop_views:  # the starting point of the curve
        held = evaluate(params, early_stop_views, 0, background)
        history.append({"iteration": 0, "seconds": time.perf_counter() - start, "loss": None,
                        "heldout_psnr": held["psnr"], "gaussians": len(params)})
        last_eval_iteration = 0
        if config.keep_best:
            best_psnr, best_state = held["psnr"], {"params": params.snapshot(), "sh_degree": 0, "iteration": 0}
    bar = tqdm(total=config.iterations, disable=not progress, desc=f"fit {scene.scene_id}", unit="it")
    for iteration in range(1, config.iterations + 1):
        if not order:
            order = rng.permutation(len(train_views)).tolist()
        view = train_views[order.pop()]
        sh_degree = min(config.sh_degree, (iteration - 1) // config.sh_increase_every)
        params.set_lr("means", means_lr(iteration - 1, config, extent))

        out = render_view(params, view, sh_degree, background)
        loss = fitting_loss(masked_render(out.image, view), view.image, config.lambda_dssim)
        if (view.depth is not None and config.lambda_depth > 0.0
                and (not config.depth_until or iteration <= config.depth_until)):
            loss = loss + config.lambda_depth * depth_loss(out.depth, view.depth, view.valid)
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
            if (config.opacity_reset and iteration < config.densify_until
                    and iteration % config.opacity_reset_every == 0):
                left = iterations_left(iteration, config, time.perf_counter() - start, step_times)
                if left >= config.opacity_reset_every:
                    reset_opacity(params, config.opacity_reset_value)
                    opacity_resets.append(iteration)
                else:  # the run would end before the Gaussians are opaque again: the reset goes
                    skipped_resets.append(iteration)
        step_times.append(time.perf_counter())

        if progress and (iteration % 10 == 0 or iteration == 1):
            bar.set_postfix(psnr=f"{float(psnr(out.image.detach().clamp(0, 1), view.image)):.2f}", n=len(params))
        bar.update(1)

        if config.eval_every and iteration % config.eval_every == 0 and early_stop_views:
            held = evaluate(params, early_stop_views, sh_degree, background)
            history.append({"iteration": iteration, "seconds": time.perf_counter() - start, "loss": float(np.mean(window_losses)),
                            "heldout_psnr": held["psnr"], "gaussians": len(params)})
            window_losses = []
            last_eval_iteration = iteration
            if held["psnr"] > best_psnr + config.min_psnr_gain:
                best_iteration, evals_since_best = iteration, 0
            else:
                evals_since_best += 1
            if held["psnr"] > best_psnr:
                best_psnr = held["psnr"]
                if config.keep_best:
                    best_state = {"params": params.snapshot(), "sh_degree": sh_degree, "iteration": iteration}
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
    final_heldout = None
    if config.keep_best and best_state is not None and early_stop_views:
        if last_eval_iteration != iteration:  # the last state competes too
            held = evaluate(params, early_stop_views, final_degree, background)
            final_heldout = held["psnr"]
            history.append({"iteration": iteration, "seconds": time.perf_counter() - start,
                            "loss": float(np.mean(window_losses)) if window_losses else None,
                            "heldout_psnr": held["psnr"], "gaussians": len(params)})
        else:
            final_heldout = history[-1]["heldout_psnr"]
        if final_heldout > best_psnr:
            best_psnr, best_state = final_heldout, None
    returned_iteration = iteration
    if best_state is not None and config.keep_best and best_state["iteration"] != iteration:
        params.restore(best_state["params"])
        final_degree = best_state["sh_degree"]
        returned_iteration = best_state["iteration"]
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
        "returned_iteration": returned_iteration,
        "best_heldout_psnr": None if best_psnr == -math.inf else best_psnr,
        "final_heldout_psnr": final_heldout,
        "depth_views": depth_views,
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
        "opacity_resets": opacity_resets,
        "skipped_opacity_resets": skipped_resets,
    }
    return FitResult(gaussians, metrics, history)


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
    ensure_writable_dir(Path(out).parent)  # fail before the fit, not after it
    scene = read_source_scene(source, root, scene_id)
    result = fit_scene(scene, config, seed=seed, progress=progress)
    write_fit_outputs(result, config, out)
    return result
