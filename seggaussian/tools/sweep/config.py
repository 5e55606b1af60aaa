"""Configuration of the stage sweeps (``seggaussian.tools.sweep.run``; CLI ``seggaussian bench --stage``), kept
apart from code.

Each stage's sweep is one-knob-at-a-time around a base setting: the base row (every knob at its base
value) plus one row per other value of each knob. In a full run the base is the shipped default of the
stage's own config (``FitConfig``, ``TransferConfig``, ``ViewConfig``, ``BuildConfig``), so the shipped
default is always one of the measured rows; ``--quick`` shrinks scenes, images and grids to seconds.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

from seggaussian.fit.config import FitConfig

STAGES = ("fit", "transfer", "render", "build")

Stage = Literal["fit", "transfer", "render", "build"]


@dataclass(frozen=True)
class FitSweep:
    """Knobs of ``fit_scene`` swept by the fit sweep (each tuple lists the values tried)."""

    iterations: tuple[int, ...] = (300, 1000, 3000)
    """``FitConfig.iterations`` values."""
    downscale: tuple[float, ...] = (1.0, 2.0, 4.0)
    """``FitConfig.downscale`` values (images divided by this before fitting)."""
    max_gaussians: tuple[int, ...] = (20_000, 50_000, 200_000)
    """``FitConfig.max_gaussians`` values."""
    patience: tuple[int, ...] = (0, 2, 4)
    """``FitConfig.patience`` values (0 = no early stop)."""
    preset: str = "default"
    """``FitConfig.preset`` the rows start from: ``default`` (``FitConfig()``) or ``profile``
    (``FitConfig.profile()``, the ~30 s CPU fit of a 160x120 profile room)."""
    base: dict = field(default_factory=dict)
    """Overrides of the preset used as the base of every fit row ({} = the preset as shipped)."""
    eval_scale: float = 1.0
    """Novel views are scored at this share of the source image size, whatever the fit's downscale."""


@dataclass(frozen=True)
class TransferSweep:
    """Knobs of the label transfer swept by the transfer sweep."""

    candidates: tuple[str, ...] = ("all", "labelled")
    """``TransferConfig.candidates`` values (``all`` = unlabelled points keep ignore; ``labelled`` = the rule
    before 2026-11, labels spill onto unlabelled surfaces within the gate)."""
    backend: tuple[str, ...] = ("scipy", "open3d")
    """Nearest-neighbour backends (``TransferConfig.backend``)."""
    vote_k: tuple[int, ...] = (1, 3, 5)
    """1 = the shipped nearest-point transfer; k > 1 = majority vote of the k nearest candidates
    within the gate (ties go to the nearest), ``transfer_vote.transfer_labels_vote``, on the same KD-tree."""
    point_fraction: tuple[float, ...] = (1.0, 0.5, 0.25)
    """Share of the labelled points kept (seeded random subsample after mesh densification)."""
    mesh_sample_spacing: tuple[float, ...] = (0.0, 0.015, 0.03)
    """``TransferConfig.mesh_sample_spacing`` values (metres; 0 = vertices only)."""
    gate_factor: tuple[float, ...] = (2.0, 4.0, 8.0)
    """``TransferConfig.gate_factor`` values (gate = factor x median point spacing)."""
    gate_min: tuple[float, ...] = (0.01, 0.02, 0.05)
    """``TransferConfig.gate_min`` values (metres; lower bound of the derived gate)."""
    base: dict = field(default_factory=dict)
    """Overrides of the base row's knobs ({} = the shipped ``TransferConfig`` with k = 1 and every point)."""
    num_gaussians: int = 40_000
    """Oracle Gaussians per scene (``OracleConfig.num_gaussians``): they carry their true label."""
    surface_noise: float = 0.01
    """Standard deviation (metres) of a seeded offset of every oracle centre along its surface normal:
    fitted Gaussians sit a few cm off the mesh, oracle samples exactly on it."""
    repeats: int = 1
    """Each row is timed this many times; the median is reported."""


