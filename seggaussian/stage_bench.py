"""Per-stage speed/accuracy sweeps (``seggaussian bench --stage fit|transfer|render|build``).

Data flow: ``prepare_data`` (the default synthetic set, synthesized once into the work folder, or a raw
tree) -> ``discover_scenes`` -> one ``bench_<stage>`` sweep (one knob at a time around the base, which in a
full run is the stage's shipped default) -> ``Trial`` rows -> ``mark_pareto`` (minimize seconds, maximize
the stage's quality) -> ``StageBenchResult`` -> ``format_table`` / ``to_dict`` (JSON) / ``plot_trials`` (PNG).

Ground truth comes from the labelled mesh, never from the stage under test:
- fit: novel (held-out) views of the scene, scored at ``FitSweep.eval_scale`` of the source size whatever
  the fit's downscale (PSNR is the quality; SSIM and L1 are reported);
- transfer: oracle Gaussians sampled on the visible labelled triangles carry their true label (the corner
  of the sampled triangle with the largest barycentric weight, ``build.sample_oracle_gaussians``); their
  centres are pushed off the surface along the normal by seeded noise (``TransferSweep.surface_noise``)
  because fitted Gaussians sit a few cm off the mesh. Quality = label agreement over all Gaussians, ignore
  counted as a label: a Gaussian on a labelled surface must get its class (ignore is wrong), one on an
  unlabelled surface (rug, None-mapped object, masked disc) must stay ignore. ``label_accuracy`` (labelled
  surfaces only) and ``unlabelled_kept`` (unlabelled surfaces only) are reported beside it;
- render: the same labelled oracle Gaussians; label maps are compared with label images raycast from the
  mesh at the same resolution (hit triangle's corner with the largest barycentric weight, the rule that
  labels the oracle Gaussians). Quality = pixel agreement over the pixels whose ray hits the mesh, ignore
  counted as a label (a hit on an unlabelled surface must render ignore); ``labelled_agreement`` (labelled
  ground-truth pixels, the quality before 2026-11) and ``unlabelled_kept`` are reported beside it, and the
  ``vote`` knob's ``labelled_only`` row replays the former label-map rule (unlabelled contributors did not
  vote) on the same blend weights. The feature-render residual ``|render_features(W, f) - rasterize(features=f)|``
  is reported too;
- build: every setting must give byte-identical shards; quality = 1 when the Parquet shards equal those of
  the first (jobs 1, fresh folder) build, else 0; seconds per scene is the cost.

The k-nearest vote of the transfer bench (``transfer_labels_vote``) is implemented here on the same KD-tree
backends, candidates, spacing estimate and gate rule as ``seggaussian.transfer``; with k = 1 it equals
``transfer_labels`` exactly (tested), and ``transfer_labels_vote_reference`` is its brute-force reference.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.atomic import atomic_dir, atomic_path, sweep_temps, write_text_atomic
from seggaussian.constants import IGNORE_LABEL
from seggaussian.stage_bench_config import STAGES, StageBenchConfig

#: Quality axis of each stage (higher is better) and its unit, as printed in tables and plots.
QUALITY = {
    "fit": ("novel_psnr", "dB"),
    "transfer": ("label_agreement", "share"),
    "render": ("pixel_agreement", "share"),
    "build": ("identical_output", "0/1"),
}
#: Relative timing differences below this count as noise when marking the Pareto front of measured rows
#: (run-to-run noise on these VMs is 15-30% on medians, see shared/notes/cpu-kernels.md; 0.15 keeps a
#: setting whose only change is a threshold from "beating" an identical-cost row by noise alone).
PARETO_TIME_TOLERANCE = 0.15
#: Quality differences at most this large count as ties when marking the Pareto front: 0.1 percentage point
#: of accuracy / pixel agreement (below what one scene's sampling changes), 0.05 dB of PSNR (the fit's own
#: ``min_psnr_gain``); builds are 0/1.
QUALITY_TOLERANCE = {"fit": 0.05, "transfer": 1e-3, "render": 1e-3, "build": 0.0}
#: Marker file written into a synthesized set once every scene is in place.
SYNTH_DONE_MARKER = ".stage-bench-complete"

Progress = Callable[[str], None]


class BenchDataError(ValueError):
    """The bench cannot use the given data; the message names the path and what is missing."""


class Trial(NamedTuple):
    """One measured setting of a stage.

    Fields:
        stage: ``fit``, ``transfer``, ``render`` or ``build``.
        knob: the knob this row varies from the base (``base`` for the base row).
        settings: value of every swept knob in this row.
        seconds: time of the stage summed over the benched scenes (median over repeats); build rows: wall
            time of the whole build divided by the number of scenes.
        quality: the stage's quality (``QUALITY[stage]``; higher is better); NaN when not measurable.
        metrics: stage-specific errors and counts (JSON-ready).
        is_default: the row is the shipped default setting of the stage.
        pareto: no other row is at least as fast and at least as good, and strictly better in one.
    """

    stage: str
    knob: str
    settings: dict
    seconds: float
    quality: float
    metrics: dict
    is_default: bool
    pareto: bool = False


class StageBenchResult(NamedTuple):
    """All rows of one stage's sweep.

    Fields:
        stage: the benched stage.
        quality_name: name of the quality axis (``QUALITY[stage][0]``).
        trials: the rows, Pareto flags set.
        scenes: scene ids the rows were measured on.
        skipped: settings that could not run, with the reason (e.g. Ray not installed).
        machine: CPU count and load average when the sweep started (timings under load are marked).
        config: the ``StageBenchConfig`` as a dict.
    """

    stage: str
    quality_name: str
    trials: list
    scenes: list
    skipped: list
    machine: dict
    config: dict

    def to_dict(self) -> dict:
        out = self._asdict()
        out["trials"] = [t._asdict() for t in self.trials]
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "StageBenchResult":
        trials = [Trial(**{**t, "quality": float("nan") if t["quality"] is None else t["quality"]})
                  for t in d["trials"]]
        return cls(d["stage"], d["quality_name"], trials, list(d["scenes"]), list(d["skipped"]), dict(d["machine"]),
                   dict(d["config"]))

    @property
    def default_trials(self) -> list:
        return [t for t in self.trials if t.is_default]


# --- Pareto front -------------------------------------------------------------------------------------
def mark_pareto(trials: Sequence[Trial], time_tolerance: float = 0.0, quality_tolerance: float = 0.0) -> list[Trial]:
    """Rows with ``pareto`` set: not dominated in (seconds down, quality up). NaN quality is never optimal."""
    seconds = np.array([t.seconds for t in trials], np.float64)
    quality = np.array([t.quality for t in trials], np.float64)
    flags = pareto_mask(seconds, quality, time_tolerance, quality_tolerance)
    return [t._replace(pareto=bool(f)) for t, f in zip(trials, flags)]


def pareto_mask(seconds: np.ndarray, quality: np.ndarray, time_tolerance: float = 0.0,
                quality_tolerance: float = 0.0) -> np.ndarray:
    """``[T]`` bool: row i is optimal when no row j dominates it. With ``time_tolerance`` = 0, j dominates i
    when seconds_j <= seconds_i and quality_j >= quality_i with one of the two strict. With a tolerance t,
    times within a factor (1 +- t) count as equal (timing noise): j dominates i when quality_j >= quality_i
    and either seconds_j < (1 - t) seconds_i, or seconds_j <= (1 + t) seconds_i and quality_j > quality_i.
    With ``quality_tolerance`` q, qualities within q count as equal (j needs quality_j >= quality_i - q, and
    quality_j > quality_i + q to beat a row of equal time). Rows with a NaN are not optimal and dominate nothing."""
    seconds, quality = np.asarray(seconds, np.float64), np.asarray(quality, np.float64)
    ok = np.isfinite(seconds) & np.isfinite(quality)
    out = np.zeros(len(seconds), bool)
    for i in np.flatnonzero(ok):
        out[i] = not (ok & dominators(seconds, quality, i, time_tolerance, quality_tolerance)).any()
    return out


def dominators(seconds: np.ndarray, quality: np.ndarray, i: int, time_tolerance: float = 0.0,
               quality_tolerance: float = 0.0) -> np.ndarray:
    """``[T]`` bool: the rows that dominate row ``i`` (the rule of ``pareto_mask``)."""
    t, q = float(time_tolerance), float(quality_tolerance)
    if t == 0.0:
        faster, not_slower = seconds < seconds[i], seconds <= seconds[i]
    else:
        faster, not_slower = seconds < (1.0 - t) * seconds[i], seconds <= (1.0 + t) * seconds[i]
    return (quality >= quality[i] - q) & (faster | (not_slower & (quality > quality[i] + q)))


# --- sweeps ---------------------------------------------------------------------------------------------
def one_at_a_time(base: dict, grids: dict) -> list[tuple[str, dict]]:
    """(knob, settings) rows: the base, then each other value of each knob with the rest at base."""
    rows = [("base", dict(base))]
    for knob, values in grids.items():
        for value in values:
            if value != base[knob]:
                rows.append((knob, {**base, knob: value}))
    return rows


# --- data -----------------------------------------------------------------------------------------------
def prepare_data(config: StageBenchConfig, progress: Progress | None = None) -> Path:
    """The raw tree to bench: ``config.data``, or the default synthetic set synthesized (once) into
    ``config.work_dir`` (written to a temporary folder, then renamed)."""
    if config.data is not None:
        root = Path(config.data)
        if not root.is_dir():
            raise BenchDataError(f"{root}: --data does not exist or is not a folder")
        if (root / "manifest.json").is_file() or (root / ".build").is_dir():
            raise BenchDataError(f"{root}: this is a built DATASET; the stage bench needs the raw tree it was built "
                                 "from (meshes are the ground truth)")
        return root
    from seggaussian.sources.synthetic import SynthConfig, synthesize

    n_scannetpp, n_replica = config.synthetic_counts
    name = (f"synthetic-s{config.seed}-w{config.synthetic_width}-v{config.synthetic_views}"
            f"-e{config.synthetic_max_edge:g}-{n_scannetpp}x{n_replica}")
    root = work_dir(config) / name
    if (root / SYNTH_DONE_MARKER).is_file():
        return root
    sweep_temps(root.parent)  # staging folders of a killed earlier run
    synth = SynthConfig(width=config.synthetic_width, num_views=config.synthetic_views,
                        max_edge=config.synthetic_max_edge)
    with atomic_dir(root) as staging:
        for layout, count in (("scannetpp", n_scannetpp), ("replica", n_replica)):
            if count > 0:
                if progress:
                    progress(f"synthesizing {count} {layout} scenes into {root}")
                synthesize(staging / layout, count, config.seed, layout=layout, config=synth)
        write_text_atomic(staging / SYNTH_DONE_MARKER, "ok\n")
    return root


def work_dir(config: StageBenchConfig) -> Path:
    return Path(config.work_dir).expanduser()


def build_source(root: Path) -> str:
    """``BuildConfig.source`` of a raw tree: ``synthetic`` for a root holding ``scannetpp/`` or ``replica/``."""
    from seggaussian.build import detect_layout

    if (root / "scannetpp").is_dir() or (root / "replica").is_dir():
        return "synthetic"
    return detect_layout(root)


def discover_scenes(root: Path, config: StageBenchConfig) -> list:
    """``build.SceneTask`` rows of the raw tree (at most ``config.scenes``)."""
    from seggaussian.build import discover
    from seggaussian.build_config import BuildConfig

    tasks, failures = discover(BuildConfig(source=build_source(root), root=root, out=work_dir(config) / "unused",
                                           synthesize_missing=False, progress=False))
    if failures:
        raise BenchDataError(f"{root}: " + "; ".join(f"{f.scene_id}: {f.reason}" for f in failures))
    if not tasks:
        raise BenchDataError(f"{root}: no scene found (expected a ScanNet++ or Replica layout)")
    return tasks[: config.scenes] if config.scenes else tasks


def read_task_scene(task, config: StageBenchConfig):
    """The ``Scene`` of a task (Replica rooms without views are rendered into the work folder)."""
    from seggaussian.build import reader

    if task.domain == "replica":
        return reader("replica").read_scene(task.root, task.scene_id,
                                            cache_dir=work_dir(config) / "replica_views")
    return reader(task.domain).read_scene(task.root, task.scene_id)


def require_mesh(scene, stage: str) -> None:
    if scene.faces is None or not len(scene.faces):
        raise BenchDataError(f"scene {scene.scene_id} ({scene.root}): the {stage} bench needs a labelled mesh "
                             "(faces) as ground truth; this scene is a point cloud")


def oracle_labelled(scene, num_gaussians: int, seed: int):
    """(oracle Gaussians, true class [N]) sampled on the scene's visible labelled triangles."""
    from seggaussian.build import sample_oracle_gaussians, scene_seed
    from seggaussian.build_config import OracleConfig

    rng = np.random.default_rng(scene_seed(seed, scene.scene_id))
    return sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces,
                                   replace(OracleConfig(), num_gaussians=int(num_gaussians)), rng,
                                   tuple(v.camera for v in scene.views))


