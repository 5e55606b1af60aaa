"""The viewer's logic without the browser: per mode, the colour of every Gaussian and a legend; the answer to a
query; what a clicked Gaussian is. ``ovgaussian.view.app`` only wires this to viser's scene and GUI."""

from __future__ import annotations

import threading
import time
from typing import NamedTuple, Sequence

import numpy as np

from ovgaussian.view.config import MODES
from ovgaussian.view.field import QueryField
from ovgaussian.view.relevancy import (CANONICAL_NEGATIVES, DEFAULT_TEMPERATURE, DEFAULT_THRESHOLD, QueryHits,
                                       calibrated_relevancy, competitor_mask, competitors_of, dimmed_colours,
                                       query_colours, query_hits, query_offsets, top_k)
from ovgaussian.view.scene import ViewScene, pick_gaussian, splat_arrays
from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.labels.palette import label_colours, palette

#: Scores listed for a clicked Gaussian.
INSPECT_TOP_K = 3
#: Dropdown titles of the modes.
MODE_TITLES = {"rgb": "RGB", "semantic": "Ground truth: semantic", "instance": "Ground truth: instance",
               "predicted": "Predicted labels", "query": "Query"}


class LegendRow(NamedTuple):
    """One line of a legend: a label's name, its colour (uint8 RGB) and how many Gaussians carry it."""

    name: str
    rgb: tuple[int, int, int]
    count: int


class Colouring(NamedTuple):
    """The colours of one mode.

    Fields:
        mode: the mode.
        rgb: ``[N, 3]`` uint8 colour per Gaussian.
        legend: rows, most frequent first.
        status: one line saying what is shown.
        hits: the query answer (query mode), else None.
        seconds: time spent scoring and colouring.
    """

    mode: str
    rgb: np.ndarray
    legend: list
    status: str
    hits: QueryHits | None = None
    seconds: float = 0.0