@dataclass(frozen=True)
class RenderSweep:
    """Knobs of blend weights and label maps swept by the render sweep."""

    scale: tuple[float, ...] = (0.25, 0.5, 1.0)
    """Image size as a share of the view's stored size (``ViewConfig.image_scale``)."""
    top_k: tuple[int, ...] = (1, 4, 8, 16, 32)
    """``ViewConfig.top_k`` values (contributors kept per pixel)."""
    min_alpha: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
    """``ViewConfig.min_alpha`` values (label maps: IGNORE below this accumulated alpha)."""
    vote: tuple[str, ...] = ("ignore_occludes", "labelled_only")
    """Label-map vote: ``ignore_occludes`` (shipped: ignore is a label of its own) or ``labelled_only`` (the
    rule before 2026-11, replayed by moving unlabelled contributors' weight into the residual alpha)."""
    reference_width: int = 32
    """The reference (per-pixel torch) path is run only at this image width (it is O(N x pixels)); the
    fast path is run at the same width next to it for comparison."""
    num_gaussians: int = 40_000
    """Oracle Gaussians per scene, labelled with their true class."""
    views: int = 4
    """Views rendered per scene (evenly spaced over the scene's views)."""
    feature_dim: int = 8
    """Channels of the random features used for the feature-render residual."""
    repeats: int = 1
    """Each row is timed this many times; the median is reported."""


@dataclass(frozen=True)
class BuildSweep:
    """Settings of ``build_dataset`` swept by the build sweep (oracle Gaussians: fitting is swept apart)."""

    jobs: tuple[int, ...] = (1, 2)
    """``BuildConfig.jobs`` values."""
    executors: tuple[str, ...] = ("local", "ray")
    """``BuildConfig.executor`` values; ``ray`` rows are skipped (and said so) when Ray is missing."""
    cache: tuple[bool, ...] = (False, True)
    """False = a fresh dataset folder; True = an unchanged rerun on the folder the first build wrote."""
    num_gaussians: int = 40_000
    """``OracleConfig.num_gaussians`` of the swept builds."""
    max_image_side: int = 640
    """``ViewConfig.max_image_side`` of the swept builds (shipped default 640)."""


