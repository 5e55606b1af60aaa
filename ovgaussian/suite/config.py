"""Configuration of the benchmark profile (``ovgaussian bench-suite``): the data, the schedule and the rows.

The profile's tables are lists of row specifications, so that a new method is one more line:

- :data:`TABLE1_ROWS`: Table 1. A row names a predictor (a baseline, or a model run of :data:`RUNS`) and the
  ``BenchConfig`` options it is scored with. The open-vocabulary methods of issue #16 (calibrated stacking,
  generative feature synthesis, prompt ensembles) each add one ``Table1Row`` scoring the ``full`` run with
  their bench option, e.g. ``Table1Row("full + prompt ensemble", run="full", options=(("prompt_ensemble", True),))``;
  calibrated stacking names its calibration run (``stacking_run="calibration"``).
  The transductive method (``LossConfig.unlabelled_as_unseen``) is a training switch: its own run of :data:`RUNS`
  and a plain row scoring it.
- :data:`ABLATION_ROWS`: the paper's Table 2 (switches added one at a time). Without local CLIP weights the
  visual-semantic loss is off in every run, so the "V-S" row is the "none" run and says so.

No code beyond data lives here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from seggaussian.fit.config import FitConfig


@dataclass(frozen=True)
class RunSpec:
    """One training run of the profile (its switches; the schedule is the suite's)."""

    name: str
    """Folder name under OUT/runs/."""
    use_adapter: bool = True
    """Voxel-to-point adapter on."""
    no_3dt_align: bool = False
    """3D-to-text cross-entropy off."""
    no_vs_align: bool = False
    """Visual-semantic (MaskCLIP) cosine loss off (it is off anyway without a local CLIP)."""
    holdout_classes: tuple[str, ...] = ()
    """Seen classes held out as pseudo-unseen (``DataConfig.holdout_classes``): the calibration run of calibrated
    stacking."""
    trained_on: Literal["splats", "oracle", "default-fit", "scan", "split"] = "splats"
    """Dataset the run trains on: the profile's splats, or the oracle Gaussians of the same rooms (the control of
    the 90 % check: what the method reaches when trained and scored on Gaussians sampled on the mesh), or one more
    rendition of the splat zoo (:data:`ZOO_RENDITIONS`)."""
    also_trains_on: tuple[Literal["default-fit", "oracle", "scan"], ...] = ()
    """More renditions of the same rooms each training sample draws its splat among (``DataConfig.renditions``): the
    splat zoo's recipe."""
    off_surface_augment: bool = False
    """Copies of a share of the Gaussians moved off their surfaces (``DataConfig.off_surface_augment``)."""
    colour_augment: bool = True
    """Scenes recoloured by a random hue turn, saturation and gain (``DataConfig.colour_augment``). Every run of the
    profile recolours: on the profile's fits it adds 23 % to the cross-domain 3D CDA (rooms with other floor and wall
    colours) and costs 5 % of the seen-domain 3D CSA (benchmarks/results/bench_suite.md, "What the colour augment
    does here")."""
    surface_radius: float = 0.0
    """The run places a labelled splat's Gaussians on its own surface first, with this reach in metres
    (``TrainConfig.surface_radius``)."""
    epochs_factor: int = 1
    """This run trains ``SuiteConfig.epochs`` times this many epochs: the splat zoo's recipe, whose samples are drawn
    among four renditions, trains three times the steps of a model trained on one (on the profile's rooms, twice
    left the default-preset fits at 0.84 of their matched model's 3D CSA; with three renditions, 30 epochs instead
    of 60 cost every CSA cell 4-7 points: benchmarks/results/bench_suite.md, "The splat zoo")."""
    unlabelled_as_unseen: bool = False
    """Transductive zero-shot: the unlabelled parts of the training rooms supervised as 'one of the unseen
    classes' (``LossConfig.unlabelled_as_unseen``)."""
    seed_offset: int = 0
    """Added to ``SuiteConfig.seed`` for this run's training seed (initial weights, scene order, samples): the
    members of an ensemble differ only in it."""


@dataclass(frozen=True)
class Table1Row:
    """One row of Table 1."""

    label: str
    """Row label."""
    predictor: Literal["model", "majority", "nearest-colour"] = "model"
    """What is scored (``BenchConfig.predictor``)."""
    run: Optional[str] = None
    """Name of the run of :data:`RUNS` scored (predictor ``model``)."""
    options: tuple[tuple[str, object], ...] = ()
    """Extra ``BenchConfig`` fields of this row (an open-vocabulary method's switch), as (field, value) pairs."""
    stacking_run: Optional[str] = None
    """Name of the calibration run of :data:`RUNS` whose gamma this row's calibrated stacking uses
    (``BenchConfig.stacking_run``)."""
    scored_on: Literal["splats", "oracle"] = "splats"
    """Which dataset of the same rooms the row is scored on: the profile's splats (``SuiteConfig.splats``) or
    Gaussians sampled on the labelled mesh (the control: what the same run reaches without a fit's defects)."""
    ensemble: tuple[str, ...] = ()
    """Names of more runs of :data:`RUNS` scored with ``run`` as one ensemble, their class scores averaged
    (``BenchConfig.ensemble_runs``): the same recipe trained with other seeds. Such rows are scored only with
    ``SuiteConfig.ensemble``."""
    fit_recipe: bool = False
    """The profile's method for fitted splats (issue #27): this row's pair with the control of the same method
    decides the 90 % check, and the other pairs are reported in its detail. Without this row in the profile
    (``--no-ensemble``) the full model's plain pair decides."""


@dataclass(frozen=True)
class AblationRow:
    """One row of the paper's Table 2."""

    vs_align: bool
    """Visual-semantic alignment asked for."""
    t3d_align: bool
    """3D-to-text alignment."""
    adapter: bool
    """Voxel-to-point adapter."""
    run: str
    """The run of :data:`RUNS` that trains this configuration here."""
    paper: tuple[float, float, float]
    """Paper Table 2 at K = 20 (3D CSA, 2D CSA, NVA), for comparison."""


#: Seen classes held out in the calibration run of calibrated stacking (data_specs/BENCHMARK.md's example): a
#: large, a medium and a small seen object class; the true unseen labels are never read.
CALIBRATION_HOLDOUT = ("table", "cabinet", "door")

#: The runs the tables need: the transductive run, the full model, the calibration run of calibrated stacking, the
#: full model's oracle control, a second training seed of the full model and of its control (the ensemble rows) and
#: the two ablation configurations that differ from the full model. Longest first: ``SuiteConfig.jobs`` of them
#: train at once.
RUNS = (
    RunSpec("transductive", unlabelled_as_unseen=True),
    RunSpec("full"),
    RunSpec("calibration", holdout_classes=CALIBRATION_HOLDOUT),
    RunSpec("full-seed1", seed_offset=1),
    RunSpec("full-oracle", trained_on="oracle"),
    RunSpec("full-oracle-seed1", trained_on="oracle", seed_offset=1),
    RunSpec("no-adapter", use_adapter=False),
    RunSpec("text-2d-only", use_adapter=False, no_3dt_align=True),
)

#: The runs of the splat zoo (``SuiteConfig.zoo``): the recipe for splats made any way (trained across the profile's
#: fits, default-preset fits, a scan and oracle Gaussians of the same rooms, with fit-like shells added, recoloured,
#: for three times the epochs, and placing a splat's Gaussians on its own surface where it labels one:
#: benchmarks/results/renditions.md and bench_suite.md; without the default-preset fits it reached 0.72 of their
#: matched model's 3D CSA), and one model per rendition trained on it alone, on the profile's schedule, recoloured as
#: every run of the profile is (so that a ratio to it measures the renditions, not the colour augment). The profile
#: fit's and the oracle Gaussians' matched runs are Table 1's ``full`` and ``full-oracle``.
ZOO_RUNS = (
    RunSpec("zoo", also_trains_on=("default-fit", "scan", "oracle"), off_surface_augment=True, surface_radius=0.15,
            epochs_factor=3),
    RunSpec("matched-default-fit", trained_on="default-fit"),
    RunSpec("matched-scan", trained_on="scan"),
    RunSpec("matched-split", trained_on="split"),
)


@dataclass(frozen=True)
class ZooRendition:
    """One rendition of the val and cross-domain rooms in the splat zoo."""

    name: Literal["splats", "default-fit", "oracle", "scan", "split"]
    """Which dataset (``splats``: the profile's own fits; the others: :func:`ovgaussian.suite.zoo.zoo_datasets`)."""
    label: str
    """Column label."""
    matched_run: str
    """The run (of :data:`RUNS` or :data:`ZOO_RUNS`) trained on this rendition alone."""
    recipe_trains: bool
    """Whether the zoo's recipe trains on this rendition."""
    min_share: float
    """Least share of the matched model's score the recipe must reach (issue #54: 0.85, 0.8 where never trained)."""


#: The splat zoo's renditions (issue #54, item 3), in column order.
ZOO_RENDITIONS = (
    ZooRendition("splats", "profile fit", "full", True, 0.85),
    ZooRendition("default-fit", "default-preset fit", "matched-default-fit", True, 0.85),
    ZooRendition("oracle", "oracle Gaussians", "full-oracle", True, 0.85),
    ZooRendition("scan", "scan (a Gaussian per vertex)", "matched-scan", True, 0.85),
    ZooRendition("split", "split fit (never trained)", "matched-split", False, 0.80),
)

#: Table 1: both non-learned baselines, the full model, then one line per open-vocabulary method (#16a), the oracle
#: controls of issue #27 (each method on fitted splats beside the same method trained and scored on oracle
#: Gaussians), and the two-seed ensembles (opt-in, ``SuiteConfig.ensemble``). The ensemble rows are opt-in because the
#: single run's pair clears the 90 % check with its whole interval since the transfer leaves out surfaces no view
#: sees; without them, the full model's plain pair decides the check (benchmarks/results/bench_suite.md,
#: "The 90 % check").
TABLE1_ROWS = (
    Table1Row("majority (baseline)", predictor="majority"),
    Table1Row("nearest-colour (baseline)", predictor="nearest-colour"),
    Table1Row("OVGaussian (full)", run="full"),
    Table1Row("full + prompt ensemble", run="full", options=(("prompt_ensemble", True),)),
    Table1Row("full + generative synthesis", run="full", options=(("generative", True),)),
    Table1Row("full + calibrated stacking", run="full", stacking_run="calibration"),
    Table1Row("transductive (unlabelled as unseen)", run="transductive"),
    Table1Row("control: full trained and scored on oracle Gaussians", run="full-oracle", scored_on="oracle"),
    Table1Row("full (fitted splats), scored on oracle Gaussians", run="full", scored_on="oracle"),
    Table1Row("full + class offsets", run="full", options=(("class_offsets", True),)),
    Table1Row("control + class offsets", run="full-oracle", options=(("class_offsets", True),), scored_on="oracle"),
    Table1Row("full, 2 training seeds (ensemble)", run="full", ensemble=("full-seed1",)),
    Table1Row("control, 2 training seeds (ensemble)", run="full-oracle", ensemble=("full-oracle-seed1",),
              scored_on="oracle"),
    Table1Row("full, 2 training seeds + class offsets", run="full", ensemble=("full-seed1",),
              options=(("class_offsets", True),), fit_recipe=True),
    Table1Row("control, 2 training seeds + class offsets", run="full-oracle", ensemble=("full-oracle-seed1",),
              options=(("class_offsets", True),), scored_on="oracle"),
)

#: Table 2 of the paper at K = 20, top to bottom.
ABLATION_ROWS = (
    AblationRow(False, False, False, "text-2d-only", (32.18, 37.15, 56.35)),
    AblationRow(True, False, False, "text-2d-only", (34.57, 40.17, 57.71)),
    AblationRow(True, True, False, "no-adapter", (40.55, 43.70, 67.55)),
    AblationRow(True, True, True, "full", (43.84, 45.76, 69.51)),
)


@dataclass(frozen=True)
class SuiteConfig:
    """The benchmark profile: synthetic rooms, one schedule for every run, every Table-1 and Table-2 row."""

    out: Path = Path("out/bench-suite")
    """Folder of everything the profile writes (raw rooms, dataset, runs, reports, tables); finished stages
    found there are reused."""
    scenes: int = 56
    """ScanNet++-layout rooms (split train:val by ``val_ratio``)."""
    replica_scenes: int = 16
    """Replica-layout rooms (the cross-domain set). 16, not the paper's 8: with 8 the 2D CDA intervals of the
    model and nearest colour touched; 16 tell them apart (benchmarks/results/bench_suite.md, "The whiteboard fix and
    16 cross-domain rooms")."""
    val_ratio: tuple[int, int] = (4, 1)
    """train:val ratio of the ScanNet++-layout rooms."""
    width: int = 160
    """Image width of the synthetic views (height 3/4 of it)."""
    views: int = 32
    """Views per room (ScanNet++ rooms: a quarter of them are novel views for NVA). 32, not 16: a room's fit
    (``FitConfig.profile``) gains 1.1 dB novel-view PSNR at the same CPU cost (benchmarks/results/fit.md)."""
    splats: Literal["fit", "oracle"] = "fit"
    """What every run trains on and every row (but the control) is scored on: ``fit``, 3DGS fitted to each room's
    images on the CPU (``fit``), as users bring scenes; ``oracle``, Gaussians sampled on the labelled mesh."""
    fit: FitConfig = field(default_factory=FitConfig.profile)
    """How each room is fitted (``FitConfig.profile``: the schedule measured for these rooms in
    benchmarks/results/fit.md)."""
    gaussians: int = 40000
    """Oracle Gaussians sampled per room (the oracle dataset: the control row, or everything with
    ``splats="oracle"``)."""
    epochs: int = 30
    """Epochs of every run (30 x 15 steps of 3 rooms; one schedule for all runs). What the profile from nothing
    takes with it, the 72 room fits and the four trainings included, why 30 and not 45, and what 45 buys:
    benchmarks/results/bench_suite.md, "The profile from nothing"."""
    batch_scenes: int = 3
    """Scenes per optimizer step."""
    pixels_per_view: int = 4096
    """Pixels sampled per view for the 2D losses."""
    loss_gaussians: Optional[int] = 15000
    """Gaussians drawn per room for each step's 3D-to-text loss (``DataConfig.loss_gaussians``; None, or 0 on the
    command line: every Gaussian). The network still voxelizes every Gaussian; the adapter, head and 3D loss run on
    the drawn ones and the sampled pixels' contributors. With 15,000 the profile's trainings took 16-19 % less CPU on
    the fitted rooms (about 30,000 Gaussians) and 26 % less on the oracle rooms (40,000), and the profile from
    nothing fits its 75 minutes; 2,048 learned less (benchmarks/results/bench_suite.md, "The profile from nothing"
    and "What moved the fitted score")."""
    scene_cache_size: int = 64
    """Prepared rooms each training keeps in memory (``DataConfig.scene_cache_size``): at least the train split,
    so a room is read and decoded from the shards once per run, not once per epoch (0.07 s CPU a room, three rooms a
    step: a tenth of a step's cost here). With the profile's 45 train rooms a training process held about 2.7 GB."""
    lr: float = 0.05
    """Initial SGD learning rate (cosine decay)."""
    model_preset: Literal["default", "slim"] = "slim"
    """Network widths."""
    voxel_size: float = 0.1
    """Voxel edge in metres of the network's finest level."""
    use_coordinates: bool = True
    """Give the network the normalized Gaussian positions."""
    voxel_geometry: bool = False
    """Give the backbone how each voxel's Gaussians lie inside it (``OVGaussianNetConfig.voxel_geometry``: the
    centres' mean offset and covariance). What it changed on the profile's rooms, and why it is off:
    benchmarks/results/bench_suite.md, "What moved the fitted score"."""
    class_balance: float = 0.75
    """Exponent of the class weights of the text cross-entropies (``LossConfig.class_balance``); why 0.75 and not
    0.5 or 1.0: benchmarks/results/bench_suite.md, "Whiteboard, the class balance and the open-vocabulary
    settings"."""
    lovasz_weight: float = 1.0
    """Weight of the Lovasz-softmax term (an IoU surrogate) of the 3D-to-text loss of every run
    (``LossConfig.lovasz_weight``), beside the cross-entropy of weight 1, as Pointcept's PTv3 configs for ScanNet
    train; 0: cross-entropy only. Its effect on fitted splats and on the oracle control:
    benchmarks/results/bench_suite.md, "What moved the fitted score"."""
    opacity_power: float = 0.0
    """Exponent p of the opacity^p weights of each Gaussian's 3D-to-text cross-entropy term in every run
    (``LossConfig.opacity_power``); 0: every Gaussian alike. The oracle Gaussians share one opacity, so the control
    runs do not change with it. Its effect on the profile: benchmarks/results/bench_suite.md, "What moved the fitted
    score"."""
    num_classes: int = 20
    """Vocabulary size K."""
    max_views: int = 4
    """Views scored per scene in 2D."""
    ablation: bool = False
    """Also train and score the Table-2 runs (two more trainings; opt-in because the profile's 72 fits already
    lengthen it: its time with them is not yet measured on a quiet machine)."""
    ensemble: bool = False
    """Also train the full model and its oracle control with a second seed (``seed`` + 1) and score the Table-1
    rows of the two-seed ensemble, whose pair with class offsets then decides the 90 % check (two more trainings and
    four rows; what they cost and why they are opt-in: benchmarks/results/bench_suite.md, "Training seeds")."""
    zoo: bool = False
    """Also score the splat zoo (issue #54; ``ovgaussian.suite.zoo``): the val and cross-domain rooms in five
    renditions (the profile fit, a default-preset fit, oracle Gaussians, a scan, the fit split in two), the recipe
    trained across renditions against a model trained on each rendition alone and both baselines. Opt-in: a
    default-preset fit of every room and four more trainings, the profile fit's and the oracle's matched runs being
    Table 1's ``full`` and ``full-oracle`` (what it costs: benchmarks/results/bench_suite.md, "The splat zoo")."""
    zoo_fit_iterations: int = 600
    """Iterations of each room's default-preset fit in the zoo (``FitConfig()`` with its schedule, stopped there
    with its last state: five densification rounds. At 500, one of 13 val and cross-domain rooms held 96,937
    Gaussians; at 600 the two smallest hold 106,518 and 110,783, benchmarks/results/bench_suite.md, "The splat zoo").
    An iteration count, unlike a time budget, fits the same splat on any machine."""
    jobs: int = 2
    """Processes working at once: scenes of the build, then training runs and bench rows, a row once the runs it
    scores are done (each process with cpu_count // jobs torch and numba threads)."""
    bootstrap_draws: int = 2000
    """Bootstrap draws per interval."""
    seed: int = 0
    """Seed of the rooms, the split and every run."""
    progress: bool = True
    """Print a line per stage."""