def machine_info() -> dict:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    cpus = os.cpu_count() or 1
    return {"cpus": cpus, "load_average_1min": load[0], "under_load": bool(load[0] > 0.5 * cpus)}


# --- transfer -------------------------------------------------------------------------------------------
def transfer_labels_vote(
    gaussian_means: np.ndarray,  # [N, 3]
    points: np.ndarray,  # [P, 3]
    semantic: np.ndarray,  # [P]
    k: int,
    config,  # TransferConfig
) -> tuple[np.ndarray, float]:  # ([N] int32 labels, gate)
    """Majority vote of the ``k`` nearest candidates within the distance gate (ties: the label of the
    nearest voter). Same candidates (``config.candidates``: with ``all``, unlabelled points vote for
    ignore), spacing estimate and gate rule as ``transfer.transfer_labels``; with ``k = 1`` the labels are
    identical to it."""
    from seggaussian.transfer import median_spacing

    means = np.asarray(gaussian_means, np.float64)
    points = np.asarray(points, np.float64)
    semantic = np.asarray(semantic).astype(np.int32)
    if config.candidates not in ("all", "labelled"):
        raise ValueError(f"transfer_labels_vote: candidates must be 'all' or 'labelled', got {config.candidates!r}")
    cand = np.arange(len(points)) if config.candidates == "all" else np.flatnonzero(semantic != IGNORE_LABEL)
    cpts, csem = points[cand], semantic[cand]
    labels = np.full(len(means), IGNORE_LABEL, np.int32)
    if not len(cpts) or not len(means):
        return labels, float(config.max_distance or config.gate_min)
    query = _knn_backend(cpts, config.backend)
    spacing = median_spacing(query, cpts, config)
    gate = float(config.max_distance) if config.max_distance is not None else max(config.gate_min,
                                                                                 config.gate_factor * spacing)
    finite = np.flatnonzero(np.isfinite(means).all(axis=1))
    kk = int(min(k, len(cpts)))
    d, i = query(means[finite], kk)  # [Q, kk], ascending distance
    labels[finite] = vote(csem[i], d <= gate)
    return labels, gate