@dataclass(frozen=True)
class StageSweepConfig:
    """One ``seggaussian bench --stage ...`` run."""

    stage: Stage
    """Which stage to sweep: ``fit``, ``transfer``, ``render`` or ``build``."""
    data: Path | None = None
    """Raw tree (ScanNet++ or Replica layout, or a synthetic root holding ``scannetpp/`` and
    ``replica/``); None = the default synthetic set, synthesized into ``work_dir`` on first use."""
    work_dir: Path = Path("~/.cache/seggaussian-bench")
    """Scratch folder (``~`` expanded): synthesized scenes, Replica view renders, swept build datasets."""
    scenes: int = 0
    """Use at most this many scenes (0 = all; the first ones in discovery order)."""
    synthetic_counts: tuple[int, int] = (9, 3)
    """Default synthetic set: scenes per layout (ScanNet++, Replica), as ``BuildConfig.synthetic_counts``."""
    synthetic_width: int = 320
    """Image width of the synthesized scenes (``SynthConfig.width``)."""
    synthetic_views: int = 32
    """Views per synthesized scene (``SynthConfig.num_views``)."""
    synthetic_max_edge: float = 0.06
    """Longest mesh edge of the synthesized scenes in metres (``SynthConfig.max_edge``)."""
    seed: int = 0
    """Seed of synthesis, oracle sampling, subsampling, noise and fitting."""
    quick: bool = False
    """Tiny sweep for tests (set by ``quick_config``)."""
    fit: FitSweep = field(default_factory=FitSweep)
    transfer: TransferSweep = field(default_factory=TransferSweep)
    render: RenderSweep = field(default_factory=RenderSweep)
    build: BuildSweep = field(default_factory=BuildSweep)

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise ValueError(f"stage sweep: stage must be one of {', '.join(STAGES)}, got {self.stage!r}")
        if self.scenes < 0:
            raise ValueError(f"stage sweep: scenes must be >= 0, got {self.scenes}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["data"] = None if self.data is None else str(self.data)
        d["work_dir"] = str(self.work_dir)
        return d


def _coerce(text: str, like):
    """``text`` parsed as the type of ``like`` (bool, int, float or str)."""
    if isinstance(like, bool):
        if text.lower() not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
            raise ValueError(f"expected a boolean, got {text!r}")
        return text.lower() in ("true", "1", "yes", "on")
    if isinstance(like, int):
        return int(text)
    if isinstance(like, float):
        return float(text)
    return text


def with_params(config: StageSweepConfig, params: tuple[str, ...] = (), base: tuple[str, ...] = ()) -> StageSweepConfig:
    """Override fields of the stage's sweep: ``params`` as ``NAME=V1,V2`` (tuple fields) or ``NAME=V`` (scalars);
    ``base`` as ``NAME=V`` entries of the sweep's ``base`` dict (fit: any ``FitConfig`` field; transfer: a
    swept knob). ValueError naming the option for unknown names or unparsable values."""
    sweep = getattr(config, config.stage)
    changes: dict = {}
    for item in params:
        name, sep, text = item.partition("=")
        if not sep or not hasattr(sweep, name) or name == "base":
            raise ValueError(f"--param {item!r}: expected NAME=VALUE with NAME a field of {type(sweep).__name__}")
        current = getattr(sweep, name)
        try:
            if isinstance(current, tuple):
                like = current[0] if current else ("" if name in ("backend", "executors") else 0.0)
                changes[name] = tuple(_coerce(v, like) for v in text.split(",") if v != "")
            else:
                changes[name] = _coerce(text, current)
        except ValueError as exc:
            raise ValueError(f"--param {item!r}: {exc}") from None
    if base:
        if not hasattr(sweep, "base"):
            raise ValueError(f"--base: the {config.stage} sweep has no base overrides")
        merged = dict(sweep.base)
        defaults = FitConfig() if config.stage == "fit" else None
        for item in base:
            name, sep, text = item.partition("=")
            like = getattr(defaults, name, None) if defaults is not None else None
            if not sep or (defaults is not None and not hasattr(defaults, name)):
                raise ValueError(f"--base {item!r}: expected NAME=VALUE with NAME a FitConfig field")
            try:
                merged[name] = _coerce(text, like if like is not None else _guess(text))
            except ValueError as exc:
                raise ValueError(f"--base {item!r}: {exc}") from None
        changes["base"] = merged
    return replace(config, **{config.stage: replace(sweep, **changes)}) if changes else config


def _guess(text: str):
    for kind in (int, float):
        try:
            kind(text)
            return kind()
        except ValueError:
            pass
    return ""


#: FitConfig overrides of the quick fit base: a few iterations on tiny images, densifying early.
QUICK_FIT_BASE = {
    "iterations": 16, "eval_every": 4, "densify_from": 4, "densify_until": 8, "densify_every": 4,
    "opacity_reset_every": 1000, "max_gaussians": 2000, "init_voxel_size": 0.05, "sh_degree": 0,
}


def quick_config(stage: Stage, **overrides) -> StageSweepConfig:
    """A sweep that runs in seconds on one tiny synthetic scene (used by the tests and ``--quick``)."""
    config = StageSweepConfig(
        stage=stage, scenes=1, synthetic_counts=(1, 0), synthetic_width=48, synthetic_views=8,
        synthetic_max_edge=0.25, quick=True,
        fit=FitSweep(iterations=(8, 16), downscale=(1.0, 2.0), max_gaussians=(500, 2000), patience=(0, 1),
                     base=dict(QUICK_FIT_BASE)),
        transfer=TransferSweep(backend=("scipy", "open3d"), vote_k=(1, 3), point_fraction=(1.0, 0.5),
                               mesh_sample_spacing=(0.0, 0.1), gate_factor=(2.0, 4.0), gate_min=(0.02,),
                               num_gaussians=2000,
                               repeats=1, base={"mesh_sample_spacing": 0.1}),
        render=RenderSweep(scale=(0.5, 1.0), top_k=(2, 16), min_alpha=(0.3, 0.5), reference_width=12,
                           vote=("ignore_occludes", "labelled_only"),
                           num_gaussians=1500, views=1),
        build=BuildSweep(jobs=(1,), executors=("local",), cache=(False, True), num_gaussians=1000,
                         max_image_side=48),
    )
    return replace(config, **overrides)