class ViewerState:
    """A scene, its optional language field and ground truth, and everything the modes derive from them.

    Args:
        scene: the Gaussians (and ground-truth labels) shown.
        field: the run's language field of these Gaussians (None: only RGB and ground-truth modes).
        vocabulary: class names of the predicted-labels mode.
        negatives: the canonical negatives of the relevancy.
        temperature: softmax temperature of the calibrated relevancy (the run's training temperature).
        offsets: ``{name: logit offset}`` of the calibrated relevancy (``calibration.run_calibration``, fitted for
            this vocabulary and these negatives); None or a missing name: 0.
        calibration_note: one line saying where ``offsets`` came from (shown in the summary).
    """

    def __init__(self, scene: ViewScene, field: QueryField | None = None, vocabulary: Sequence[str] = (),
                 negatives: Sequence[str] = CANONICAL_NEGATIVES, temperature: float = DEFAULT_TEMPERATURE,
                 offsets: dict[str, float] | None = None, calibration_note: str = "") -> None:
        if field is not None and len(field) != len(scene.gaussians):
            raise ValueError(f"{scene.source}: {len(scene.gaussians)} Gaussians but {len(field)} language vectors")
        if field is not None and not vocabulary:
            raise ValueError(f"{scene.source}: the predicted-labels mode needs a vocabulary (--vocab)")
        if field is not None and not negatives:
            raise ValueError(f"{scene.source}: the relevancy needs at least one canonical negative")
        self.scene = scene
        self.field = field
        self.vocabulary = tuple(vocabulary)
        self.negatives = tuple(negatives)
        self.temperature = float(temperature)
        if not self.temperature > 0:
            raise ValueError(f"{scene.source}: the relevancy temperature must be > 0, got {temperature}")
        self.offsets = dict(offsets or {})
        self.calibration_note = calibration_note
        self.competitors = competitors_of(self.vocabulary, self.negatives)
        self.arrays = splat_arrays(scene.gaussians)
        self.radii = scene.gaussians.scales().max(axis=1) if len(scene.gaussians) else np.zeros(0, np.float32)
        self.dimmed = dimmed_colours(self.arrays.rgb)
        self.class_names = read_class_names()
        self._lock = threading.Lock()
        self._relevancy: dict[tuple[str, ...], np.ndarray] = {}

    # --- modes -------------------------------------------------------------------------------------
    @property
    def modes(self) -> tuple[str, ...]:
        """The modes this scene supports, in dropdown order."""
        have = {"rgb": True, "semantic": self.scene.semantic is not None, "instance": self.scene.instance is not None,
                "predicted": self.field is not None, "query": self.field is not None}
        return tuple(m for m in MODES if have[m])

    def colouring(self, mode: str, queries: Sequence[str] = (), threshold: float = DEFAULT_THRESHOLD) -> Colouring:
        """The colours of ``mode`` (``queries`` and ``threshold`` for the query mode)."""
        if mode not in self.modes:
            raise ValueError(f"{self.scene.source}: mode {mode!r} is not available (available: {', '.join(self.modes)})")
        start = time.perf_counter()
        n = len(self.scene.gaussians)
        if mode == "rgb":
            return Colouring(mode, self.arrays.rgb, [], f"RGB: {n:,} Gaussians", None, time.perf_counter() - start)
        if mode == "semantic":
            rgb, legend = self._label_colouring(self.scene.semantic, self._class_name)
            return Colouring(mode, rgb, legend, f"ground-truth classes: {len(legend)} present",
                             None, time.perf_counter() - start)
        if mode == "instance":
            rgb, legend = self._label_colouring(self.scene.instance, lambda i: f"instance {i}")
            return Colouring(mode, rgb, legend, f"ground-truth instances: {len(legend)} present",
                             None, time.perf_counter() - start)
        if mode == "predicted":
            labels = self.field.argmax(self.vocabulary)
            colours = palette(len(self.vocabulary))
            counts = np.bincount(labels, minlength=len(self.vocabulary))
            legend = sorted((LegendRow(name, tuple(int(c) for c in colours[i]), int(counts[i]))
                             for i, name in enumerate(self.vocabulary) if counts[i]), key=lambda r: -r.count)
            return Colouring(mode, colours[labels], legend,
                             f"predicted: {len(self.vocabulary)} classes, {len(legend)} present",
                             None, time.perf_counter() - start)
        return self._query_colouring(tuple(queries), threshold, start)

    def _class_name(self, label: int) -> str:
        if label == IGNORE_LABEL or label < 0:
            return "unlabelled"
        return self.class_names[label] if label < len(self.class_names) else f"class {label}"

    def _label_colouring(self, labels: np.ndarray, name_of) -> tuple[np.ndarray, list]:
        ids, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
        table = label_colours(ids)  # [U, 3]
        legend = sorted((LegendRow(name_of(int(i)), tuple(int(c) for c in table[j]), int(counts[j]))
                         for j, i in enumerate(ids)), key=lambda r: -r.count)
        return table[inverse.reshape(-1)], legend

    # --- queries ---------------------------------------------------------------------------------------
    def relevancies(self, queries: Sequence[str]) -> np.ndarray:
        """``[N, Q]`` calibrated relevancy of every Gaussian to each query against the vocabulary and the negatives,
        with each query's offset (``relevancy.calibrated_relevancy``; cached per query list)."""
        queries = tuple(queries)
        if self.field is None:
            raise ValueError(f"{self.scene.source}: queries need a run (--run)")
        with self._lock:
            if queries in self._relevancy:
                return self._relevancy[queries]
            out = calibrated_relevancy(self.field.scores(queries), self.field.scores(self.competitors),
                                       competitor_mask(queries, self.competitors), self.temperature,
                                       query_offsets(queries, self.offsets))
            self._relevancy = {queries: out}  # the last answer only: 4 bytes x N x Q
            return out

    def _query_colouring(self, queries: tuple[str, ...], threshold: float, start: float) -> Colouring:
        if not queries:
            return Colouring("query", self.dimmed, [], "query: type one or more comma-separated phrases",
                             None, time.perf_counter() - start)
        hits = query_hits(self.relevancies(queries), threshold)
        query_rgb = palette(len(queries)) if len(queries) > 1 else None
        rgb = query_colours(self.dimmed, hits, query_rgb)
        legend = []
        for j, text in enumerate(queries):
            count = int(np.count_nonzero(hits.hit & (hits.best == j)))
            colour = query_rgb[j] if query_rgb is not None else np.array([255, 0, 0])
            legend.append(LegendRow(text, tuple(int(c) for c in colour), count))
        total = int(np.count_nonzero(hits.hit))
        best = float(hits.value.max()) if len(hits.value) else float("nan")
        status = (f"query {', '.join(repr(q) for q in queries)}: {total:,} of {len(hits.hit):,} Gaussians at "
                  f"relevancy >= {threshold:.3f} (calibrated default {DEFAULT_THRESHOLD:.3f}; max {best:.3f})")
        return Colouring("query", rgb, legend, status, hits, time.perf_counter() - start)

    # --- clicks ----------------------------------------------------------------------------------------
    def pick(self, origin, direction) -> int | None:
        """The Gaussian under a click ray (``scene.pick_gaussian``)."""
        return pick_gaussian(self.arrays.centers, self.radii, self.arrays.opacities, origin, direction)

    def inspect(self, index: int, queries: Sequence[str] = ()) -> dict:
        """What Gaussian ``index`` is: position, predicted class and top scores, ground truth, query relevancy."""
        index = int(index)
        if not 0 <= index < len(self.scene.gaussians):
            raise IndexError(f"{self.scene.source}: no Gaussian {index} (the scene has {len(self.scene.gaussians)})")
        out: dict = {"index": index, "position": [float(v) for v in self.arrays.centers[index]],
                     "rgb": [int(v) for v in self.arrays.rgb[index]]}
        if self.field is not None:
            scores = self.field.gaussian_scores(index, self.vocabulary)
            ranked = top_k(scores, self.vocabulary, INSPECT_TOP_K)
            out["predicted"] = ranked[0][0]
            out["top"] = [{"name": name, "score": score} for name, score in ranked]
            if queries:
                rel = self.relevancies(tuple(queries))[index]
                out["relevancy"] = {q: float(rel[j]) for j, q in enumerate(queries)}
        if self.scene.semantic is not None:
            label = int(self.scene.semantic[index])
            out["ground_truth"] = self._class_name(label)
            out["ground_truth_id"] = label
        if self.scene.instance is not None:
            out["instance"] = int(self.scene.instance[index])
        return out