def vote(labels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``[Q]`` majority label of each row of ``labels`` ``[Q, k]`` over its ``valid`` slots (slots ordered
    nearest first; ties go to the earliest slot; IGNORE_LABEL votes like any label); IGNORE_LABEL for rows
    without a valid slot."""
    counts = np.zeros(labels.shape, np.int64)
    for j in range(labels.shape[1]):
        counts += valid[:, j : j + 1] & (labels == labels[:, j : j + 1])
    counts = np.where(valid, counts, -1)
    best = np.argmax(counts, axis=1)  # first maximum = nearest voter among the tied labels
    out = labels[np.arange(len(labels)), best].astype(np.int32)
    return np.where(valid.any(axis=1), out, IGNORE_LABEL).astype(np.int32)


def transfer_labels_vote_reference(means, points, semantic, k: int, gate: float, candidates: str = "all") -> np.ndarray:
    """Brute-force reference of ``transfer_labels_vote`` for a given gate (tiny inputs only)."""
    means, points = np.asarray(means, np.float64), np.asarray(points, np.float64)
    semantic = np.asarray(semantic).astype(np.int32)
    cand = np.ones(len(points), bool) if candidates == "all" else semantic != IGNORE_LABEL
    cpts, csem = points[cand], semantic[cand]
    out = np.full(len(means), IGNORE_LABEL, np.int32)
    for r, x in enumerate(means):
        if not np.isfinite(x).all() or not len(cpts):
            continue
        d = np.sqrt(((cpts - x) ** 2).sum(axis=1))
        order = np.argsort(d, kind="stable")[:k]
        voters = [(csem[j], d[j]) for j in order if d[j] <= gate]
        if not voters:
            continue
        tally: dict[int, int] = {}
        for lab, _ in voters:
            tally[int(lab)] = tally.get(int(lab), 0) + 1
        top = max(tally.values())
        out[r] = next(int(lab) for lab, _ in voters if tally[int(lab)] == top)
    return out


def _knn_backend(cpts: np.ndarray, backend: str):
    """A ``query(x [Q, 3], k) -> (distances [Q, k], indices [Q, k])`` closure on scipy or open3d."""
    if backend == "scipy":
        from scipy.spatial import cKDTree

        tree = cKDTree(cpts)

        def query(x, k):
            d, i = tree.query(x, k=k, workers=-1)
            return np.asarray(d, np.float64).reshape(len(x), k), np.asarray(i, np.int64).reshape(len(x), k)

        return query
    if backend == "open3d":
        import open3d as o3d

        nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(cpts)))
        nns.knn_index()

        def query(x, k):
            if not len(x):
                return np.zeros((0, k)), np.zeros((0, k), np.int64)
            i, d2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(x)), k)
            return np.sqrt(np.maximum(d2.numpy().astype(np.float64), 0.0)), i.numpy().astype(np.int64)

        return query
    raise ValueError(f"transfer bench: backend must be scipy or open3d, got {backend!r}")


def _noisy_oracle(scene, sweep, seed: int):
    """(Gaussian centres pushed off the surface [N, 3], true class [N])."""
    from seggaussian.build import scene_seed

    gaussians, truth = oracle_labelled(scene, sweep.num_gaussians, seed)
    normals = gaussians.rotation_matrices()[:, :, 2].astype(np.float64)
    rng = np.random.default_rng(scene_seed(seed + 1, scene.scene_id))
    offsets = rng.normal(0.0, sweep.surface_noise, len(gaussians)) if sweep.surface_noise > 0 else 0.0
    return gaussians.means.astype(np.float64) + normals * np.reshape(offsets, (-1, 1)), truth


def run_transfer_setting(scene, means: np.ndarray, settings: dict, seed: int) -> tuple[np.ndarray, dict]:
    """Labels of ``means`` under one transfer setting (the timed work: mesh densification, subsample,
    KD-tree, query). Returns (labels [N], facts)."""
    from seggaussian.build_config import TransferConfig
    from seggaussian.transfer import densify_labelled_mesh, transfer_labels

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


def bench_transfer(config: StageBenchConfig, tasks: list, progress: Progress | None = None) -> tuple[list, list]:
    from seggaussian.build_config import TransferConfig
    from seggaussian.transfer import label_accuracy

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
        prepared.append((scene, *_noisy_oracle(scene, sweep, config.seed)))
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


# --- render ---------------------------------------------------------------------------------------------
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


def labelled_only_blend(blend, semantic):
    """The blend weights on which the shipped vote reproduces the former label-map rule (only labelled
    contributors voted): unlabelled contributors' weight moves into ``residual_alpha``, so the coverage
    test (weights + residual >= min_alpha) is unchanged and they can no longer win."""
    import torch

    from seggaussian.render.blend import BlendWeights

    used = blend.ids >= 0
    unlabelled = used & (semantic[blend.ids.clamp_min(0)] == IGNORE_LABEL)
    moved = torch.where(unlabelled, blend.weights, torch.zeros_like(blend.weights))
    return BlendWeights(blend.ids, blend.weights - moved, blend.residual_alpha + moved.sum(-1))


def evenly_spaced(items: Sequence, count: int) -> list:
    if count >= len(items):
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def render_camera(camera, settings: dict, reference_width: int):
    """The camera of a render row: ``scale`` of the stored size, or the tiny reference width."""
    if settings["backend"] == "reference" or settings.get("tiny"):
        return camera.scaled(reference_width / camera.width)
    return camera if settings["scale"] == 1.0 else camera.scaled(settings["scale"])


def bench_render(config: StageBenchConfig, tasks: list, progress: Progress | None = None) -> tuple[list, list]:
    import torch

    from seggaussian.build import view_scale
    from seggaussian.build_config import ViewConfig
    from seggaussian.constants import read_class_names
    from seggaussian.render import compute_blend_weights, rasterize, render_features, render_label_maps
    from seggaussian.render.rasterize import camera_tensors, default_backend
    from seggaussian.sources.raycast import MeshRaycaster

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
            raise BenchDataError(f"scene {scene.scene_id} ({scene.root}): no views to render")
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
    _warm_up_render(prepared[0][1], prepared[0][3][0].camera, sweep.reference_width, fast)
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


def _warm_up_render(t: dict, camera, width: int, backend: str) -> None:
    """One tiny blend-weights call and forward/backward rasterization (loads the numba kernels)."""
    import torch

    from seggaussian.render import compute_blend_weights, rasterize
    from seggaussian.render.rasterize import camera_tensors

    cam = camera.scaled(width / camera.width)
    viewmat, K = camera_tensors(cam)
    sub = {k: v[:256] for k, v in t.items()}
    compute_blend_weights(sub["means"], sub["quats"], sub["log_scales"], sub["opacity_logits"], viewmat, K,
                          cam.width, cam.height, top_k=4, backend=backend)
    means = sub["means"].clone().requires_grad_(True)
    out = rasterize(means, sub["quats"], sub["log_scales"], sub["opacity_logits"], viewmat, K, cam.width, cam.height,
                    sh=sub["sh"], sh_degree=0, backend=backend)
    out.image.sum().backward()


# --- fit ------------------------------------------------------------------------------------------------
def score_novel_views(gaussians, views, sh_degree: int, eval_scale: float, background) -> dict:
    """Mean PSNR / SSIM / L1 of the fitted Gaussians on ``views`` at ``eval_scale`` of the source size."""
    import cv2
    import torch

    from seggaussian.fit import read_image
    from seggaussian.losses import l1_loss, psnr, ssim
    from seggaussian.render import render_gaussians

    psnrs, ssims, l1s = [], [], []
    for view in views:
        rgb = read_image(view.image_path, view.camera)
        cam = view.camera if eval_scale == 1.0 else view.camera.scaled(eval_scale)
        if (cam.width, cam.height) != (view.camera.width, view.camera.height):
            rgb = cv2.resize(rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        target = torch.from_numpy(rgb.astype(np.float32) / 255.0)
        with torch.no_grad():
            image = render_gaussians(gaussians, cam, sh_degree=sh_degree,
                                     background=torch.tensor(background, dtype=torch.float32)).image.clamp(0, 1)
        psnrs.append(float(psnr(image, target)))
        ssims.append(float(ssim(image, target)))
        l1s.append(float(l1_loss(image, target)))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "l1": float(np.mean(l1s))}


def bench_fit(config: StageBenchConfig, tasks: list, progress: Progress | None = None) -> tuple[list, list]:
    from seggaussian.build import scene_seed
    from seggaussian.fit import fit_scene
    from seggaussian.fit_config import FitConfig

    sweep = config.fit
    base_config = replace(FitConfig(), **sweep.base)
    knobs = ("iterations", "downscale", "max_gaussians", "patience")
    base = {k: getattr(base_config, k) for k in knobs}
    rows = one_at_a_time(base, {k: getattr(sweep, k) for k in knobs})
    scenes = []
    for task in tasks:
        scene = read_task_scene(task, config)
        novel = scene.views_with_role("novel")
        if not novel or not scene.views_with_role("train"):
            raise BenchDataError(f"scene {scene.scene_id} ({scene.root}): the fit bench needs train and held-out "
                                 "(novel) views")
        scenes.append((scene, novel))
    from seggaussian.render.rasterize import default_backend

    g0, _ = oracle_labelled(scenes[0][0], 256, config.seed)
    _warm_up_render(g0.to_torch(), scenes[0][1][0].camera, 32, default_backend())
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
                                            sweep.eval_scale, fit_config.background))
            facts.append({"scene": scene.scene_id, "iterations": result.metrics["iterations"],
                          "gaussians": result.metrics["gaussians"],
                          "early_stop": result.metrics["early_stop_reason"]})
        metrics = {"novel_ssim": float(np.mean([s["ssim"] for s in scores])),
                   "novel_l1": float(np.mean([s["l1"] for s in scores])),
                   "iterations_run": int(sum(f["iterations"] for f in facts)),
                   "gaussians": int(sum(f["gaussians"] for f in facts)), "per_scene": facts}
        trials.append(Trial("fit", knob, settings, seconds, float(np.mean([s["psnr"] for s in scores])), metrics,
                            fit_config == FitConfig()))
    return trials, []


# --- build ----------------------------------------------------------------------------------------------
def shards_digest(dataset: Path) -> str:
    """sha256 over the relative paths and bytes of the dataset's Parquet files (the cache excluded)."""
    h = hashlib.sha256()
    for path in sorted(p for p in Path(dataset).rglob("*.parquet") if ".build" not in p.relative_to(dataset).parts):
        h.update(str(path.relative_to(dataset)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def bench_build(config: StageBenchConfig, tasks: list, root: Path, progress: Progress | None = None) -> tuple[list, list]:
    from seggaussian.build import STAGES as BUILD_STAGES
    from seggaussian.build import build_dataset
    from seggaussian.build_config import BuildConfig, OracleConfig, ViewConfig

    sweep = config.build
    shipped = BuildConfig(source="synthetic", root=root, out=root)
    skipped, trials = [], []
    reference_digest = None
    for executor in sweep.executors:
        if executor == "ray":
            try:
                import ray  # noqa: F401
            except ImportError:
                skipped.append("executor ray: Ray is not installed (pip install ray)")
                continue
        for jobs in sweep.jobs:
            out = work_dir(config) / "build-bench" / f"{executor}-j{jobs}"
            if out.exists():
                shutil.rmtree(out)
            bcfg = BuildConfig(source=build_source(root), root=root, out=out, scenes=tuple(t.scene_id for t in tasks),
                               jobs=jobs, executor=executor, gaussians="oracle", progress=False,
                               synthesize_missing=False, seed=config.seed,
                               oracle=replace(OracleConfig(), num_gaussians=sweep.num_gaussians),
                               views=replace(ViewConfig(), max_image_side=sweep.max_image_side))
            for cache in sorted(set(sweep.cache)):  # False (fresh folder) first, then the unchanged rerun
                if not cache and (out / ".build").exists():
                    shutil.rmtree(out)
                if progress:
                    progress(f"build executor={executor} jobs={jobs} cache={'on' if cache else 'off'}")
                t0 = time.perf_counter()
                report = build_dataset(bcfg)
                seconds = time.perf_counter() - t0
                digest = shards_digest(out)
                if reference_digest is None:
                    reference_digest = digest
                n = len(report.outcomes)
                per_scene = []
                for o in report.outcomes:
                    info = o.info or {}
                    tr = info.get("transfer", {})
                    per_scene.append({
                        "scene": o.scene_id, "status": o.status, "stages_run": list(o.stages_run),
                        "stages_cached": [s for s in BUILD_STAGES if s not in o.stages_run and o.status != "failed"],
                        "views_stored": info.get("num_views"),
                        "gaussians": info.get("num_gaussians"),
                        "gaussians_ignored": tr.get("ignored"),
                        "gaussians_outside_box": tr.get("outside_box"),
                        "gaussians_beyond_gate": tr.get("beyond_gate"),
                        "reason": o.reason,
                    })
                failed = sum(o.status == "failed" for o in report.outcomes)
                metrics = {"scenes": n, "failed": failed,
                           "scenes_per_minute": 60.0 * n / seconds if seconds > 0 else None,
                           "stages_cached": sum(len(p["stages_cached"]) for p in per_scene),
                           "stages_run": sum(len(p["stages_run"]) for p in per_scene),
                           "shards_rewritten": bool(report.assembled), "per_scene": per_scene}
                settings = {"executor": executor, "jobs": jobs, "cache": "on" if cache else "off"}
                quality = 1.0 if digest == reference_digest and not failed else 0.0
                is_default = (executor == shipped.executor and jobs == shipped.jobs and cache)
                first = trials[0].settings if trials else settings
                knob = "+".join(k for k in settings if settings[k] != first[k]) or "base"
                trials.append(Trial("build", knob, settings, seconds / max(n, 1), quality, metrics, is_default))
    return trials, skipped


# --- the bench ------------------------------------------------------------------------------------------
def run_stage_bench(config: StageBenchConfig, progress: Progress | None = None) -> StageBenchResult:
    """Sweep one stage on the configured data; see the module docstring."""
    machine = machine_info()
    root = prepare_data(config, progress)
    tasks = discover_scenes(root, config)
    if config.stage == "fit":
        trials, skipped = bench_fit(config, tasks, progress)
    elif config.stage == "transfer":
        trials, skipped = bench_transfer(config, tasks, progress)
    elif config.stage == "render":
        trials, skipped = bench_render(config, tasks, progress)
    elif config.stage == "build":
        trials, skipped = bench_build(config, tasks, root, progress)
    else:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {config.stage!r}")
    trials = mark_pareto(trials, PARETO_TIME_TOLERANCE, QUALITY_TOLERANCE[config.stage])
    return StageBenchResult(config.stage, QUALITY[config.stage][0], trials,
                            [t.scene_id for t in tasks], skipped, machine, config.to_dict())


# --- output ---------------------------------------------------------------------------------------------
def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not np.isfinite(value):
            return "nan"
        return f"{value:.4g}"
    return str(value)


#: Extra columns of each stage's table (metric keys).
TABLE_METRICS = {
    "fit": ("novel_ssim", "novel_l1", "iterations_run", "gaussians"),
    "transfer": ("label_accuracy", "unlabelled_kept", "ignored_share", "wrong_label_share", "spacing_median",
                 "gate_median", "label_points"),
    "render": ("labelled_agreement", "unlabelled_kept", "ignored_share", "feature_residual_mean", "feature_residual_max",
               "residual_alpha_mean", "image_size"),
    "build": ("scenes_per_minute", "stages_run", "stages_cached", "shards_rewritten"),
}


def seconds_label(stage: str) -> str:
    """What the seconds of a row are: per scene for builds, summed over the scenes for the other stages."""
    return "seconds per scene" if stage == "build" else "seconds (all scenes)"


def format_table(result: StageBenchResult) -> str:
    """Markdown table of the rows, fastest first; ``P`` marks Pareto-optimal rows, ``D`` the shipped default."""
    if not result.trials:
        return f"(no {result.stage} rows)"
    knobs = list(result.trials[0].settings)
    extra = TABLE_METRICS[result.stage]
    header = ["mark", "varied", *knobs, seconds_label(result.stage), result.quality_name, *extra]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for t in sorted(result.trials, key=lambda t: (t.seconds, -t.quality if np.isfinite(t.quality) else 0)):
        mark = ("P" if t.pareto else "") + ("D" if t.is_default else "")
        cells = [mark or ".", t.knob, *[_fmt(t.settings.get(k)) for k in knobs], f"{t.seconds:.3f}", _fmt(t.quality),
                 *[_fmt(t.metrics.get(k)) for k in extra]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _row_label(t: Trial) -> str:
    """``knob=value`` of a row (``a=1, b=2`` for a row varying several knobs; ``base`` for the base)."""
    if t.knob == "base":
        return "base"
    return ", ".join(f"{k}={_fmt(t.settings.get(k))}" for k in t.knob.split("+"))


def default_verdict(result: StageBenchResult) -> str:
    """One sentence: is the shipped default on the Pareto front?"""
    defaults = result.default_trials
    if not defaults:
        return f"{result.stage}: the shipped default was not among the rows (quick/base overrides)"
    parts = []
    for d in defaults:
        if d.pareto:
            parts.append(f"{result.stage}: shipped default is Pareto-optimal "
                         f"({result.quality_name} {_fmt(d.quality)} in {d.seconds:.3f} s)")
        else:
            seconds = np.array([t.seconds for t in result.trials], np.float64)
            quality = np.array([t.quality for t in result.trials], np.float64)
            rows = dominators(seconds, quality, result.trials.index(d), PARETO_TIME_TOLERANCE,
                              QUALITY_TOLERANCE[result.stage])
            better = [t for t, r in zip(result.trials, rows) if r and np.isfinite(t.quality)]
            alt = min(better, key=lambda t: t.seconds) if better else None
            parts.append(f"{result.stage}: shipped default is NOT on the Pareto front ({result.quality_name} "
                         f"{_fmt(d.quality)} in {d.seconds:.3f} s)"
                         + (f"; dominated by {_row_label(alt)} ({_fmt(alt.quality)} in {alt.seconds:.3f} s)"
                            if alt else ""))
    return "; ".join(parts)


def plot_trials(results: Sequence[StageBenchResult], path: Path) -> Path:
    """A PNG with one panel per stage: seconds (log) against quality, the Pareto front joined, the shipped
    default circled. Needs matplotlib (optional): ImportError with the install command otherwise."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError("--plot needs matplotlib: pip install matplotlib") from None
    path = Path(path)
    ncols = min(3, max(1, len(results)))
    nrows = -(-len(results) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.5 * ncols, 4.2 * nrows), squeeze=False)
    for ax in axes.flat[len(results):]:
        ax.set_visible(False)
    for ax, result in zip(axes.flat, results):
        xs = np.array([t.seconds for t in result.trials])
        ys = np.array([t.quality for t in result.trials])
        ax.scatter(xs, ys, c=["tab:red" if t.pareto else "tab:gray" for t in result.trials], s=24, zorder=2)
        front = sorted((t for t in result.trials if t.pareto), key=lambda t: t.seconds)
        if front:
            ax.step([t.seconds for t in front], [t.quality for t in front], where="post", c="tab:red", lw=1, zorder=1)
        for t in result.trials:
            label = _row_label(t)
            ax.annotate(label, (t.seconds, t.quality), fontsize=6, xytext=(3, 3), textcoords="offset points")
            if t.is_default:
                ax.scatter([t.seconds], [t.quality], s=140, facecolors="none", edgecolors="tab:blue", lw=1.5,
                           zorder=3, label="shipped default")
        if np.all(xs > 0):
            ax.set_xscale("log")
        ax.set_xlabel(seconds_label(result.stage))
        ax.set_ylabel(f"{result.quality_name} ({QUALITY[result.stage][1]})")
        ax.set_title(f"{result.stage} ({len(result.scenes)} scene{'s' if len(result.scenes) != 1 else ''})")
        ax.grid(alpha=0.3)
        if any(t.is_default for t in result.trials):
            ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return path


def format_build_scenes(result: StageBenchResult) -> str:
    """Per-scene table of every build row: what ran, what was cached, views stored, Gaussians left unlabelled."""
    header = ["executor", "jobs", "cache", "scene", "status", "stages run", "stages cached", "views stored",
              "gaussians", "ignored (outside box / beyond gate)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for t in result.trials:
        for p in t.metrics.get("per_scene", []):
            lines.append("| " + " | ".join([
                t.settings["executor"], str(t.settings["jobs"]), t.settings["cache"], p["scene"], p["status"],
                ",".join(p["stages_run"]) or "-", ",".join(p["stages_cached"]) or "-", _fmt(p.get("views_stored")),
                _fmt(p.get("gaussians")),
                f"{_fmt(p.get('gaussians_ignored'))} ({_fmt(p.get('gaussians_outside_box'))} / "
                f"{_fmt(p.get('gaussians_beyond_gate'))})"]) + " |")
    return "\n".join(lines)


def write_markdown(results: Sequence[StageBenchResult], path: Path, command_line: str) -> Path:
    """The tables of ``results`` with the command that produced them and the default verdicts (atomic write)."""
    path = Path(path)
    lines = ["# Stage benchmarks: time against error", "",
             f"Produced by `{command_line}`.", "",
             "`P` = Pareto-optimal (no other row is at least as fast and at least as good), `D` = shipped default. "
             "Rows vary one knob from the base (`varied`); seconds are summed over the scenes.", ""]
    for r in results:
        m = r.machine
        lines += [f"## {r.stage}: {r.quality_name} ({QUALITY[r.stage][1]}) vs seconds", "",
                  f"{len(r.scenes)} scenes: {', '.join(r.scenes)}. Machine: {m.get('cpus')} CPUs, load average "
                  f"{_fmt(m.get('load_average_1min'))}" + (" -- **measured under load**" if m.get("under_load") else ""),
                  ""]
        if r.config.get("command"):
            lines += [f"Measured by `{r.config['command']}`.", ""]
        lines += [format_table(r), "", default_verdict(r), ""]
        if r.stage == "build":
            lines += [format_build_scenes(r), ""]
        lines += [f"- skipped: {s}" for s in r.skipped]
        if r.skipped:
            lines.append("")
    write_text_atomic(path, "\n".join(lines))
    return path
