"""The OVGaussian benchmark (paper Table 1): CSA, OVA, NVA, CDA in 3D and 2D from confusion matrices.

Protocol (``data_specs/BENCHMARK.md`` is the prose version):

- Vocabulary: K class ids (top-100 indices) from ``seggaussian.core.classes.benchmark_vocabulary(K)``.
  Every prediction is an index into this vocabulary (argmax of the predictor's K class scores).
- Ground truth: a top-100 id that is not in the vocabulary, and IGNORE_LABEL, become IGNORE (not scored).
- 3D: one label per Gaussian from its per-Gaussian vector; scored against ``extras['semantic']``.
- 2D: per view, the per-Gaussian vectors are blended with the view's blend weights (M = W S), then
  classified per pixel, one band of rows at a time (bounded memory; nothing per pixel is stored); pixels with accumulated alpha < ``min_alpha`` have no prediction (a miss where
  the ground truth has a label). Scored against the stored label map of the view.
- One confusion matrix per (split, dim) accumulated over all scenes/views of the set:
  CSA = mIoU over the K classes, OVA = mIoU over the unseen classes (same matrix as CSA: val scenes,
  all views), NVA = mIoU over the K classes on the novel-role views of the train scenes (2D only),
  CDA = mIoU over the common classes (vocabulary classes present in the labels of the xval scenes),
  scored on the xval (Replica) scenes.

A predictor is anything with ``encode(scene) -> [N, F]`` per-Gaussian vectors (linear in 2D: they
are blended) and ``classify(vectors [M, F], class_ids [K]) -> [M, K]`` scores. The trained model, the
baselines of ``baseline.py`` and test stand-ins all fit it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Protocol, Sequence

import numpy as np

from ovgaussian.bench import baselines as baseline
from ovgaussian.bench.config import (
    DEFAULT_BAND_ROWS,
    DEFAULT_MIN_ALPHA,
    METRIC_DIMS,
    METRIC_SPLITS,
    METRICS,
    TABLE1_COLUMNS,
    BenchConfig,
)
from ovgaussian.bench.bootstrap import DEFAULT_DRAWS, Interval, bootstrap_miou
from ovgaussian.openvocab.calibration import Calibration, StackedPredictor, calibrate
from ovgaussian.openvocab.class_offsets import OffsetPredictor, fit_offsets
from ovgaussian.run.checkpoint import CONFIG_NAME, latest_checkpoint, read_json, weights_sha256
from ovgaussian.run.devices import resolve_device
from ovgaussian.openvocab.feature_synthesis import fit_generative_predictor
from ovgaussian.metrics import ConfusionMatrix, SegmentationScores
from ovgaussian.predict.query import load_ensemble, load_model_predictor
from ovgaussian.text.prompt_ensemble import PROMPT_TEMPLATES
from ovgaussian.run.config import config_to_dict
from ovgaussian.predict.view_labels import BlendFunctions, default_blend_functions, stream_view_labels
from ovgaussian.text.vocabulary import Vocabulary, benchmark_vocabulary, to_vocabulary_labels, training_vocabulary
from seggaussian import shards
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.shards import sha256_file


class Predictor(Protocol):
    """What the benchmark scores."""

    name: str

    def encode(self, scene) -> np.ndarray:
        """``[N, F]`` float per-Gaussian vectors of a SceneRecord (blended linearly for 2D)."""

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        """``[M, F]`` vectors -> ``[M, K]`` scores of the K classes ``class_ids`` (top-100 ids)."""


class MetricResult(NamedTuple):
    """One metric in one dimension.

    Fields:
        metric, dim: e.g. ``CSA``, ``3d``.
        split: split it was scored on.
        classes: ``[S]`` vocabulary indices averaged over (before dropping NaN classes).
        scores: per-class IoU/accuracy of the set's confusion matrix and the means over ``classes``.
        num_scenes: scenes that contributed; num_views: views (2D) that contributed.
    """

    metric: str
    dim: str
    split: str
    classes: np.ndarray
    scores: SegmentationScores
    num_scenes: int
    num_views: int


class BenchResult(NamedTuple):
    """All metrics of one evaluation plus what identifies it (for the JSON report)."""

    vocabulary: Vocabulary
    results: dict  # {(dim, metric): MetricResult}
    common_classes: np.ndarray | None
    confusion: dict  # {(split, dim): [K, K+1] counts}
    scene_confusion: dict | None = None  # {(split, dim): [S, K, K+1] counts, one matrix per scored scene}


# ---------------------------------------------------------------------------------------------
# vocabulary and labels
# ---------------------------------------------------------------------------------------------
# ---------------------------------------------------------------------------------------------
# prediction
# ---------------------------------------------------------------------------------------------
def classify_vectors(predictor: Predictor, vectors: np.ndarray, vocabulary: Vocabulary,
                     chunk_rows: int = 65536) -> np.ndarray:
    """``[M, F]`` vectors -> ``[M]`` vocabulary indices (argmax of the K scores), in chunks of rows."""
    out = np.empty(vectors.shape[0], dtype=np.int64)
    for start in range(0, vectors.shape[0], chunk_rows):
        scores = np.asarray(predictor.classify(vectors[start:start + chunk_rows], vocabulary.class_ids))
        if scores.shape != (min(chunk_rows, vectors.shape[0] - start), vocabulary.class_ids.size):
            raise ValueError(f"predictor {getattr(predictor, 'name', predictor)!r} returned scores of shape "
                             f"{scores.shape}, expected (rows, {vocabulary.class_ids.size})")
        if not np.isfinite(scores).any(axis=1).all():
            raise ValueError(f"predictor {getattr(predictor, 'name', predictor)!r} returned a row with no finite score")
        out[start:start + scores.shape[0]] = np.argmax(np.where(np.isnan(scores), -np.inf, scores), axis=1)
    return out


def predict_view_labels(predictor: Predictor, vectors: np.ndarray, blender, vocabulary: Vocabulary,
                        functions: BlendFunctions, min_alpha: float, chunk_rows: int = 65536,
                        band_rows: int = DEFAULT_BAND_ROWS) -> np.ndarray:
    """``[H, W]`` vocabulary indices of one view, IGNORE_LABEL where the accumulated alpha < ``min_alpha``."""
    return stream_view_labels(lambda rendered: classify_vectors(predictor, rendered, vocabulary, chunk_rows),
                              vectors, blender, functions, min_alpha, band_rows)


# ---------------------------------------------------------------------------------------------
# the protocol
# ---------------------------------------------------------------------------------------------
def _views_with_role(scene, role: str | None, limit: int | None):
    views = [v for v in scene.views if role is None or v.role == role]
    views.sort(key=lambda v: v.name)
    return views if limit is None else views[:limit]


def _present_labels(scene) -> set[int]:
    """Top-100 ids present in a scene's Gaussian labels and stored label maps."""
    present = set()
    semantic = scene.gaussians.extras.get("semantic")
    if semantic is not None:
        present.update(int(v) for v in np.unique(semantic))
    for view in scene.views:
        if view.semantic is not None:
            present.update(int(v) for v in np.unique(view.semantic))
    present.discard(IGNORE_LABEL)
    return present


