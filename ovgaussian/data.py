"""Training data of OVGaussian: split shards -> per-step batches of (scene, one view) samples.

Flow, one scene at a time (memory bounded):

1. :func:`scan_scenes` reads every scene of the split once: counts Gaussians, train views and
   labels, marks scenes that are empty or all-ignore as skipped (counted, never silently
   dropped) and computes a data fingerprint.
2. :class:`TrainingData` prepares a scene on demand (in-memory LRU of ``scene_cache_size``): means
   recentred on the bounding-box centre (float64 subtraction, then float32), unit quaternions (their
   sign is made canonical by ``ovgaussian.model.gaussian_attributes``, as on every path),
   colours, labels mapped from top-100 class ids to the *seen-class index* (0..C_seen-1) with
   unseen and out-of-vocabulary classes set to ``IGNORE_LABEL``, in 3D and in the 2D label maps.
3. For a view it keeps the label map and the MaskCLIP patch features (computed once, cached on
   disk at patch resolution in the run's cache folder) in a view LRU of ``view_cache_size``.
4. :meth:`TrainingData.sample` draws, from a generator seeded by (seed, epoch, step, scene), one
   train view, an augmentation and the pixels of the 2D losses, and computes the blend weights W
   (top ``blend_top_k`` contributors, on the stored, un-augmented geometry, float64 camera) at those
   pixels only (``seggaussian.render.pixel_blend``): bit-identical to the whole view's weights at
   those pixels, and nothing per pixel is stored on disk.

Augmentation (random uniform scale, rotation about the up axis z, mirror of x and/or y) is a
similarity ``A`` applied to the network input only: means ``A x``, covariances ``A Sigma A^T``
(quaternions and log-scales updated). Applying the same ``A`` to the camera would leave the
rendered image unchanged (a similarity of scene and camera together does not change any pixel),
so the blend weights computed once on the stored geometry stay exact and ``M = W S`` needs no
re-rasterization.
"""

from __future__ import annotations

import hashlib
import json
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Protocol, Sequence

import numpy as np

from ovgaussian.cache_budget import folder_bytes
from ovgaussian.teacher import sample_patch_features
from ovgaussian.train_config import DataConfig
from ovgaussian.vocabulary import (  # noqa: F401  (re-exported: the training data's API)
    Vocabulary,
    benchmark_class_ids,
    map_labels,
    training_vocabulary,
)
from seggaussian import shards
from seggaussian.constants import IGNORE_LABEL
from seggaussian.gaussians import quats_to_rotmats
from seggaussian.render.pixel_blend import compute_pixel_blend_weights
from seggaussian.render.rasterize import camera_tensors

if TYPE_CHECKING:
    import torch

    from ovgaussian.teacher import DenseTeacher

#: Bytes a safetensors file takes beyond its tensor data (JSON header with names, shapes, offsets); an
#: upper bound used when checking the cache budget before writing.
SAFETENSORS_HEADER_ALLOWANCE = 512
#: Quaternions recovered from rotation matrices: the largest of the four candidates is at least 1/2, so
#: this floor only protects against a non-orthonormal input.
QUAT_FROM_MATRIX_EPS = 1e-12


# --- geometry --------------------------------------------------------------------------------------


