"""Training data of OVGaussian: the scenes of a split prepared on demand, and one (scene, view) sample per step.

Flow, one scene at a time (memory bounded):

1. The split's scenes come from a ``scene_source.SceneSource``, scanned once by ``scene_source.scan_scenes``
   (skipped scenes counted, a data fingerprint).
2. :class:`TrainingData` prepares a scene on demand (from the dataset or, with renditions, from the dataset of
   another splat of the same room that the sample drew) (in-memory LRU of ``scene_cache_size``): means
   recentred on the bounding-box centre (float64 subtraction, then float32), unit quaternions (their
   sign is made canonical by ``ovgaussian.model.network.gaussian_attributes``, as on every path),
   colours, labels mapped from top-100 class ids to the *seen-class index* (0..C_seen-1) with
   unseen and out-of-vocabulary classes set to ``IGNORE_LABEL``, in 3D and in the 2D label maps.
3. For a view it keeps the label map and the MaskCLIP patch features (computed once, cached on
   disk at patch resolution in the run's cache folder) in a view LRU of ``view_cache_size``.
4. :meth:`TrainingData.sample` draws, from a generator seeded by (seed, epoch, step, scene)
   (``schedule.sample_seed``), one train view, an augmentation (``augmentation``: a similarity applied to
   the network input only) and the pixels of the 2D losses, and computes the blend weights W
   (top ``blend_top_k`` contributors, on the stored, un-augmented geometry, float64 camera) at those
   pixels only (``seggaussian.render.pixel_blend``): bit-identical to the whole view's weights at
   those pixels, and nothing per pixel is stored on disk.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np
import torch

from ovgaussian.data.augmentation import (COLOUR_AUGMENT_PROBABILITY, OFF_SURFACE_PROBABILITY, RENDITION_PROBABILITY,
                                          SPLAT_AUGMENT_PROBABILITY, augment_gaussians, off_surface, recolour,
                                          rendition, sample_augmentation, splat_statistics, surface_normals)
from ovgaussian.data.cache_budget import folder_bytes
from ovgaussian.data.scene_source import ScanResult, SceneSource, scan_scenes
from ovgaussian.text.teacher import sample_patch_features
from ovgaussian.run.config import DataConfig
from ovgaussian.text.vocabulary import Vocabulary, map_labels
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render.pixel_blend import compute_pixel_blend_weights
from seggaussian.render.rasterize import camera_tensors

if TYPE_CHECKING:
    from ovgaussian.text.teacher import DenseTeacher

#: Bytes a safetensors file takes beyond its tensor data (JSON header with names, shapes, offsets); an
#: upper bound used when checking the cache budget before writing.
SAFETENSORS_HEADER_ALLOWANCE = 512


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
        camera: the view's ``seggaussian.core.cameras.Camera``.
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
        loss_rows: ``[L]`` int64 increasing rows of the Gaussians in the 3D-to-text loss
            (``DataConfig.loss_gaussians``), or None for every Gaussian.
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
    loss_rows: "torch.Tensor | None" = None


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
    return GeometryTensors(*(torch.tensor(getattr(gaussians, name))
                             for name in ("means", "quats", "log_scales", "opacity_logits")))


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
                 cache_budget_bytes: int | None = None, renditions: Sequence[SceneSource] = ()):
        self.config, self.vocabulary = config, vocabulary
        self.sources = (source, *renditions)  # rendition 0 is the dataset itself
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.teacher = teacher
        self.pixel_blend_function = pixel_blend_function or default_pixel_blend_function()
        self.scan = scan if scan is not None else scan_scenes(source, vocabulary)
        self._scenes: OrderedDict[tuple[int, str], tuple[PreparedScene, object, GeometryTensors]] = OrderedDict()
        self._views: OrderedDict[tuple[int, str, str], PreparedView] = OrderedDict()
        self._normals: dict[tuple[int, str], np.ndarray] = {}  # off_surface's, stored frame, per cached scene
        self.blend_computations = 0  # calls of the pixel blend function (one per sample)
        self.cache_budget_bytes = cache_budget_bytes
        self._cache_bytes: int | None = None  # bytes under cache_dir, counted on first use
        self.teacher_uncached = 0  # teacher features computed without caching (budget reached)

    @property
    def scene_ids(self) -> tuple[str, ...]:
        return self.scan.usable

    # scenes ---------------------------------------------------------------------------------
    def _record_and_scene(self, scene_id: str, rendition: int = 0):
        key = (rendition, scene_id)
        if key in self._scenes:
            self._scenes.move_to_end(key)
            return self._scenes[key]
        record = self.sources[rendition].read_scene(scene_id)
        if hasattr(record, "_replace"):  # keep only what later steps need: the train views, no instance maps
            record = record._replace(views=[v._replace(instance=None) for v in record.views if v.role == "train"])
        entry = (prepare_scene(record, self.vocabulary), record, geometry_tensors(record.gaussians))
        self._scenes[key] = entry
        while len(self._scenes) > max(1, self.config.scene_cache_size) * len(self.sources):
            evicted, _ = self._scenes.popitem(last=False)
            self._normals.pop(evicted, None)
        return entry

    def prepared_scene(self, scene_id: str, rendition: int = 0) -> PreparedScene:
        return self._record_and_scene(scene_id, rendition)[0]

    def _stored_normals(self, scene_id: str, rendition: int, means: np.ndarray) -> np.ndarray:
        """``[N, 3]`` surface normals of a prepared scene's means (``augmentation.surface_normals``), kept as long
        as its scene is (dropped when the scene cache lets it go)."""
        key = (rendition, scene_id)
        if key not in self._normals:
            self._normals[key] = surface_normals(means)
        return self._normals[key]

    # views ----------------------------------------------------------------------------------
    def pixel_blend_weights(self, scene_id: str, view: PreparedView, pixels: "torch.Tensor", rendition: int = 0):
        """``(ids [P, K], weights [P, K])`` of the view at ``pixels [P, 2]`` (u, v), on the stored geometry."""
        geometry = self._record_and_scene(scene_id, rendition)[2]
        cam = view.camera
        viewmat, K = camera_tensors(cam)  # float64, as the benchmark's and the build's blend weights
        blend = self.pixel_blend_function(*geometry, viewmat, K, cam.width, cam.height, pixels,
                                          top_k=self.config.blend_top_k)
        self.blend_computations += 1
        return blend.ids.long(), blend.weights.float()

    def prepared_view(self, scene_id: str, view_name: str, rendition: int = 0) -> PreparedView:
        key = (rendition, scene_id, view_name)
        if key in self._views:
            self._views.move_to_end(key)
            return self._views[key]
        record = self._record_and_scene(scene_id, rendition)[1]
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
            # a rendition's views may be rendered from its own Gaussians: its features are cached apart
            prefix = "" if rendition == 0 else f"rendition{rendition}__"
            teacher = self._teacher_features(view.rgb, f"{prefix}{safe_name(scene_id)}__{safe_name(view_name)}")
        prepared = PreparedView(view_name, view.camera, labels, teacher)
        self._views[key] = prepared
        while len(self._views) > max(1, self.config.view_cache_size) * len(self.sources):
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
        """One rendition of a scene (when there are several), view, augmentation and pixel set, drawn from ``rng``."""
        drawn = int(rng.integers(len(self.sources))) if len(self.sources) > 1 else 0  # one source: as before
        scene = self.prepared_scene(scene_id, drawn)
        view_name = scene.train_views[int(rng.integers(len(scene.train_views)))]
        view = self.prepared_view(scene_id, view_name, drawn)
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
        pixel_ids, pixel_weights = self.pixel_blend_weights(scene_id, view, pixels, drawn)
        teacher = None
        if view.teacher is not None:
            teacher = sample_patch_features(view.teacher, pixels, (h, w))
        opacity_logits, sh_dc, labels = scene.opacity_logits, scene.sh_dc, scene.labels
        remade = False  # whether the Gaussians are other than the stored ones under the similarity
        if self.config.splat_augment and rng.random() < SPLAT_AUGMENT_PROBABILITY:
            means, quats, log_scales, opacity_logits, sh_dc, labels = splat_statistics(
                rng, means, quats, log_scales, opacity_logits, sh_dc, labels, IGNORE_LABEL)
            remade = True
        if self.config.rendition_augment and rng.random() < RENDITION_PROBABILITY:
            means, quats, log_scales, opacity_logits, sh_dc, labels = rendition(
                rng, means, quats, log_scales, opacity_logits, sh_dc, labels)
            remade = True
        if self.config.off_surface_augment and rng.random() < OFF_SURFACE_PROBABILITY:
            normals = None
            if not remade:  # the stored Gaussians' normals, turned with the similarity
                normals = self._stored_normals(scene_id, drawn, scene.means) @ augmentation.linear.T
                normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
            means, quats, log_scales, opacity_logits, sh_dc, labels = off_surface(
                rng, means, quats, log_scales, opacity_logits, sh_dc, labels, normals)
        if self.config.colour_augment and rng.random() < COLOUR_AUGMENT_PROBABILITY:
            sh_dc = recolour(rng, sh_dc)
        loss_rows = None
        wanted = self.config.loss_gaussians
        if wanted is not None and wanted < len(labels):  # drawn last: without it a run draws as before, bitwise
            loss_rows = torch.from_numpy(np.sort(rng.choice(len(labels), size=wanted, replace=False)))
        return SceneSample(
            scene_id, view_name, torch.from_numpy(means), torch.from_numpy(quats), torch.from_numpy(log_scales),
            torch.from_numpy(opacity_logits), torch.from_numpy(sh_dc), torch.from_numpy(labels),
            pixels, pixel_ids, pixel_weights, torch.from_numpy(view.labels.reshape(-1)[flat]), teacher, (h, w),
            loss_rows,
        )


def safe_name(name: str) -> str:
    """A file-name-safe version of a scene or view name (readable prefix + short digest)."""
    keep = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:64]
    return f"{keep}-{hashlib.sha1(name.encode()).hexdigest()[:8]}"
