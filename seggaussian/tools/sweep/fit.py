"""The fit stage sweep: novel-view quality of fitted Gaussians against fitting time.

Ground truth: novel (held-out) views of the scene, scored at ``FitSweep.eval_scale`` of the source size
whatever the fit's downscale (PSNR is the quality; SSIM and L1 are reported). Scoring is the fit's own
``fit.evaluate`` (anonymized pixels masked as in the fit), on views loaded by ``fit.load_views``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from seggaussian.util.seeds import scene_seed
from seggaussian.fit.optimize import evaluate, fit_scene
from seggaussian.fit.config import FitConfig
from seggaussian.fit.params import GaussianParameters
from seggaussian.fit.views import load_views
from seggaussian.render.rasterize import default_backend
from seggaussian.tools.sweep.pareto import Trial, one_at_a_time
from seggaussian.tools.sweep.config import StageSweepConfig
from seggaussian.tools.sweep.data import Progress, SweepDataError, oracle_labelled, read_task_scene
from seggaussian.tools.sweep.render import warm_up_render

#: The knobs of ``FitConfig`` the fit sweep varies (``FitSweep`` lists their values).
FIT_KNOBS = ("iterations", "downscale", "max_gaussians", "patience")


def score_novel_views(gaussians, views, sh_degree: int, eval_scale: float, config: FitConfig) -> dict:
    """Mean PSNR / SSIM / L1 of the fitted Gaussians on ``views`` (``scene.View``) at ``eval_scale`` of the
    source size (the fit's scorer, ``fit.evaluate``)."""
    params = GaussianParameters(gaussians, config, extent=1.0)
    background = torch.tensor(config.background, dtype=torch.float32)
    return evaluate(params, load_views(views, 1.0 / eval_scale), sh_degree, background)


def sweep_fit(config: StageSweepConfig, tasks: list, progress: Progress | None = None) -> tuple[list, list]:
    """(rows, skipped) of the fit sweep over ``tasks``."""
    sweep = config.fit
    base_config = replace(FitConfig.preset(sweep.preset), **sweep.base)
    base = {k: getattr(base_config, k) for k in FIT_KNOBS}
    rows = one_at_a_time(base, {k: getattr(sweep, k) for k in FIT_KNOBS})
    scenes = []
    for task in tasks:
        scene = read_task_scene(task, config)
        novel = scene.views_with_role("novel")
        if not novel or not scene.views_with_role("train"):
            raise SweepDataError(f"scene {scene.scene_id} ({scene.root}): the fit sweep needs train and held-out "
                                 "(novel) views")
        scenes.append((scene, novel))
    g0, _ = oracle_labelled(scenes[0][0], 256, config.seed)
    warm_up_render(g0.to_torch(), scenes[0][1][0].camera, 32, default_backend())
    # one short fit outside the timings (first-call costs of autograd, losses, optimizer)
    fit_scene(scenes[0][0], replace(base_config, iterations=2, eval_every=0, downscale=max(base_config.downscale, 4.0),
                                    max_gaussians=min(base_config.max_gaussians, 2000)), seed=0, progress=False)
    trials = []
    for knob, settings in rows:
        if progress:
            progress(f"fit {knob}: {settings}")
        fit_config = replace(base_config, **settings)
        seconds, scores, facts = 0.0, [], []
        for scene, novel in scenes:
            result = fit_scene(scene, fit_config, seed=scene_seed(config.seed, scene.scene_id) % 2**31,
                               progress=False)
            seconds += float(result.metrics["seconds"])
            scores.append(score_novel_views(result.gaussians, novel, result.metrics["active_sh_degree"],
                                            sweep.eval_scale, fit_config))
            facts.append({"scene": scene.scene_id, "iterations": result.metrics["iterations"],
                          "gaussians": result.metrics["gaussians"],
                          "early_stop": result.metrics["early_stop_reason"]})
        metrics = {"novel_ssim": float(np.mean([s["ssim"] for s in scores])),
                   "novel_l1": float(np.mean([s["l1"] for s in scores])),
                   "iterations_run": int(sum(f["iterations"] for f in facts)),
                   "gaussians": int(sum(f["gaussians"] for f in facts)), "per_scene": facts}
        trials.append(Trial("fit", knob, settings, seconds, float(np.mean([s["psnr"] for s in scores])), metrics,
                            fit_config == FitConfig.preset(sweep.preset)))
    return trials, []
