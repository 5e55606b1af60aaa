"""A run's relevancy calibration: one logit offset per name of its vocabulary, fitted on the train split's rooms.

The calibrated relevancy (``relevancy.calibrated_relevancy``) is the query's softmax probability ``p`` against
the vocabulary and the canonical negatives at the run's training temperature. One threshold on ``p`` does not suit
every class: a wall borders doors and windows everywhere, so many of its Gaussians sit below 0.5 and its best
threshold is lower; doors, tables and monitors, which other things resemble, are best taken higher. The
calibration moves each class's operating point, with the labels of the rooms the run was trained on and nothing
else (the val and cross-domain rooms stay unseen):

- every name of the vocabulary with at least ``MIN_CLASS_GAUSSIANS`` Gaussians in at least one train room gets
  the logit offset ``d`` of the grid (``offset_grid``) whose threshold ``sigmoid(d)`` on ``p`` gives the highest
  mean IoU over those rooms (per room, the Gaussians with ``p >= sigmoid(d)`` against the class's; ties: the
  offset nearest 0), as ``openvocab.class_offsets`` fits per-class score offsets to the train split's mIoU;
- the others (too rare in the train rooms, and every name outside the vocabulary) keep ``d = 0``.

The viewer lowers the query's logit by ``d`` (``calibrated_relevancy(..., offsets)``), so its one default 0.5
falls at each class's fitted threshold. The grid stops at ``OFFSET_MIN = -ln 2`` below (threshold 1/3: the query
at least half as likely as all its competitors together): a lower bar takes neighbours of a class it has learnt to
look for in rooms that do not hold it. This bound is the one constant not fitted on the train rooms: it was set after
seeing names absent from the val and cross-domain rooms light up, and then tested on rooms made afterwards
(``benchmarks/results/relevancy.md``, "Fresh rooms"). Above, the grid reaches ``ln 49`` (threshold 0.98).

The fit is done once per run and vocabulary, on demand, and cached in the run folder (``CALIBRATION_NAME``,
keyed by the weights' sha256, the competitors, the temperature, the train rooms and ``CALIBRATION_FORMAT``).
Where the recorded train rooms cannot be read, the viewer's ``--dataset`` is tried; where neither can, a cached fit of
the same model and vocabulary is still used, and otherwise every offset is 0: the uncalibrated default
(``CalibrationResult.note`` says why).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Sequence

import numpy as np

from ovgaussian.run.checkpoint import CONFIG_NAME, read_json, weights_sha256
from ovgaussian.view.field import QueryField
from ovgaussian.view.relevancy import calibrated_relevancy, competitor_mask, competitors_of
from seggaussian import shards
from seggaussian.core.constants import read_class_names
from seggaussian.util.atomic import write_json_atomic

#: File of the cached calibration in the run folder.
CALIBRATION_NAME = "relevancy_calibration.json"
#: Version of the fit: a cache of another version is refitted.
CALIBRATION_FORMAT = 1
#: Lowest offset: threshold 1/3 on the probability (module docstring).
OFFSET_MIN = -math.log(2.0)
#: Highest offset: threshold 0.98.
OFFSET_MAX = math.log(49.0)
#: Grid step of the offsets (logit units).
OFFSET_STEP = 0.05
#: Gaussians of a class a train room must hold to take part in its fit (the benchmark's smallest queried class).
MIN_CLASS_GAUSSIANS = 20


def offset_grid() -> np.ndarray:
    """The candidate offsets: multiples of ``OFFSET_STEP`` within [``OFFSET_MIN``, ``OFFSET_MAX``] and the bound
    ``OFFSET_MIN`` itself, ascending (0 is one of them)."""
    ks = np.arange(math.ceil(OFFSET_MIN / OFFSET_STEP), math.floor(OFFSET_MAX / OFFSET_STEP) + 1)
    return np.unique(np.concatenate([[OFFSET_MIN], np.round(ks * OFFSET_STEP, 12)]))


def iou_curve(probability: np.ndarray, truth: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """``[K]`` IoU of ``probability >= t`` with ``truth`` for every threshold ``t`` (sorted counts, no mask per
    threshold); 0 where both are empty."""
    p = np.asarray(probability, np.float64)
    truth = np.asarray(truth, bool)
    t = np.asarray(thresholds, np.float64)
    all_sorted = np.sort(p)
    true_sorted = np.sort(p[truth])
    hits = len(all_sorted) - np.searchsorted(all_sorted, t, side="left")  # #(p >= t)
    inter = len(true_sorted) - np.searchsorted(true_sorted, t, side="left")
    union = hits + len(true_sorted) - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


def iou_curve_reference(probability, truth, thresholds) -> np.ndarray:
    """The IoU curve one threshold and one Gaussian at a time (tests)."""
    out = []
    for t in thresholds:
        inter = union = 0
        for p, y in zip(probability, truth):
            hit = float(p) >= float(t)
            inter += hit and bool(y)
            union += hit or bool(y)
        out.append(inter / union if union else 0.0)
    return np.array(out)


def best_offset(curves: np.ndarray, grid: np.ndarray) -> float:
    """The offset of ``grid`` whose column of ``curves`` (``[rooms, K]`` IoU) has the highest mean; ties go to
    the offset nearest 0 (then the lower one)."""
    mean = np.asarray(curves, np.float64).mean(axis=0)
    order = np.lexsort((grid, np.abs(grid), -mean))  # primary: highest mean; then nearest 0; then lower
    return float(grid[order[0]])


class ClassFit(NamedTuple):
    """One name's fit: its offset, the train rooms it was fitted on and their mean IoU at 0 and at the offset."""

    offset: float
    rooms: int
    iou_at_zero: float | None
    iou_at_offset: float | None


