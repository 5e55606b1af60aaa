"""Per-class score offsets chosen on the train split for mIoU, added to the scores before the argmax.

A model's cosine scores are not calibrated across classes: on fitted splats the text cross-entropy, weighted by
class, leaves walls scored below windows where the two look alike, and since the IoU counts Gaussians, a few
percent of a wall's many Gaussians taken by the window costs the window most of its IoU (benchmarks/results/bench_suite.md).
A per-class offset ``b_c`` added to column ``c`` moves each class's decision boundary; the offsets are chosen to
maximize the pooled mIoU of the **train** split (logit adjustment, as Menon et al., ICLR 2021, with the offsets
fitted to the metric rather than set from class priors).

The protocol, as calibrated stacking's (``calibration.py``): the training vocabulary (the benchmark's minus the
unseen classes) scores the train split's Gaussians, so every unseen-class label is IGNORE through its lookup and
never read; only the training classes get an offset, every other class keeps 0. The fit is coordinate ascent on
a grid: each sweep visits the classes in order and moves one offset at a time to the grid value of best mIoU (ties
keep the current value), then halves the grid step. Each move is exact: the argmax with the offsets, ties to the
lowest index as ``np.argmax``. The training mIoU never falls; the chosen offsets, the grid and the mIoU before and
after are returned in ``ClassOffsets`` and written into the bench report.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Iterable, NamedTuple, Sequence

import numpy as np

from ovgaussian.metrics import scores_from_confusion
from ovgaussian.openvocab.calibration import calibration_samples
from ovgaussian.text.vocabulary import Vocabulary
from seggaussian.core.constants import UNSEEN_CLASSES, read_class_names

#: First sweep's grid: offsets within +-OFFSET_SPAN of the current one in steps of OFFSET_SPAN / OFFSET_STEPS.
#: Scores are cosines: a typical class margin is a few hundredths.
OFFSET_SPAN = 0.2
OFFSET_STEPS = 20
#: Sweeps over the classes; each halves the grid's span and step.
OFFSET_SWEEPS = 3


class ClassOffsets(NamedTuple):
    """Offsets per class name and how they were chosen (JSON-ready through ``as_dict``).

    Fields:
        names: the training classes, in vocabulary order; offsets: ``[C]`` their offsets (float32 values).
        train_miou_before, train_miou_after: pooled mIoU of the scored train Gaussians without and with them.
        span, steps, sweeps: the grid (first sweep: ``2 * steps + 1`` values within +-span).
        num_scenes, num_gaussians: what was scored.
    """

    names: tuple[str, ...]
    offsets: tuple[float, ...]
    train_miou_before: float
    train_miou_after: float
    span: float
    steps: int
    sweeps: int
    num_scenes: int
    num_gaussians: int

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self._asdict().items()}

    def by_name(self) -> dict[str, float]:
        return dict(zip(self.names, self.offsets))


def pooled_miou(counts: np.ndarray) -> float:
    """The bench's mIoU of ``[K, K+1]`` confusion counts (``scores_from_confusion``), 0 when no class is scored."""
    return scores_from_confusion(counts).miou or 0.0


def _counts(labels: np.ndarray, predicted: np.ndarray, num: int) -> np.ndarray:
    """``metrics.confusion_matrix`` without its per-call label checks: the search calls it thousands of times on
    labels checked once and predictions that are column indices by construction."""
    counts = np.bincount(labels * num + predicted, minlength=num * num).reshape(num, num)
    return np.concatenate([counts, np.zeros((num, 1), np.int64)], axis=1)  # no "none" predictions here


def fit_class_offsets(
    scores: np.ndarray,  # [M, C] float32
    labels: np.ndarray,  # [M] int, class index in 0..C-1 (no IGNORE row)
    fitted: np.ndarray,  # [C] bool: the columns that get an offset (others stay 0)
    span: float = OFFSET_SPAN,
    steps: int = OFFSET_STEPS,
    sweeps: int = OFFSET_SWEEPS,
) -> tuple[np.ndarray, float, float]:  # offsets [C] float32, mIoU before, mIoU after
    """Coordinate ascent of the pooled mIoU of ``argmax(scores + offsets)`` (module docstring)."""
    scores = np.ascontiguousarray(scores, dtype=np.float32)
    labels = np.asarray(labels, dtype=np.int64)
    rows, num = scores.shape
    if labels.shape != (rows,) or (rows and (labels.min() < 0 or labels.max() >= num)):
        raise ValueError(f"class offsets: labels must be {rows} indices in 0..{num - 1}")
    if not np.isfinite(scores).all():
        raise ValueError("class offsets: the scores hold NaN/Inf")
    offsets = np.zeros(num, np.float32)
    best = pooled_miou(_counts(labels, np.argmax(scores, axis=1), num))
    before = best
    for sweep in range(sweeps):
        step = span / steps / 2**sweep
        for c in np.flatnonzero(np.asarray(fitted, bool)):
            others = scores + offsets[None, :]
            others[:, c] = -np.inf
            rival = np.argmax(others, axis=1)  # the argmax without c (lowest index on ties)
            rival_score = others[np.arange(rows), rival]
            own = scores[:, c]
            current = offsets[c]
            for k in range(-steps, steps + 1):
                candidate = np.float32(current + np.float32(k * step))
                value = own + candidate
                wins = (value > rival_score) | ((value == rival_score) & (c < rival))
                miou = pooled_miou(_counts(labels, np.where(wins, c, rival), num))
                if miou > best:
                    best, offsets[c] = miou, candidate
    return offsets, before, best


