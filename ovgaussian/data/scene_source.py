"""Where OVGaussian's training scenes come from, and the scan that decides which of them are trained on.

A :class:`SceneSource` lists and reads SceneRecords: :class:`ShardSource` for a split of a dataset written by
``seggaussian build``/``split``, :class:`InMemorySource` for tests and notebooks. :func:`scan_scenes` reads
every scene of the split once (one at a time, memory bounded): counts Gaussians, train views and labels,
marks scenes that are empty or all-ignore as skipped (counted, never silently dropped) and computes a
data fingerprint (what ``--resume`` checks).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import NamedTuple, Protocol, Sequence

import numpy as np

from ovgaussian.text.vocabulary import Vocabulary, map_labels
from seggaussian import shards
from seggaussian.core.constants import IGNORE_LABEL


class SceneSource(Protocol):
    """Where scenes come from: ``seggaussian.shards`` for a dataset split, or memory in tests."""

    def list_scenes(self) -> list[str]: ...

    def read_scene(self, scene_id: str): ...  # -> SceneRecord


class ShardSource:
    """Scenes of one split of a dataset written by ``seggaussian build``/``split``."""

    def __init__(self, dataset: Path, split: str, verify: bool = False):
        self.dataset, self.split, self.verify = Path(dataset), split, verify

    def list_scenes(self) -> list[str]:
        return list(shards.list_scenes(self.dataset, self.split))

    def read_scene(self, scene_id: str):
        return shards.read_scene(self.dataset, self.split, scene_id, verify=self.verify)

    def fingerprint_files(self) -> dict[str, str]:
        """sha256 of the dataset's manifest files (``*manifest*.json``)."""
        out = {}
        for path in sorted(self.dataset.rglob("*manifest*.json")):
            out[str(path.relative_to(self.dataset))] = hashlib.sha256(path.read_bytes()).hexdigest()
        return out


class InMemorySource:
    """Scenes held in memory (tests, notebooks): ``records`` are SceneRecord-like objects."""

    def __init__(self, records: Sequence):
        self.records = {r.scene_id: r for r in records}

    def list_scenes(self) -> list[str]:
        return list(self.records)

    def read_scene(self, scene_id: str):
        return self.records[scene_id]

    def fingerprint_files(self) -> dict[str, str]:
        return {}


class SceneSummary(NamedTuple):
    """What the scan learned about a scene.

    Fields:
        scene_id: identifier.
        num_gaussians: N.
        train_views: names of the views with role ``train``.
        labelled_gaussians: Gaussians with a seen-class label.
        labelled_pixels: pixels of the train views with a seen-class label.
        skip_reason: None, or why the scene is not trained on (``empty``, ``no train view``, ``all ignore``).
        class_counts: ``[C]`` Gaussians per seen class (for class-balanced loss weights).
    """

    scene_id: str
    num_gaussians: int
    train_views: tuple[str, ...]
    labelled_gaussians: int
    labelled_pixels: int
    skip_reason: str | None
    class_counts: tuple[int, ...] = ()


class ScanResult(NamedTuple):
    """The split's scenes.

    Fields:
        summaries: one per scene, in ``list_scenes`` order.
        usable: ids of the scenes trained on.
        skipped: ``{reason: count}``.
        fingerprint: hex digest of the data (manifest files, scene ids, sizes, label counts).
    """

    summaries: tuple[SceneSummary, ...]
    usable: tuple[str, ...]
    skipped: dict[str, int]
    fingerprint: str


def summarize_scene(record, vocabulary: Vocabulary) -> SceneSummary:
    """Counts of one SceneRecord and whether it can be trained on."""
    n = len(record.gaussians)
    views = tuple(v.name for v in record.views if v.role == "train")
    semantic = record.gaussians.extras.get("semantic")
    mapped = np.zeros(0, np.int64) if semantic is None else map_labels(semantic, vocabulary)
    mapped = mapped[mapped != IGNORE_LABEL]
    labelled = int(mapped.size)
    class_counts = tuple(int(c) for c in np.bincount(mapped, minlength=vocabulary.class_ids.size))
    pixels = sum(int((map_labels(v.semantic, vocabulary) != IGNORE_LABEL).sum())
                 for v in record.views if v.role == "train" and v.semantic is not None)
    reason = None
    if n == 0:
        reason = "empty"
    elif not views:
        reason = "no train view"
    elif labelled == 0 and pixels == 0:
        reason = "all ignore"
    return SceneSummary(record.scene_id, n, views, labelled, pixels, reason, class_counts)


def class_weights(scan: ScanResult, num_classes: int, exponent: float) -> np.ndarray:
    """``[C]`` float32 loss weights ``n_c ** -exponent`` of the seen classes from the usable scenes' Gaussian
    counts ``n_c``, scaled so the labelled Gaussians' mean weight is 1; 0 counts as 1 (a class never seen
    gets the largest weight, harmlessly: it has no sample). ``exponent`` 0 gives all ones."""
    counts = np.zeros(num_classes, np.float64)
    usable = set(scan.usable)
    for summary in scan.summaries:
        if summary.scene_id in usable and summary.class_counts:
            counts += np.asarray(summary.class_counts, np.float64)
    weights = np.maximum(counts, 1.0) ** -float(exponent)
    total = counts.sum()
    if total > 0:
        weights *= total / float((weights * counts).sum())
    return weights.astype(np.float32)


def scan_scenes(source: SceneSource, vocabulary: Vocabulary) -> ScanResult:
    """Read every scene once (one at a time) and summarize the split."""
    summaries = []
    for scene_id in source.list_scenes():
        summaries.append(summarize_scene(source.read_scene(scene_id), vocabulary))
    skipped: dict[str, int] = {}
    for s in summaries:
        if s.skip_reason is not None:
            skipped[s.skip_reason] = skipped.get(s.skip_reason, 0) + 1
    files = source.fingerprint_files() if hasattr(source, "fingerprint_files") else {}
    payload = json.dumps({"files": files, "scenes": [list(s[:5]) for s in summaries],
                          "vocabulary": vocabulary.class_ids.tolist()}, sort_keys=True)
    fingerprint = hashlib.sha256(payload.encode()).hexdigest()
    usable = tuple(s.scene_id for s in summaries if s.skip_reason is None)
    return ScanResult(tuple(summaries), usable, skipped, fingerprint)


def with_renditions(scan: ScanResult, renditions: Sequence[SceneSource], names: Sequence[str],
                    vocabulary: Vocabulary) -> ScanResult:
    """``scan`` of the dataset, checked against other renditions of its rooms (other splats of the same scenes):
    every scene trained on must be trainable in each rendition too (ValueError naming the rendition ``names[i]``
    and the scene otherwise); the fingerprint then covers the renditions' data as well (what ``--resume`` checks)."""
    digests = [scan.fingerprint]
    for name, source in zip(names, renditions):
        other = scan_scenes(source, vocabulary)
        usable = set(other.usable)
        missing = [s for s in scan.usable if s not in usable]
        if missing:
            raise ValueError(f"{name}: rendition has no trainable scene {missing[0]!r} of the training split "
                             f"({len(missing)} of {len(scan.usable)} missing; build it from the same raw tree and "
                             f"split it the same way)")
        digests.append(other.fingerprint)
    fingerprint = hashlib.sha256(json.dumps(digests).encode()).hexdigest() if renditions else scan.fingerprint
    return scan._replace(fingerprint=fingerprint)
