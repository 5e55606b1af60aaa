"""Configuration of ``ovgaussian bench`` (``PredictConfig`` of ``ovgaussian predict`` and the rendering defaults both share are in
``ovgaussian.predict.config``):
frozen dataclasses and the protocol constants, no code.

The protocol these settings drive is written down in ``data_specs/BENCHMARK.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from ovgaussian.openvocab.config import SynthesisConfig
from ovgaussian.predict.config import DEFAULT_BAND_ROWS, DEFAULT_MIN_ALPHA

#: Metric names in Table-1 order.
METRICS = ("CSA", "OVA", "NVA", "CDA")
#: Which dimensions each metric exists in (NVA is 2D only: novel views).
METRIC_DIMS = {"CSA": ("3d", "2d"), "OVA": ("3d", "2d"), "NVA": ("2d",), "CDA": ("3d", "2d")}
#: Which split each metric is scored on.
METRIC_SPLITS = {"CSA": "val", "OVA": "val", "NVA": "train", "CDA": "xval"}
#: Columns of a Table-1 row, in the paper's order.
TABLE1_COLUMNS = (("3d", "CSA"), ("3d", "OVA"), ("3d", "CDA"), ("2d", "CSA"), ("2d", "OVA"), ("2d", "NVA"), ("2d", "CDA"))

@dataclass(frozen=True)
class BenchConfig:
    """One benchmark evaluation."""

    dataset: Path = Path("dataset")
    """Dataset folder written by ``seggaussian build`` + ``seggaussian split`` (splits train/val/xval)."""
    run: Optional[Path] = None
    """Run folder of ``ovgaussian train`` whose model is scored (needed by ``predictor = model``)."""
    checkpoint: Optional[Path] = None
    """A checkpoint folder of the run (RUN/checkpoints/epoch-XXXX); None takes the run's latest checkpoint."""
    predictor: Literal["model", "majority", "nearest-colour"] = "model"
    """What is scored: the trained model, or a non-learned baseline fitted on the train split (baseline.py)."""
    prompt_ensemble: bool = False
    """Open vocabulary: embed each class name under several prompt templates, averaged (ovgaussian.text.prompt_ensemble)."""
    ensemble_runs: tuple[Path, ...] = ()
    """More runs scored with ``run`` as one ensemble: each encodes the scenes, and their class scores are averaged
    (ovgaussian.predict.ensemble). Typically the same recipe trained with other seeds. Not with stacking_run or
    generative; class_offsets are then fitted on the ensemble's scores."""
    stacking_run: Optional[Path] = None
    """Open vocabulary, calibrated stacking: a run trained with --holdout-classes; gamma is chosen with it on the train split (never on unseen labels), recorded in the report, and subtracted from the seen classes' scores (ovgaussian.openvocab.calibration)."""
    class_offsets: bool = False
    """Per-class score offsets: chosen on the train split to maximize its mIoU (training classes only, unseen labels never read), recorded in the report, and added to the model's scores before the argmax (ovgaussian.openvocab.class_offsets). Not with stacking_run."""
    faint_neighbours: int = 0
    """Blend each Gaussian's semantic vector with those of its this many nearest Gaussians (itself included), by its
    opacity, before scoring in 3D and rendering in 2D: an opaque one keeps its own, a faint one takes mostly its
    opaque neighbours' (ovgaussian.predict.faint_blend); 0 or 1: off. Applies to the model and every ensemble member,
    and to the train-split scores that class offsets are fitted on."""
    generative: bool = False
    """Open vocabulary, generative zero-shot synthesis: a generator learns text embedding -> feature on the seen classes of the train split, synthesizes unseen-class features, and a classifier retrained on real seen + synthetic unseen features scores (ovgaussian.openvocab.feature_synthesis)."""
    synthesis: SynthesisConfig = field(default_factory=SynthesisConfig)
    """Settings of the generative method."""
    metrics: tuple[str, ...] = METRICS
    """Metrics to compute (subset of CSA, OVA, NVA, CDA)."""
    dims: tuple[str, ...] = ("3d", "2d")
    """Dimensions to score: ``3d`` on the Gaussians, ``2d`` on rendered label maps."""
    num_classes: int = 20
    """Vocabulary size (20, 50 or 100): the 4 unseen classes plus the first num_classes - 4 other top-100 classes."""
    min_alpha: float = DEFAULT_MIN_ALPHA
    """Rendered pixels whose accumulated alpha is below this get no prediction (counted as a miss)."""
    blend_top_k: int = 16
    """Contributors kept per pixel in the blend weights W of M = W S."""
    max_views_per_scene: Optional[int] = None
    """Score at most this many views (of the metric's role) per scene, the first ones by name; None: all."""
    max_scenes: Optional[int] = None
    """Score at most this many scenes per split (the first ones by id); None: all."""
    chunk_rows: int = 65536
    """Gaussians or pixels decoded and classified at once (bounds the memory of phi's D-wide output)."""
    band_rows: int = DEFAULT_BAND_ROWS
    """Image rows whose blend weights are computed, rendered and classified at once (bounds the memory of a view)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device of the model."""
    progress: bool = True
    """Show a progress bar over scenes."""
    verify: bool = False
    """Check every shard read against the manifest's sha256 (sizes are always checked)."""