def evaluate(
    predictor: Predictor,
    scenes_by_split: dict[str, Iterable],
    vocabulary: Vocabulary,
    *,
    metrics: Sequence[str] = METRICS,
    dims: Sequence[str] = ("3d", "2d"),
    min_alpha: float = DEFAULT_MIN_ALPHA,
    blend_top_k: int = 16,
    max_views_per_scene: int | None = None,
    chunk_rows: int = 65536,
    functions: BlendFunctions | None = None,
    progress: Callable[[str, str], None] | None = None,
    band_rows: int = DEFAULT_BAND_ROWS,
) -> BenchResult:
    """Score ``predictor`` on the scenes of each split (``{split: iterable of SceneRecord}``).

    Each split is iterated once; a scene's per-Gaussian vectors are computed once and reused for its
    3D labels and every view. Views are streamed: one view's blend weights at a time, ``band_rows`` rows at once.
    Returns per-(dim, metric) results, the confusion matrices and one matrix per scored scene (for the
    bootstrap intervals of ``ovgaussian.bench.bootstrap``).
    """
    unknown = set(metrics) - set(METRICS)
    if unknown:
        raise ValueError(f"unknown metrics {sorted(unknown)}; choose from {METRICS}")
    if set(dims) - {"3d", "2d"}:
        raise ValueError(f"unknown dims {sorted(set(dims) - {'3d', '2d'})}; choose from 3d, 2d")
    k = vocabulary.class_ids.size
    wanted = [(d, m) for m in metrics for d in METRIC_DIMS[m] if d in dims]
    if not wanted:
        raise ValueError(f"nothing to compute: {', '.join(metrics)} in {', '.join(dims)} (NVA exists in 2D only)")
    # what each split must provide: {split: {dim: view role (2D) or None (3D)}}
    plan: dict[str, dict[str, str | None]] = {}
    for dim, metric in wanted:
        split = METRIC_SPLITS[metric]
        role = None if metric in ("CSA", "OVA", "CDA") else "novel"
        plan.setdefault(split, {})[dim] = role
    if any(d == "2d" for d, _ in wanted) and functions is None:
        functions = default_blend_functions()

    confusion: dict[tuple[str, str], ConfusionMatrix] = {}
    per_scene: dict[tuple[str, str], list[np.ndarray]] = {}
    counts: dict[tuple[str, str], list[int]] = {}
    common: set[int] = set()
    for split, dim_roles in plan.items():
        for dim in dim_roles:
            confusion[(split, dim)] = ConfusionMatrix(k)
            per_scene[(split, dim)] = []
            counts[(split, dim)] = [0, 0]
        for scene in scenes_by_split.get(split, ()):
            if progress is not None:
                progress(split, scene.scene_id)
            if split == "xval":
                common |= _present_labels(scene)
            vectors = np.asarray(predictor.encode(scene))
            n = len(scene.gaussians)
            if vectors.ndim != 2 or vectors.shape[0] != n:
                raise ValueError(f"scene {scene.scene_id}: predictor returned vectors of shape {vectors.shape}, "
                                 f"expected ({n}, F)")
            if not np.isfinite(vectors).all():
                raise ValueError(f"scene {scene.scene_id}: predictor returned non-finite vectors")
            if "3d" in dim_roles:
                semantic = scene.gaussians.extras.get("semantic")
                if semantic is None:
                    raise ValueError(f"scene {scene.scene_id} ({split}): Gaussians have no 'semantic' labels")
                gt = to_vocabulary_labels(semantic, vocabulary, f"scene {scene.scene_id} Gaussians.semantic")
                pred = classify_vectors(predictor, vectors, vocabulary, chunk_rows)
                scene_cm = ConfusionMatrix(k)
                scene_cm.update(pred, gt)
                confusion[(split, "3d")].counts += scene_cm.counts
                per_scene[(split, "3d")].append(scene_cm.counts)
                counts[(split, "3d")][0] += 1
            if "2d" in dim_roles:
                views = _views_with_role(scene, dim_roles["2d"], max_views_per_scene)
                scene_cm = ConfusionMatrix(k)
                for view in views:
                    if view.semantic is None:
                        raise ValueError(f"scene {scene.scene_id} view {view.name}: no stored semantic label map")
                    gt = to_vocabulary_labels(view.semantic, vocabulary, f"scene {scene.scene_id} view {view.name}")
                    blender = functions.blend(scene.gaussians, view.camera, blend_top_k)
                    pred = predict_view_labels(predictor, vectors, blender, vocabulary, functions,
                                               min_alpha, chunk_rows, band_rows)
                    if pred.shape != gt.shape:
                        raise ValueError(f"scene {scene.scene_id} view {view.name}: rendered {pred.shape} but "
                                         f"the stored label map is {gt.shape}")
                    scene_cm.update(pred, gt)
                    counts[(split, "2d")][1] += 1
                confusion[(split, "2d")].counts += scene_cm.counts
                if views:
                    per_scene[(split, "2d")].append(scene_cm.counts)
                counts[(split, "2d")][0] += 1 if views else 0

    common_idx = None
    if "xval" in plan:
        common_idx = np.array(sorted(int(vocabulary.lut[c]) for c in common
                                     if 0 <= c < vocabulary.lut.size and vocabulary.lut[c] != IGNORE_LABEL),
                              dtype=np.int64)
    results = {}
    for dim, metric in wanted:
        split = METRIC_SPLITS[metric]
        if metric == "OVA":
            classes = vocabulary.unseen
        elif metric == "CDA":
            classes = common_idx
        else:
            classes = np.arange(k)
        cm = confusion[(split, dim)]
        scenes, views = counts[(split, dim)]
        results[(dim, metric)] = MetricResult(metric, dim, split, classes, cm.scores(classes), scenes, views)
    stacked = {key: np.stack(mats) if mats else np.zeros((0, k, k + 1), np.int64) for key, mats in per_scene.items()}
    return BenchResult(vocabulary, results, common_idx, {key: cm.counts for key, cm in confusion.items()}, stacked)


