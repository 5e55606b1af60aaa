"""The render stage sweep: label maps of oracle Gaussians against label images raycast from the mesh.

The oracle Gaussians carry their true label; label maps are compared with label images raycast from the mesh
at the same resolution (hit triangle's corner with the largest barycentric weight, the rule that labels the
oracle Gaussians). Quality = pixel agreement over the pixels whose ray hits the mesh, ignore counted as a
label (a hit on an unlabelled surface must render ignore); ``labelled_agreement`` (labelled ground-truth
pixels, the quality before 2026-11) and ``unlabelled_kept`` are reported beside it, and the ``vote`` knob's
``labelled_only`` row replays the former label-map rule (unlabelled contributors did not vote) on the same
blend weights. The feature-render residual ``|render_features(W, f) - rasterize(features=f)|`` is reported too.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from seggaussian.pipeline.stages.views import view_scale
from seggaussian.pipeline.config import ViewConfig
from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.fit.views import evenly_spaced
from seggaussian.render import compute_blend_weights, rasterize, render_features, render_label_maps
from seggaussian.render.results import BlendWeights
from seggaussian.render.rasterize import camera_tensors, default_backend
from seggaussian.sources.raycast import MeshRaycaster
from seggaussian.tools.sweep.pareto import Trial, one_at_a_time
from seggaussian.tools.sweep.config import StageSweepConfig
from seggaussian.tools.sweep.data import Progress, SweepDataError, oracle_labelled, read_task_scene, require_mesh


def raycast_labels(caster, camera, semantic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(``[H, W]`` ground-truth class per pixel, ``[H, W]`` bool ray hit): the hit triangle's corner with the
    largest barycentric weight (the oracle Gaussians' labelling rule); IGNORE_LABEL where the ray misses or
    the hit surface is unlabelled."""
    hits = caster.cast(camera)
    out = np.full(hits.face_ids.shape, IGNORE_LABEL, np.int64)
    hit = hits.face_ids >= 0
    uv = hits.barycentric[hit]
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    vertex = caster.faces[hits.face_ids[hit], np.argmax(bary, axis=1)]
    out[hit] = np.asarray(semantic, np.int64)[vertex]
    return out, hit


def labelled_only_blend(blend: BlendWeights, semantic: torch.Tensor) -> BlendWeights:
    """The blend weights on which the shipped vote reproduces the former label-map rule (only labelled
    contributors voted): unlabelled contributors' weight moves into ``residual_alpha``, so the coverage
    test (weights + residual >= min_alpha) is unchanged and they can no longer win."""
    used = blend.ids >= 0
    unlabelled = used & (semantic[blend.ids.clamp_min(0)] == IGNORE_LABEL)
    moved = torch.where(unlabelled, blend.weights, torch.zeros_like(blend.weights))
    return BlendWeights(blend.ids, blend.weights - moved, blend.residual_alpha + moved.sum(-1))


def render_camera(camera, settings: dict, reference_width: int):
    """The camera of a render row: ``scale`` of the stored size, or the tiny reference width."""
    if settings["backend"] == "reference" or settings.get("tiny"):
        return camera.scaled(reference_width / camera.width)
    return camera if settings["scale"] == 1.0 else camera.scaled(settings["scale"])


def warm_up_render(t: dict, camera, width: int, backend: str) -> None:
    """One tiny blend-weights call and forward/backward rasterization (loads the numba kernels)."""
    cam = camera.scaled(width / camera.width)
    viewmat, K = camera_tensors(cam)
    sub = {k: v[:256] for k, v in t.items()}
    compute_blend_weights(sub["means"], sub["quats"], sub["log_scales"], sub["opacity_logits"], viewmat, K,
                          cam.width, cam.height, top_k=4, backend=backend)
    means = sub["means"].clone().requires_grad_(True)
    out = rasterize(means, sub["quats"], sub["log_scales"], sub["opacity_logits"], viewmat, K, cam.width, cam.height,
                    sh=sub["sh"], sh_degree=0, backend=backend)
    out.image.sum().backward()