def fit_offsets(predictor, scenes: Iterable, vocabulary: Vocabulary) -> ClassOffsets:
    """Offsets of ``predictor`` on ``scenes`` (the train split) against ``vocabulary`` (the training classes: no
    unseen class may be in it, so no unseen label is read)."""
    bad = [n for n in vocabulary.names if n in UNSEEN_CLASSES]
    if bad:
        raise ValueError(f"class offsets: the vocabulary holds unseen classes {bad}: their labels must not be read")
    scores, labels, num_scenes = calibration_samples(predictor, scenes, vocabulary)
    offsets, before, after = fit_class_offsets(scores, labels, np.ones(scores.shape[1], bool))
    return ClassOffsets(tuple(vocabulary.names), tuple(float(v) for v in offsets), before, after, OFFSET_SPAN,
                        OFFSET_STEPS, OFFSET_SWEEPS, num_scenes, int(labels.size))


class OffsetPredictor:
    """A predictor whose scores get the per-class ``offsets`` (by class name; other classes: 0)."""

    def __init__(self, inner, offsets: ClassOffsets | dict[str, float]) -> None:
        self.inner = inner
        self.offsets = offsets.by_name() if isinstance(offsets, ClassOffsets) else dict(offsets)
        self.name = f"{getattr(inner, 'name', 'model')}+offsets"
        self._names = read_class_names()

    def encode(self, scene) -> np.ndarray:
        return self.inner.encode(scene)

    def classify(self, vectors: np.ndarray, class_ids: np.ndarray) -> np.ndarray:
        scores = np.asarray(self.inner.classify(vectors, class_ids), dtype=np.float32)
        shift = np.array([self.offsets.get(self._names[int(i)], 0.0) for i in class_ids], np.float32)
        return scores + shift[None, :]


def _read_report(path: Path) -> dict:
    try:
        report = json.loads(path.read_text())
    except OSError as err:
        raise ValueError(f"{path}: cannot read the bench report ({err.strerror or err})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not a JSON bench report ({err})") from None
    return report if isinstance(report, dict) else {}


def _predictor_record(path: Path) -> dict:
    predictor = _read_report(path).get("predictor")
    return predictor if isinstance(predictor, dict) else {}


def read_class_offsets(path) -> dict[str, float]:
    """``{class name: offset}`` recorded in a bench report (``predictor.class_offsets`` of the JSON that
    ``ovgaussian bench --class-offsets`` writes); a one-line ValueError naming the file and field otherwise."""
    path = Path(path)
    record = _predictor_record(path).get("class_offsets")
    if not isinstance(record, dict):
        raise ValueError(f"{path}: no predictor.class_offsets (a report of `ovgaussian bench --class-offsets`)")
    names, offsets = record.get("names"), record.get("offsets")
    if not (isinstance(names, list) and isinstance(offsets, list) and len(names) == len(offsets)
            and all(isinstance(n, str) for n in names)):
        raise ValueError(f"{path}: predictor.class_offsets needs lists 'names' and 'offsets' of one length")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in offsets):
        raise ValueError(f"{path}: predictor.class_offsets.offsets must be finite numbers")
    return {name: float(value) for name, value in zip(names, offsets)}


def offsets_checkpoints(path) -> tuple[str, ...]:
    """sha256 of the weights whose scores a bench report's class offsets were fitted on: ``predictor.
    checkpoint_sha256``, then each ``predictor.ensemble`` member's; empty when the report does not record them."""
    predictor = _predictor_record(Path(path))
    members = predictor.get("ensemble")
    records = [predictor, *(members if isinstance(members, list) else [])]
    digests = tuple(r.get("checkpoint_sha256") for r in records if isinstance(r, dict))
    return digests if digests and all(isinstance(d, str) for d in digests) else ()


def offsets_faint_neighbours(path) -> int:
    """The ``--faint-neighbours`` of the bench whose scores a report's class offsets were fitted on:
    ``predictor.faint_neighbours``; 0 (no blend) for a report written before the option existed. 0 and 1 both
    mean off and read as 0."""
    value = _predictor_record(Path(path)).get("faint_neighbours", 0)
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise ValueError(f"{path}: predictor.faint_neighbours must be a non-negative integer")
    return value if value > 1 else 0


def reference_fit_class_offsets(scores: Sequence[Sequence[float]], labels: Sequence[int], grid: Sequence[float]
                                ) -> tuple[tuple[float, ...], float]:
    """Exhaustive search (tests): the offsets on ``grid`` for every column (the first column fixed at 0) with the
    best pooled mIoU, computed row by row in Python; returns (offsets, mIoU). Exponential in the columns."""
    import itertools

    num = len(scores[0])
    best = None
    for combo in itertools.product(grid, repeat=num - 1):
        offsets = (0.0, *combo)
        counts = np.zeros((num, num + 1), np.int64)
        for row, label in zip(scores, labels):
            shifted = [float(np.float32(s) + np.float32(o)) for s, o in zip(row, offsets)]
            counts[label, shifted.index(max(shifted))] += 1
        miou = pooled_miou(counts)
        if best is None or miou > best[1]:
            best = (offsets, miou)
    return best