# ---------------------------------------------------------------------------------------------
# reporting
# ---------------------------------------------------------------------------------------------
def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100.0 * value:.2f}"


def table1_header() -> str:
    """Markdown header of a Table-1 row: method | 3D CSA OVA CDA | 2D CSA OVA NVA CDA."""
    cols = " | ".join(f"{d.upper()} {m}" for d, m in TABLE1_COLUMNS)
    return f"| method | {cols} |\n|---|" + "---:|" * len(TABLE1_COLUMNS)


def table1_row(label: str, result: BenchResult) -> str:
    """Markdown row of mIoU (%) in Table-1 column order; ``-`` where not computed or nothing scored."""
    cells = []
    for dim, metric in TABLE1_COLUMNS:
        r = result.results.get((dim, metric))
        cells.append(_pct(None if r is None else r.scores.miou))
    return f"| {label} | " + " | ".join(cells) + " |"


def _finite_or_none(value) -> float | None:
    return float(value) if np.isfinite(value) else None


def metric_interval(result: BenchResult, dim: str, metric: str, *, draws: int = DEFAULT_DRAWS,
                    seed: int = 0) -> Interval | None:
    """95 % percentile-bootstrap interval over scenes of one metric's mIoU (None without per-scene matrices)."""
    r = result.results.get((dim, metric))
    if r is None or result.scene_confusion is None or (r.split, dim) not in result.scene_confusion:
        return None
    return bootstrap_miou(result.scene_confusion[(r.split, dim)], r.classes, draws=draws, seed=seed)