def fit_offsets(rooms: Iterable[tuple[np.ndarray, np.ndarray]], num_names: int,
                min_gaussians: int = MIN_CLASS_GAUSSIANS) -> list[ClassFit]:
    """Offsets of ``num_names`` names from ``rooms``: per room ``(probability [N, V], truth [N])``, the calibrated
    relevancy of each name (offset 0) and each Gaussian's name index (-1: none of them)."""
    grid = offset_grid()
    thresholds = 1.0 / (1.0 + np.exp(-grid))
    zero = int(np.flatnonzero(grid == 0.0)[0])
    curves: list[list[np.ndarray]] = [[] for _ in range(num_names)]
    for probability, truth in rooms:
        truth = np.asarray(truth, np.int64)
        counts = np.bincount(truth[truth >= 0], minlength=num_names)
        for v in np.flatnonzero(counts[:num_names] >= min_gaussians):
            curves[v].append(iou_curve(probability[:, v], truth == v, thresholds))
    out = []
    for v in range(num_names):
        if not curves[v]:
            out.append(ClassFit(0.0, 0, None, None))
            continue
        table = np.stack(curves[v])
        offset = best_offset(table, grid)
        k = int(np.flatnonzero(grid == offset)[0])
        out.append(ClassFit(offset, len(curves[v]), float(table[:, zero].mean()), float(table[:, k].mean())))
    return out


class RelevancyCalibration(NamedTuple):
    """A run's fitted offsets and what they were fitted with (JSON-ready through ``as_dict``).

    Fields:
        names: the vocabulary; offsets, rooms, iou_at_zero, iou_at_offset: per name (``ClassFit``).
        competitors, temperature: the softmax the offsets apply to.
        weights_sha256: the checkpoint's weights; dataset, split, scenes: the train rooms read.
        format: ``CALIBRATION_FORMAT``.
    """

    names: tuple[str, ...]
    offsets: tuple[float, ...]
    rooms: tuple[int, ...]
    iou_at_zero: tuple[float | None, ...]
    iou_at_offset: tuple[float | None, ...]
    competitors: tuple[str, ...]
    temperature: float
    weights_sha256: str | None
    dataset: str
    split: str
    scenes: tuple[str, ...]
    format: int = CALIBRATION_FORMAT

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self._asdict().items()}

    def by_name(self) -> dict[str, float]:
        """``{name: offset}`` of the names with a non-zero offset."""
        return {n: o for n, o in zip(self.names, self.offsets) if o != 0.0}


def fit_calibration(fields: Iterable[tuple[object, np.ndarray]], vocabulary: Sequence[str],
                    negatives: Sequence[str], temperature: float, class_names: Sequence[str]) -> list[ClassFit]:
    """Per name of ``vocabulary``, its fit on ``fields``: per room ``(QueryField, semantic [N] class ids)``."""
    vocabulary = tuple(vocabulary)
    competitors = competitors_of(vocabulary, negatives)
    mask = competitor_mask(vocabulary, competitors)
    index = {name: i for i, name in enumerate(class_names)}
    lookup = np.full(len(class_names), -1, np.int64)  # class id -> vocabulary index
    for v, name in enumerate(vocabulary):
        if name in index:
            lookup[index[name]] = v

    def rooms():
        for field, semantic in fields:
            semantic = np.asarray(semantic, np.int64)
            known = (semantic >= 0) & (semantic < len(lookup))
            truth = np.where(known, lookup[np.where(known, semantic, 0)], -1)
            yield calibrated_relevancy(field.scores(vocabulary), field.scores(competitors), mask, temperature), truth

    return fit_offsets(rooms(), len(vocabulary))


class CalibrationResult(NamedTuple):
    """The offsets the viewer uses (``{name: offset}``; empty: uncalibrated), the calibration (None without one)
    and one line saying where they came from."""

    offsets: dict
    calibration: RelevancyCalibration | None
    note: str