def rotmats_to_quats(rotmats: np.ndarray) -> np.ndarray:
    """``[N, 3, 3]`` rotation matrices -> ``[N, 4]`` unit quaternions (w, x, y, z) (Shepperd).

    The sign of each row is whatever the method gives; the network's inputs are made sign-canonical in
    one place for every path, ``ovgaussian.model.gaussian_attributes``."""
    r = np.asarray(rotmats, dtype=np.float64)
    trace = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    candidates = np.stack([trace, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    choice = np.argmax(candidates, axis=1)
    q = np.empty((r.shape[0], 4), dtype=np.float64)
    for k in range(4):
        rows = choice == k
        if not rows.any():
            continue
        m = r[rows]
        if k == 0:
            s = np.sqrt(np.maximum(1.0 + trace[rows], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([0.25 * s, (m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                                (m[:, 1, 0] - m[:, 0, 1]) / s], axis=1)
        elif k == 1:
            s = np.sqrt(np.maximum(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / s, 0.25 * s, (m[:, 0, 1] + m[:, 1, 0]) / s,
                                (m[:, 0, 2] + m[:, 2, 0]) / s], axis=1)
        elif k == 2:
            s = np.sqrt(np.maximum(1.0 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([(m[:, 0, 2] - m[:, 2, 0]) / s, (m[:, 0, 1] + m[:, 1, 0]) / s, 0.25 * s,
                                (m[:, 1, 2] + m[:, 2, 1]) / s], axis=1)
        else:
            s = np.sqrt(np.maximum(1.0 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1], QUAT_FROM_MATRIX_EPS)) * 2.0
            q[rows] = np.stack([(m[:, 1, 0] - m[:, 0, 1]) / s, (m[:, 0, 2] + m[:, 2, 0]) / s,
                                (m[:, 1, 2] + m[:, 2, 1]) / s, 0.25 * s], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


class Augmentation(NamedTuple):
    """A similarity ``x -> scale * flip @ rot_z @ x`` about the scene centre.

    Fields:
        scale: uniform scale factor (> 0).
        angle: rotation about z in radians.
        flip: ``[3]`` signs (+-1 on x and y, +1 on z).
    """

    scale: float
    angle: float
    flip: np.ndarray

    @property
    def linear(self) -> np.ndarray:
        """``[3, 3]`` matrix ``scale * diag(flip) @ R_z(angle)``."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return self.scale * np.diag(self.flip) @ rot

    @classmethod
    def identity(cls) -> "Augmentation":
        return cls(1.0, 0.0, np.ones(3))


def sample_augmentation(rng: np.random.Generator, config: DataConfig) -> Augmentation:
    """Random scale in ``scale_range``, angle in [0, 2 pi), x/y mirrors with ``flip_probability``."""
    if not config.augment:
        return Augmentation.identity()
    low, high = config.scale_range
    scale = float(rng.uniform(low, high))
    angle = float(rng.uniform(0.0, 2.0 * np.pi))
    flips = rng.random(2) < config.flip_probability
    flip = np.array([-1.0 if flips[0] else 1.0, -1.0 if flips[1] else 1.0, 1.0])
    return Augmentation(scale, angle, flip)


def augment_gaussians(
    means: np.ndarray,  # [N, 3] recentred
    quats: np.ndarray,  # [N, 4] unit, w x y z
    log_scales: np.ndarray,  # [N, 3]
    augmentation: Augmentation,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means, quaternions and log-scales of the Gaussians mapped by the similarity (float32 out).

    Covariance ``R S^2 R^T`` becomes ``A R S^2 R^T A^T``: with ``A = s F R_z`` the new rotation is
    ``F R_z R D`` where ``D = diag(det F, 1, 1)`` makes it proper (D commutes with ``S``), and the
    log-scales grow by ``log s``.
    """
    linear = augmentation.linear
    new_means = (means.astype(np.float64) @ linear.T).astype(np.float32)
    orthogonal = linear / augmentation.scale  # F R_z, det = det F
    rotmats = np.einsum("ij,njk->nik", orthogonal, quats_to_rotmats(quats.astype(np.float64)))
    if float(np.prod(augmentation.flip)) < 0:
        rotmats[:, :, 0] *= -1.0  # R D with D = diag(-1, 1, 1): proper again, same covariance
    new_quats = rotmats_to_quats(rotmats).astype(np.float32)
    new_log_scales = (log_scales.astype(np.float64) + np.log(augmentation.scale)).astype(np.float32)
    return new_means, new_quats, new_log_scales


# --- records ---------------------------------------------------------------------------------------


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
    """

    scene_id: str
    num_gaussians: int
    train_views: tuple[str, ...]
    labelled_gaussians: int
    labelled_pixels: int
    skip_reason: str | None


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
    labelled = 0 if semantic is None else int((map_labels(semantic, vocabulary) != IGNORE_LABEL).sum())
    pixels = sum(int((map_labels(v.semantic, vocabulary) != IGNORE_LABEL).sum())
                 for v in record.views if v.role == "train" and v.semantic is not None)
    reason = None
    if n == 0:
        reason = "empty"
    elif not views:
        reason = "no train view"
    elif labelled == 0 and pixels == 0:
        reason = "all ignore"
    return SceneSummary(record.scene_id, n, views, labelled, pixels, reason)


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


# --- prepared tensors ------------------------------------------------------------------------------


class PreparedScene(NamedTuple):
    """A scene ready for the network (numpy, float32 unless noted).

    Fields:
        scene_id: identifier.
        centre: ``[3]`` float64 bounding-box centre subtracted from the means.
        means: ``[N, 3]`` recentred means.
        quats: ``[N, 4]`` unit quaternions (w, x, y, z).
        log_scales: ``[N, 3]``.
        opacity_logits: ``[N]``.
        sh_dc: ``[N, 3]`` DC spherical-harmonic coefficients (colour = 0.5 + SH_C0 sh_dc).
        labels: ``[N]`` int64 seen-class index or IGNORE_LABEL.
        train_views: names of the train views.
    """

    scene_id: str
    centre: np.ndarray
    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    labels: np.ndarray
    train_views: tuple[str, ...]


class PreparedView(NamedTuple):
    """A view ready for the 2D losses (its blend weights are computed per step at the sampled pixels).

    Fields:
        name: view name.
        camera: the view's ``seggaussian.cameras.Camera``.
        labels: ``[H, W]`` int64 seen-class index or IGNORE_LABEL.
        teacher: ``[h, w, D]`` float32 MaskCLIP patch features, or None (no teacher).
    """

    name: str
    camera: object
    labels: np.ndarray
    teacher: "torch.Tensor | None"


class SceneSample(NamedTuple):
    """One scene of a training step (torch tensors on the CPU).

    Fields:
        scene_id, view_name: where it comes from.
        means: ``[N, 3]`` augmented, recentred means.
        quats: ``[N, 4]`` augmented unit quaternions.
        log_scales: ``[N, 3]`` augmented log-scales.
        opacity_logits: ``[N]``.
        sh_dc: ``[N, 3]`` DC SH coefficients.
        labels: ``[N]`` int64 seen-class index or IGNORE_LABEL.
        pixels: ``[P, 2]`` int64 (column u, row v) of the pixels of the 2D losses.
        pixel_ids: ``[P, K]`` int64 blend ids at those pixels (-1 unused).
        pixel_weights: ``[P, K]`` float32 blend weights at those pixels.
        pixel_labels: ``[P]`` int64 seen-class index or IGNORE_LABEL.
        teacher: ``[P, D]`` float32 teacher features at those pixels, or None.
        image_size: (H, W).
    """

    scene_id: str
    view_name: str
    means: "torch.Tensor"
    quats: "torch.Tensor"
    log_scales: "torch.Tensor"
    opacity_logits: "torch.Tensor"
    sh_dc: "torch.Tensor"
    labels: "torch.Tensor"
    pixels: "torch.Tensor"
    pixel_ids: "torch.Tensor"
    pixel_weights: "torch.Tensor"
    pixel_labels: "torch.Tensor"
    teacher: "torch.Tensor | None"
    image_size: tuple[int, int]


def prepare_scene(record, vocabulary: Vocabulary) -> PreparedScene:
    """Recentred float32 geometry, unit quaternions, colours and mapped labels of a SceneRecord."""
    g = record.gaussians
    means64 = g.means.astype(np.float64)
    if not np.isfinite(means64).all():
        raise ValueError(f"scene {record.scene_id}: Gaussians.means holds NaN/Inf")
    centre = 0.5 * (means64.min(axis=0) + means64.max(axis=0)) if len(g) else np.zeros(3)
    semantic = g.extras.get("semantic")
    labels = (np.full(len(g), IGNORE_LABEL, np.int64) if semantic is None else map_labels(semantic, vocabulary))
    return PreparedScene(
        record.scene_id, centre, (means64 - centre).astype(np.float32), g.normalized_quats(),
        g.log_scales.copy(), g.opacity_logits.copy(), g.sh[:, 0, :].copy(), labels,
        tuple(v.name for v in record.views if v.role == "train"),
    )


def default_pixel_blend_function():
    """``seggaussian.render.pixel_blend.compute_pixel_blend_weights``."""
    return compute_pixel_blend_weights


class GeometryTensors(NamedTuple):
    """The stored (un-augmented) geometry of a scene as float32 CPU tensors, for the blend weights.

    Fields:
        means: ``[N, 3]``; quats: ``[N, 4]``; log_scales: ``[N, 3]``; opacity_logits: ``[N]``.
    """

    means: "torch.Tensor"
    quats: "torch.Tensor"
    log_scales: "torch.Tensor"
    opacity_logits: "torch.Tensor"


def geometry_tensors(gaussians) -> GeometryTensors:
    """Copies of a Gaussians' geometry columns (shard arrays may be read-only numpy views)."""
    import torch

    return GeometryTensors(*(torch.tensor(getattr(gaussians, name))
                             for name in ("means", "quats", "log_scales", "opacity_logits")))


def sample_seed(seed: int, epoch: int, step: int, scene_id: str) -> list[int]:
    """Entropy of the generator of one scene of one step (rank-independent)."""
    digest = int.from_bytes(hashlib.sha256(scene_id.encode()).digest()[:4], "little")
    return [int(seed), int(epoch), int(step), digest]


class TrainingData:
    """Scenes of a split, prepared and cached for training.

    Args:
        source: where SceneRecords come from.
        config: data options.
        vocabulary: the training vocabulary.
        cache_dir: folder for the teacher cache (None: memory only).
        teacher: the dense teacher, or None (no visual-semantic loss).
        pixel_blend_function: ``compute_pixel_blend_weights``-compatible callable (default: seggaussian.render).
        cache_budget_bytes: most bytes the files under ``cache_dir`` may take (teacher features beyond it
            are computed per use, not cached); None: no limit.
    """

    def __init__(self, source: SceneSource, config: DataConfig, vocabulary: Vocabulary, *,
                 cache_dir: Path | None = None, teacher: "DenseTeacher | None" = None,
                 pixel_blend_function: Callable | None = None, scan: ScanResult | None = None,
                 cache_budget_bytes: int | None = None):
        self.source, self.config, self.vocabulary = source, config, vocabulary
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.teacher = teacher
        self.pixel_blend_function = pixel_blend_function or default_pixel_blend_function()
        self.scan = scan if scan is not None else scan_scenes(source, vocabulary)
        self._scenes: OrderedDict[str, tuple[PreparedScene, object, GeometryTensors]] = OrderedDict()
        self._views: OrderedDict[tuple[str, str], PreparedView] = OrderedDict()
        self.blend_computations = 0  # calls of the pixel blend function (one per sample)
        self.cache_budget_bytes = cache_budget_bytes
        self._cache_bytes: int | None = None  # bytes under cache_dir, counted on first use
        self.teacher_uncached = 0  # teacher features computed without caching (budget reached)

    @property
    def scene_ids(self) -> tuple[str, ...]:
        return self.scan.usable

    # scenes ---------------------------------------------------------------------------------
    def _record_and_scene(self, scene_id: str):
        if scene_id in self._scenes:
            self._scenes.move_to_end(scene_id)
            return self._scenes[scene_id]
        record = self.source.read_scene(scene_id)
        if hasattr(record, "_replace"):  # keep only what later steps need: the train views, no instance maps
            record = record._replace(views=[v._replace(instance=None) for v in record.views if v.role == "train"])
        entry = (prepare_scene(record, self.vocabulary), record, geometry_tensors(record.gaussians))
        self._scenes[scene_id] = entry
        while len(self._scenes) > max(1, self.config.scene_cache_size):
            self._scenes.popitem(last=False)
        return entry

    def prepared_scene(self, scene_id: str) -> PreparedScene:
        return self._record_and_scene(scene_id)[0]

    # views ----------------------------------------------------------------------------------
    def pixel_blend_weights(self, scene_id: str, view: PreparedView, pixels: "torch.Tensor"):
        """``(ids [P, K], weights [P, K])`` of the view at ``pixels [P, 2]`` (u, v), on the stored geometry."""
        geometry = self._record_and_scene(scene_id)[2]
        cam = view.camera
        viewmat, K = camera_tensors(cam)  # float64, as the benchmark's and the build's blend weights
        blend = self.pixel_blend_function(*geometry, viewmat, K, cam.width, cam.height, pixels,
                                          top_k=self.config.blend_top_k)
        self.blend_computations += 1
        return blend.ids.long(), blend.weights.float()

    def prepared_view(self, scene_id: str, view_name: str) -> PreparedView:
        key = (scene_id, view_name)
        if key in self._views:
            self._views.move_to_end(key)
            return self._views[key]
        record = self._record_and_scene(scene_id)[1]
        view = next((v for v in record.views if v.name == view_name), None)
        if view is None:
            raise KeyError(f"scene {scene_id}: no view named {view_name!r}")
        h, w = view.camera.height, view.camera.width
        if view.semantic is None:
            labels = np.full((h, w), IGNORE_LABEL, np.int64)
        else:
            if view.semantic.shape != (h, w):
                raise ValueError(f"scene {scene_id} view {view_name}: semantic map has shape "
                                 f"{view.semantic.shape}, camera is {(h, w)}")
            labels = map_labels(view.semantic, self.vocabulary)
        teacher = None
        if self.teacher is not None:
            if view.rgb is None:
                raise ValueError(f"scene {scene_id} view {view_name}: no RGB image for the teacher")
            teacher = self._teacher_features(view.rgb, f"{safe_name(scene_id)}__{safe_name(view_name)}")
        prepared = PreparedView(view_name, view.camera, labels, teacher)
        self._views[key] = prepared
        while len(self._views) > max(1, self.config.view_cache_size):
            self._views.popitem(last=False)
        return prepared

    def _teacher_features(self, rgb: np.ndarray, name: str) -> "torch.Tensor":
        """Patch features of a view: from the disk cache, or computed and cached while the run folder's
        caches stay within ``cache_budget_bytes``; past it computed per use (counted in ``teacher_uncached``)."""
        if self.cache_dir is None or self.cache_budget_bytes is None:
            return self.teacher.cached_patch_features(rgb, self.cache_dir, name).patch_features
        if self._cache_bytes is None:
            self._cache_bytes = folder_bytes(self.cache_dir)
        path = self.teacher.cache_path(self.cache_dir, name)
        existed = path.is_file()

        def may_write(nbytes: int) -> bool:
            room = self._cache_bytes + nbytes + SAFETENSORS_HEADER_ALLOWANCE <= self.cache_budget_bytes
            self.teacher_uncached += 0 if room else 1
            return room

        features = self.teacher.cached_patch_features(rgb, self.cache_dir, name, may_write).patch_features
        if not existed and path.is_file():
            self._cache_bytes += path.stat().st_size
        return features

    # samples --------------------------------------------------------------------------------
    def sample(self, scene_id: str, rng: np.random.Generator) -> SceneSample:
        """One view, augmentation and pixel set of a scene, drawn from ``rng``."""
        import torch

        scene = self.prepared_scene(scene_id)
        view_name = scene.train_views[int(rng.integers(len(scene.train_views)))]
        view = self.prepared_view(scene_id, view_name)
        augmentation = sample_augmentation(rng, self.config)
        means, quats, log_scales = augment_gaussians(scene.means, scene.quats, scene.log_scales, augmentation)
        h, w = view.labels.shape
        num_pixels = h * w
        if self.config.pixels_per_view is None or self.config.pixels_per_view >= num_pixels:
            flat = np.arange(num_pixels)
        else:
            flat = np.sort(rng.choice(num_pixels, size=self.config.pixels_per_view, replace=False))
        rows, cols = flat // w, flat % w
        pixels = torch.from_numpy(np.stack([cols, rows], axis=1)).long()
        pixel_ids, pixel_weights = self.pixel_blend_weights(scene_id, view, pixels)
        teacher = None
        if view.teacher is not None:
            teacher = sample_patch_features(view.teacher, pixels, (h, w))
        return SceneSample(
            scene_id, view_name, torch.from_numpy(means), torch.from_numpy(quats), torch.from_numpy(log_scales),
            torch.from_numpy(scene.opacity_logits), torch.from_numpy(scene.sh_dc), torch.from_numpy(scene.labels),
            pixels, pixel_ids, pixel_weights, torch.from_numpy(view.labels.reshape(-1)[flat]), teacher, (h, w),
        )


def safe_name(name: str) -> str:
    """A file-name-safe version of a scene or view name (readable prefix + short digest)."""
    keep = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:64]
    return f"{keep}-{hashlib.sha1(name.encode()).hexdigest()[:8]}"


def epoch_batches(scene_ids: Sequence[str], batch_scenes: int, seed: int, epoch: int) -> list[list[str]]:
    """The epoch's scene order (seeded permutation) cut into batches of ``batch_scenes`` (last may be short)."""
    if batch_scenes < 1:
        raise ValueError(f"batch_scenes must be >= 1, got {batch_scenes}")
    order = np.random.default_rng([int(seed), int(epoch), 0x5CE4E]).permutation(len(scene_ids))
    ids = [scene_ids[i] for i in order]
    return [ids[i:i + batch_scenes] for i in range(0, len(ids), batch_scenes)]


def rank_slice(batch: Sequence[str], rank: int, world_size: int) -> list[str]:
    """The contiguous part of a global batch a process handles (may be empty)."""
    bounds = np.linspace(0, len(batch), world_size + 1).round().astype(int)
    return list(batch[bounds[rank]:bounds[rank + 1]])