def result_to_dict(result: BenchResult) -> dict:
    """JSON-ready dict (no NaN: None where a class is not scored): per metric mIoU with its 95 % bootstrap
    interval over scenes, mAcc, per-class IoU by name, counts, the Table-1 row, the confusion matrices and
    the per-scene matrices."""
    voc = result.vocabulary
    metrics = {}
    for (dim, metric), r in result.results.items():
        interval = metric_interval(result, dim, metric)
        metrics.setdefault(dim, {})[metric] = {
            "split": r.split,
            "miou": r.scores.miou,
            "ci95": None if interval is None or interval.low is None else [interval.low, interval.high],
            "macc": r.scores.macc,
            "classes": [voc.names[i] for i in r.classes],
            "scored_classes": [voc.names[i] for i in r.scores.scored_classes],
            "per_class_iou": {voc.names[i]: _finite_or_none(r.scores.iou[i]) for i in r.classes},
            "per_class_acc": {voc.names[i]: _finite_or_none(r.scores.acc[i]) for i in r.classes},
            "num_samples": r.scores.num_samples,
            "num_unpredicted": r.scores.num_unpredicted,
            "num_scenes": r.num_scenes,
            "num_views": r.num_views,
        }
    return {
        "vocabulary": {
            "num_classes": int(voc.class_ids.size),
            "class_ids": voc.class_ids.tolist(),
            "names": list(voc.names),
            "unseen": [voc.names[i] for i in voc.unseen],
            "common": None if result.common_classes is None else [voc.names[i] for i in result.common_classes],
        },
        "metrics": metrics,
        "row": {f"{d}_{m}": (None if (d, m) not in result.results else result.results[(d, m)].scores.miou)
                for d, m in TABLE1_COLUMNS},
        "confusion": {f"{split}_{dim}": counts.tolist() for (split, dim), counts in result.confusion.items()},
        "scene_confusion": {f"{split}_{dim}": counts.tolist()
                            for (split, dim), counts in (result.scene_confusion or {}).items()},
    }