def sweep_render(config: StageSweepConfig, tasks: list, progress: Progress | None = None) -> tuple[list, list]:
    """(rows, skipped) of the render sweep over ``tasks``."""
    sweep = config.render
    shipped = ViewConfig()
    fast = default_backend()
    num_classes = len(read_class_names())
    prepared = []
    for task in tasks:
        scene = read_task_scene(task, config)
        require_mesh(scene, "render")
        gaussians, truth = oracle_labelled(scene, sweep.num_gaussians, config.seed)
        views = evenly_spaced(list(scene.views), sweep.views)
        if not views:
            raise SweepDataError(f"scene {scene.scene_id} ({scene.root}): no views to render")
        rng = np.random.default_rng(config.seed)
        features = torch.from_numpy(rng.random((len(gaussians), sweep.feature_dim)).astype(np.float32))
        prepared.append((scene, gaussians.to_torch(), torch.from_numpy(truth.astype(np.int64)), views, features,
                         MeshRaycaster(scene.points, scene.faces)))
    cam0 = prepared[0][3][0].camera
    default_scale = view_scale(cam0.width, cam0.height, shipped)
    base = {"scale": default_scale, "top_k": shipped.top_k, "min_alpha": shipped.min_alpha, "vote": "ignore_occludes",
            "backend": fast}
    grids = {"scale": tuple(sweep.scale), "top_k": sweep.top_k, "min_alpha": sweep.min_alpha, "vote": sweep.vote}
    rows = one_at_a_time(base, grids)
    # fast vs reference, both at the tiny reference width (the reference is O(N x pixels))
    rows.append(("backend", {**base, "scale": None, "backend": fast, "tiny": True}))
    rows.append(("backend", {**base, "scale": None, "backend": "reference", "tiny": True}))
    skipped = []
    if fast == "reference":
        skipped.append("fast backend unavailable (numba kernels did not import): every row uses the reference")
    gt_cache: dict = {}
    warm_up_render(prepared[0][1], prepared[0][3][0].camera, sweep.reference_width, fast)
    trials = []
    for knob, settings in rows:
        if progress:
            progress(f"render {knob}: {settings}")
        seconds, agree, labelled, ignored, res_sum, res_max, res_n, residual_alpha, pixels = 0.0, 0, 0, 0, 0.0, 0.0, 0, 0.0, 0
        hit_agree, hit_pixels, unlabelled, kept = 0, 0, 0, 0
        size = None
        for si, (scene, t, truth, views, features, caster) in enumerate(prepared):
            views_here = views[:1] if settings.get("tiny") else views
            for vi, view in enumerate(views_here):
                cam = render_camera(view.camera, settings, sweep.reference_width)
                size = (cam.width, cam.height)
                key = (si, vi, cam.width, cam.height)
                if key not in gt_cache:
                    gt_cache[key] = raycast_labels(caster, cam, scene.semantic)
                gt, hit = gt_cache[key]
                viewmat, K = camera_tensors(cam)
                times = []
                for _ in range(max(1, sweep.repeats)):
                    t0 = time.perf_counter()
                    blend = compute_blend_weights(t["means"], t["quats"], t["log_scales"], t["opacity_logits"],
                                                  viewmat, K, cam.width, cam.height, top_k=settings["top_k"],
                                                  backend=settings["backend"])
                    voting = blend if settings["vote"] == "ignore_occludes" else labelled_only_blend(blend, truth)
                    maps = render_label_maps(voting, truth, torch.zeros_like(truth), num_classes,
                                             min_alpha=settings["min_alpha"])
                    times.append(time.perf_counter() - t0)
                seconds += float(np.median(times))
                pred = maps.semantic.numpy()
                mask = gt != IGNORE_LABEL
                agree += int((pred[mask] == gt[mask]).sum())
                labelled += int(mask.sum())
                ignored += int((pred[mask] == IGNORE_LABEL).sum())
                hit_agree += int((pred[hit] == gt[hit]).sum())
                hit_pixels += int(hit.sum())
                unlabelled += int((hit & ~mask).sum())
                kept += int((pred[hit & ~mask] == IGNORE_LABEL).sum())
                with torch.no_grad():
                    direct = rasterize(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], viewmat, K,
                                       cam.width, cam.height, features=features, backend=settings["backend"]).image
                    diff = (render_features(blend, features) - direct).abs()
                res_sum += float(diff.sum())
                res_n += diff.numel()
                res_max = max(res_max, float(diff.max()) if diff.numel() else 0.0)
                residual_alpha += float(blend.residual_alpha.sum())
                pixels += cam.width * cam.height
        metrics = {"labelled_pixels": labelled, "agreeing_pixels": agree,
                   "labelled_agreement": agree / labelled if labelled else None,
                   "hit_pixels": hit_pixels, "unlabelled_pixels": unlabelled,
                   "unlabelled_kept": kept / unlabelled if unlabelled else None,
                   "ignored_share": ignored / labelled if labelled else None,
                   "feature_residual_mean": res_sum / res_n if res_n else None, "feature_residual_max": res_max,
                   "residual_alpha_mean": residual_alpha / pixels if pixels else None,
                   "image_size": list(size) if size else None}
        settings_out = {k: v for k, v in settings.items() if k != "tiny"}
        if settings.get("tiny"):
            settings_out["scale"] = f"{sweep.reference_width}px"
        is_default = not settings.get("tiny") and settings == base
        trials.append(Trial("render", knob, settings_out, seconds, hit_agree / hit_pixels if hit_pixels else float("nan"),
                            metrics, is_default))
    return trials, skipped
