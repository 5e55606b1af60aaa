"""The transfer stage sweep: label agreement of the label transfer against oracle Gaussians' true labels.

Oracle Gaussians sampled on the visible labelled triangles carry their true label (the corner of the sampled
triangle with the largest barycentric weight, ``oracle.sample_oracle_gaussians``); their centres are pushed off
the surface along the normal by seeded noise (``TransferSweep.surface_noise``) because fitted Gaussians sit a
few cm off the mesh. Quality = label agreement over all Gaussians, ignore counted as a label: a Gaussian on a
labelled surface must get its class (ignore is wrong), one on an unlabelled surface (rug, None-mapped object,
masked disc) must stay ignore. ``label_accuracy`` (labelled surfaces only) and ``unlabelled_kept`` (unlabelled
surfaces only) are reported beside it.

Both rules come from ``seggaussian.labels.transfer``: ``vote_k = 1`` is the shipped ``transfer_labels``, ``vote_k > 1``
its k-nearest vote ``transfer_labels_vote`` (same kNN backend, candidates, spacing and gate).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from seggaussian.util.seeds import scene_seed
from seggaussian.labels.config import TransferConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.tools.sweep.pareto import Trial, one_at_a_time
from seggaussian.tools.sweep.config import StageSweepConfig
from seggaussian.tools.sweep.data import Progress, oracle_labelled, read_task_scene, require_mesh
from seggaussian.labels.transfer import densify_labelled_mesh, transfer_labels
from seggaussian.labels.scoring import label_accuracy
from seggaussian.labels.vote import transfer_labels_vote


def noisy_oracle(scene, sweep, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(Gaussian centres pushed off the surface [N, 3], true class [N])."""
    gaussians, truth = oracle_labelled(scene, sweep.num_gaussians, seed)
    normals = gaussians.rotation_matrices()[:, :, 2].astype(np.float64)
    rng = np.random.default_rng(scene_seed(seed + 1, scene.scene_id))
    offsets = rng.normal(0.0, sweep.surface_noise, len(gaussians)) if sweep.surface_noise > 0 else 0.0
    return gaussians.means.astype(np.float64) + normals * np.reshape(offsets, (-1, 1)), truth


def run_transfer_setting(scene, means: np.ndarray, settings: dict, seed: int) -> tuple[np.ndarray, dict]:
    """Labels of ``means`` under one transfer setting (the timed work: mesh densification, subsample,
    KD-tree, query). Returns (labels [N], facts)."""
    tcfg = replace(TransferConfig(), backend=settings["backend"], gate_factor=float(settings["gate_factor"]),
                   gate_min=float(settings["gate_min"]), mesh_sample_spacing=float(settings["mesh_sample_spacing"]),
                   candidates=settings["candidates"], seed=seed)
    points, semantic, instance = scene.points, scene.semantic, scene.instance
    if tcfg.mesh_sample_spacing > 0:
        samples, (s_sem, s_inst) = densify_labelled_mesh(points, scene.faces, tcfg.mesh_sample_spacing, semantic,
                                                         instance)
        points = np.concatenate([points, samples])
        semantic, instance = np.concatenate([semantic, s_sem]), np.concatenate([instance, s_inst])
    fraction = float(settings["point_fraction"])
    if fraction < 1.0:
        rng = np.random.default_rng(seed)
        keep = np.sort(rng.choice(len(points), size=max(1, int(round(fraction * len(points)))), replace=False))
        points, semantic, instance = points[keep], semantic[keep], instance[keep]
    if int(settings["vote_k"]) == 1:
        result = transfer_labels(means, points, semantic, instance, None, tcfg)
        return result.semantic, {"points": len(points), "gate": result.stats.gate, "spacing": result.stats.spacing}
    labels, gate = transfer_labels_vote(means, points, semantic, int(settings["vote_k"]), tcfg)
    return labels, {"points": len(points), "gate": gate, "spacing": None}


def sweep_transfer(config: StageSweepConfig, tasks: list, progress: Progress | None = None) -> tuple[list, list]:
    """(rows, skipped) of the transfer sweep over ``tasks``."""
    sweep = config.transfer
    shipped = TransferConfig()
    base = {"candidates": shipped.candidates, "backend": shipped.backend, "vote_k": 1, "point_fraction": 1.0,
            "mesh_sample_spacing": shipped.mesh_sample_spacing, "gate_factor": shipped.gate_factor,
            "gate_min": shipped.gate_min}
    grids = {"candidates": sweep.candidates, "backend": sweep.backend, "vote_k": sweep.vote_k,
             "point_fraction": sweep.point_fraction, "mesh_sample_spacing": sweep.mesh_sample_spacing,
             "gate_factor": sweep.gate_factor, "gate_min": sweep.gate_min}
    shipped_base = dict(base)
    base.update(sweep.base)
    rows = one_at_a_time(base, grids)
    prepared = []
    for task in tasks:
        scene = read_task_scene(task, config)
        require_mesh(scene, "transfer")
        prepared.append((scene, *noisy_oracle(scene, sweep, config.seed)))
    for backend in sweep.backend:  # warm-up (imports, first tree) outside the timings
        run_transfer_setting(prepared[0][0], prepared[0][1][:16], {**base, "backend": backend, "vote_k": 2}, config.seed)
    trials = []
    for knob, settings in rows:
        if progress:
            progress(f"transfer {knob}: {settings}")
        seconds, correct, scored, ignored, total, points, gates, spacings = [], 0, 0, 0, 0, 0, [], []
        unlabelled, kept = 0, 0
        for scene, means, truth in prepared:
            times = []
            for _ in range(max(1, sweep.repeats)):
                t0 = time.perf_counter()
                labels, facts = run_transfer_setting(scene, means, settings, config.seed)
                times.append(time.perf_counter() - t0)
            seconds.append(float(np.median(times)))
            acc = label_accuracy(labels, truth)
            correct += acc["correct"]
            scored += acc["scored"]
            ignored += int(((labels == IGNORE_LABEL) & (truth != IGNORE_LABEL)).sum())
            unlabelled += int((truth == IGNORE_LABEL).sum())
            kept += int(((labels == IGNORE_LABEL) & (truth == IGNORE_LABEL)).sum())
            total += len(labels)
            points += facts["points"]
            gates.append(facts["gate"])
            if facts["spacing"] is not None:
                spacings.append(facts["spacing"])
        agreement = (correct + kept) / total if total else float("nan")
        metrics = {"scored": scored, "correct": correct, "label_accuracy": correct / scored if scored else None,
                   "ignored_share": ignored / scored if scored else None,
                   "wrong_label_share": (scored - correct - ignored) / scored if scored else None,
                   "unlabelled": unlabelled, "unlabelled_kept": kept / unlabelled if unlabelled else None,
                   "gaussians": total, "label_points": points, "gate_median": float(np.median(gates)),
                   "spacing_median": float(np.median(spacings)) if spacings else None}
        is_default = settings == shipped_base
        trials.append(Trial("transfer", knob, settings, float(sum(seconds)), agreement, metrics, is_default))
    return trials, []