def dataset_fingerprint(dataset: Path) -> dict:
    """What identifies the scored data: sha256 of ``manifest.json`` (which itself lists the sha256 of
    every shard) and of ``splits.json`` when present."""
    dataset = Path(dataset)
    out = {}
    for name in ("manifest.json", "splits.json"):
        path = dataset / name
        out[f"{name.split('.')[0]}_sha256"] = sha256_file(path) if path.is_file() else None
    return out


# ---------------------------------------------------------------------------------------------
# one call for the CLI
# ---------------------------------------------------------------------------------------------
class BenchReport(NamedTuple):
    """What ``ovgaussian bench`` prints and writes.

    Fields:
        result: the metrics.
        payload: the JSON document (config, predictor/checkpoint, dataset fingerprint, metrics).
        row: the Table-1 markdown row (with header).
    """

    result: BenchResult
    payload: dict
    row: str


def calibrate_stacking(config: BenchConfig, templates=()) -> Calibration:
    """Gamma of calibrated stacking from ``config.stacking_run`` on the train split (``ovgaussian.openvocab.calibration``)."""
    run_config = read_json(Path(config.stacking_run) / CONFIG_NAME)
    data = run_config.get("train", {}).get("data", {})
    holdout = tuple(data.get("holdout_classes") or ())
    if not holdout:
        raise ValueError(f"{config.stacking_run}: not a calibration run (trained without --holdout-classes)")
    calibrator = load_model_predictor(config.stacking_run, device=config.device, prompt_templates=templates,
                                      faint_neighbours=config.faint_neighbours)  # scored as the main run is
    return calibrate(calibrator, _train_scenes(config), training_vocabulary(config.num_classes), holdout)


def _train_scenes(config: BenchConfig):
    """The train split's scenes (Gaussians only) that the open-vocabulary methods fit on."""
    scenes = shards.iter_scenes(config.dataset, "train", views=False, verify=config.verify)
    if config.max_scenes is not None:
        scenes = (s for i, s in enumerate(scenes) if i < config.max_scenes)
    return scenes


def _checkpoint_record(run: Path, predictor) -> dict:
    """The report's record of a model predictor: its run, checkpoint folder and the weights' sha256 (None if absent)."""
    return {"run": str(run), "checkpoint": str(predictor.checkpoint),
            "checkpoint_sha256": weights_sha256(predictor.checkpoint)}