def _read_cached(path: Path) -> dict | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _cached_calibration(doc: dict, key: dict) -> RelevancyCalibration | None:
    """The cached calibration when its key fields equal ``key`` and its lists are well formed; else None."""
    if any(doc.get(k) != v for k, v in key.items()):
        return None
    names, offsets = doc.get("names"), doc.get("offsets")
    if not (isinstance(names, list) and isinstance(offsets, list) and len(names) == len(offsets)
            and all(isinstance(o, (int, float)) and not isinstance(o, bool) and math.isfinite(o) for o in offsets)):
        return None
    try:
        return RelevancyCalibration(**{f: tuple(doc[f]) if isinstance(doc[f], list) else doc[f]
                                       for f in RelevancyCalibration._fields})
    except (KeyError, TypeError):
        return None


def run_calibration(run: Path, predictor, vocabulary: Sequence[str], negatives: Sequence[str], temperature: float,
                    progress: Callable[[str], None] | None = None, dataset: Path | None = None) -> CalibrationResult:
    """The relevancy calibration of ``run`` for ``vocabulary`` + ``negatives``: the cached one in
    ``RUN/relevancy_calibration.json`` when its key matches, else fitted on the train rooms the run's config
    records (``train.data.dataset``, ``train.data.split``) and cached.

    ``dataset``: where else the train rooms may be (the viewer's ``--dataset``), tried when the recorded path cannot
    be read (a dataset moved, or recorded relative to another folder). When neither can be read, a cached calibration
    of the same weights, vocabulary, competitors and temperature is still used (its rooms are not checked); else
    every offset is 0 (uncalibrated), said in the note."""
    say = progress or (lambda _message: None)
    run = Path(run)
    data = read_json(run / CONFIG_NAME).get("train", {}).get("data", {})
    recorded, split = data.get("dataset"), data.get("split") or "train"
    if not recorded:
        return CalibrationResult({}, None, f"{run}: no train dataset recorded; relevancy offsets 0 (uncalibrated)")
    places = [Path(recorded)] + ([Path(dataset)] if dataset is not None else [])
    scenes, problems = (), []
    for place in places:
        try:
            scenes = tuple(shards.list_scenes(place, split))
        except (OSError, ValueError) as error:  # a moved, deleted or unreadable dataset: try the next place
            problems.append(f"{place}: {str(error).splitlines()[0]}")
            continue
        if scenes:
            dataset = place
            break
        problems.append(f"{place}: no {split} rooms")
    key = {"format": CALIBRATION_FORMAT, "competitors": list(competitors_of(vocabulary, negatives)),
           "names": list(vocabulary), "temperature": float(temperature),
           "weights_sha256": weights_sha256(getattr(predictor, "checkpoint", None))}
    path = run / CALIBRATION_NAME
    if scenes:
        key.update({"dataset": str(dataset), "split": split, "scenes": list(scenes)})
    # the cached fit of this model and vocabulary (and, where the rooms can be read, of these rooms)
    cached = _read_cached(path)
    calibration = _cached_calibration(cached, key) if cached is not None else None
    if calibration is not None:
        where = (f"{len(scenes)} {split} rooms" if scenes
                 else f"its {split} rooms not readable here: {'; '.join(problems)}")
        return CalibrationResult(calibration.by_name(), calibration,
                                 f"relevancy offsets of {len(calibration.by_name())} names from {path.name} ({where})")
    if not scenes:
        return CalibrationResult({}, None, f"train rooms not readable ({'; '.join(problems)}); relevancy offsets 0 "
                                           f"(uncalibrated)")
    names = read_class_names()

    def fields():
        for i, scene_id in enumerate(scenes):
            record = shards.read_scene(Path(dataset), split, scene_id, views=False)
            say(f"relevancy calibration: {split} room {i + 1}/{len(scenes)} ({scene_id})")
            field = QueryField.from_predictor(predictor, predictor.encode_gaussians(record.gaussians))
            yield field, np.asarray(record.gaussians.extras["semantic"]).astype(np.int64)

    try:
        fits = fit_calibration(fields(), vocabulary, negatives, temperature, names)
    except (OSError, ValueError) as error:  # an unreadable shard (ShardError): uncalibrated, said in one line
        return CalibrationResult({}, None, f"{dataset}: train rooms not readable ({str(error).splitlines()[0]}); "
                                           f"relevancy offsets 0 (uncalibrated)")
    calibration = RelevancyCalibration(
        tuple(vocabulary), tuple(f.offset for f in fits), tuple(f.rooms for f in fits),
        tuple(f.iou_at_zero for f in fits), tuple(f.iou_at_offset for f in fits), tuple(key["competitors"]),
        float(temperature), key["weights_sha256"], str(dataset), split, scenes)
    note = f"relevancy offsets of {len(calibration.by_name())} names fitted on {len(scenes)} {split} rooms"
    try:
        write_json_atomic(path, calibration.as_dict())
        note += f", cached in {path.name}"
    except OSError as error:
        note += f" (not cached: {error.strerror or error})"
    return CalibrationResult(calibration.by_name(), calibration, note)