def make_predictor(config: BenchConfig) -> tuple[Predictor, dict]:
    """The predictor named by ``config`` and a JSON description of it (checkpoint path + sha256)."""
    if config.predictor == "model":
        if config.run is None:
            raise ValueError("bench: --run is needed to score the model (or pick a baseline --predictor)")
        templates = PROMPT_TEMPLATES if config.prompt_ensemble else ()
        predictor = load_model_predictor(config.run, config.checkpoint, device=config.device,
                                         prompt_templates=templates, faint_neighbours=config.faint_neighbours)
        description = {"kind": "model", **_checkpoint_record(config.run, predictor), "prompt_templates": list(templates),
                       "faint_neighbours": config.faint_neighbours}
        if config.ensemble_runs:
            if config.generative or config.stacking_run is not None:
                raise ValueError("bench: --ensemble-run is not supported with --generative or --stacking-run")
            predictor = load_ensemble(predictor, config.ensemble_runs, config.device, templates)
            description["ensemble"] = [_checkpoint_record(run, member)
                                       for run, member in zip(config.ensemble_runs, predictor.members[1:])]
        if config.generative:
            train_scenes = _train_scenes(config)
            predictor, record = fit_generative_predictor(predictor, train_scenes, benchmark_vocabulary(config.num_classes),
                                                         training_vocabulary(config.num_classes), config.synthesis)
            description["generative"] = record
        if config.class_offsets:
            if config.stacking_run is not None:
                raise ValueError("bench: --class-offsets and --stacking-run together are not supported (gamma is "
                                 "chosen on scores without offsets)")
            offsets = fit_offsets(predictor, _train_scenes(config), training_vocabulary(config.num_classes))
            predictor = OffsetPredictor(predictor, offsets)
            description["class_offsets"] = {"split": "train", "protocol": "training classes only (unseen labels "
                                            "unread); coordinate ascent of the train split's pooled mIoU",
                                            **offsets.as_dict()}
        if config.stacking_run is not None:
            calibration = calibrate_stacking(config, templates)
            predictor = StackedPredictor(predictor, calibration.gamma)
            description["stacking"] = {"run": str(config.stacking_run),
                                       "checkpoint_sha256": weights_sha256(latest_checkpoint(config.stacking_run)),
                                       "split": "train",
                                       "protocol": "seen classes held out as pseudo-unseen in the stacking run; "
                                                   "gamma maximizes the harmonic mean of their mIoU and the other "
                                                   "seen classes' mIoU on the train split; unseen labels unread",
                                       **calibration.as_dict()}
        return predictor, description

    if config.ensemble_runs:
        raise ValueError(f"bench: --ensemble-run scores trained runs; it does not apply to --predictor "
                         f"{config.predictor}")
    train = shards.iter_scenes(config.dataset, "train", views=False, verify=config.verify)
    if config.predictor == "majority":
        predictor = baseline.fit_majority(train)
    elif config.predictor == "nearest-colour":
        predictor = baseline.fit_nearest_colour(train)
    else:
        raise ValueError(f"unknown predictor {config.predictor!r}")
    return predictor, {"kind": config.predictor, "fitted_on": "train"}


def run_bench(config: BenchConfig, predictor: Predictor | None = None, *,
              functions: BlendFunctions | None = None) -> BenchReport:
    """Evaluate the configured predictor on the dataset's splits; nothing is written (the CLI writes the report)."""
    resolve_device(config.device)  # before any scene is read
    vocabulary = benchmark_vocabulary(config.num_classes)
    description = {"kind": getattr(predictor, "name", "custom")}
    if predictor is None:
        predictor, description = make_predictor(config)
    splits = {METRIC_SPLITS[m] for m in config.metrics}
    available = {}
    for split in sorted(splits):
        ids = list(shards.list_scenes(config.dataset, split))
        if config.max_scenes is not None:
            ids = sorted(ids)[: config.max_scenes]
        available[split] = ids

    bar = None
    if config.progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(len(v) for v in available.values()), desc="bench", unit="scene", leave=False)

    def progress(split, scene_id):
        if bar is not None:
            bar.set_postfix_str(f"{split}:{scene_id}")
            bar.update(1)

    splits_2d = {METRIC_SPLITS[m] for m in config.metrics if "2d" in config.dims and "2d" in METRIC_DIMS[m]}

    def read_split(split: str, ids: list[str]):
        for scene_id in ids:  # one scene in memory at a time; views (images) only when 2D is scored
            yield shards.read_scene(config.dataset, split, scene_id, views=split in splits_2d,
                                    verify=config.verify)

    scenes_by_split = {split: read_split(split, ids) for split, ids in available.items()}
    try:
        fingerprint = dataset_fingerprint(config.dataset)
        result = evaluate(predictor, scenes_by_split, vocabulary, metrics=config.metrics, dims=config.dims,
                          min_alpha=config.min_alpha, blend_top_k=config.blend_top_k,
                          max_views_per_scene=config.max_views_per_scene, chunk_rows=config.chunk_rows,
                          functions=functions, progress=progress, band_rows=config.band_rows)
    finally:
        if bar is not None:
            bar.close()
    payload = {
        "config": config_to_dict(config),
        "predictor": description,
        "dataset": {"path": str(config.dataset), **fingerprint,
                    "scenes": {split: ids for split, ids in available.items()}},
        **result_to_dict(result),
    }
    label = description.get("run") or description["kind"]
    row = table1_header() + "\n" + table1_row(str(label), result)
    return BenchReport(result, payload, row)
