"""Configuration of CPU 3D Gaussian Splatting fitting (``seggaussian.fit.optimize``), kept apart from the code.

Defaults follow the 3DGS reference (Kerbl et al. 2023, ``arguments/__init__.py``) with the schedule
shrunk from 30,000 iterations to a CPU budget: every iteration-valued field of the reference is scaled
by about ``iterations / 30000`` and noted in the field's docstring. To change the run length, use
``FitConfig().with_iterations(n)``, which scales the whole schedule; ``replace(config, iterations=n)``
alone keeps the 3,000-iteration schedule (a shorter run would then end mid-densification).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace


@dataclass(frozen=True)
class FitConfig:
    """How to fit Gaussians to a scene's posed images."""

    iterations: int = 3000
    """Optimization steps (one training view per step). 3DGS: 30,000."""

    downscale: float = 1.0
    """Images and intrinsics are divided by this factor before fitting (1 = full size)."""

    max_gaussians: int = 200_000
    """Hard cap on the number of Gaussians: densification stops adding once reached, and an
    initial point cloud above it is randomly subsampled (counted in the metrics)."""

    # --- initialization --------------------------------------------------------------------
    init_voxel_size: float = 0.04
    """Edge (metres) of the voxel grid the initial points are averaged on; 0 keeps every point."""

    init_opacity: float = 0.1
    """Opacity of every initial Gaussian (stored as a logit)."""

    init_knn: int = 3
    """Initial scale of a Gaussian = mean distance to this many nearest other points (3DGS: 3)."""

    sh_degree: int = 3
    """Largest SH degree fitted (and written to the PLY)."""

    sh_increase_every: int = 300
    """Raise the active SH degree by one every this many iterations. 3DGS: 1,000 of 30,000."""

    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour behind the Gaussians, RGB in [0, 1] (3DGS default: black)."""

    # --- optimizer (3DGS learning rates) -----------------------------------------------------
    lr_means_init: float = 1.6e-4
    """Initial learning rate of the means, multiplied by the scene extent."""

    lr_means_final: float = 1.6e-6
    """Final learning rate of the means (exponential decay over ``iterations``), times the extent."""

    lr_f_dc: float = 2.5e-3
    """Learning rate of the SH DC coefficients."""

    lr_f_rest: float = 2.5e-3 / 20.0
    """Learning rate of the higher SH coefficients (3DGS: f_dc / 20)."""

    lr_opacity: float = 0.05
    """Learning rate of the opacity logits (3DGS: 0.05 in the paper code, 0.025 in later versions)."""

    lr_scales: float = 5e-3
    """Learning rate of the log scales."""

    lr_quats: float = 1e-3
    """Learning rate of the quaternions."""

    lambda_dssim: float = 0.2
    """Loss = (1 - lambda) * L1 + lambda * (1 - SSIM)."""

    lambda_depth: float = 0.0
    """Weight of the depth term: mean relative error |D - D_mesh| / D_mesh of the rendered expected depth
    against the depth of the scene's mesh (raycast once per train view), over the pixels the mesh covers.
    0 (or a scene without a mesh) turns it off."""

    depth_until: int = 0
    """Last iteration of the depth term (0: the whole run). The term shapes the geometry early; the
    photometric loss alone then refines the appearance."""

    # --- densification and pruning -----------------------------------------------------------
    densify_from: int = 100
    """First iteration of densification. 3DGS: 500 of 30,000."""

    densify_until: int = 1800
    """Last iteration of densification. 3DGS: 15,000 of 30,000."""

    densify_every: int = 100
    """Densify and prune every this many iterations. 3DGS: 100."""

    densify_grad_threshold: float = 2e-4
    """Mean norm of the view-space (NDC) mean gradient above which a Gaussian is cloned or split."""

    percent_dense: float = 0.01
    """Gaussians whose largest scale is at most this fraction of the scene extent are cloned;
    larger ones are split."""

    split_count: int = 2
    """Children of a split Gaussian, each sampled from the parent Gaussian (3DGS: 2)."""

    split_scale_divisor: float = 1.6
    """Children of a split get the parent's scales divided by this (3DGS: 0.8 * 2 = 1.6)."""

    prune_opacity: float = 0.005
    """Gaussians with opacity below this are pruned."""

    prune_world_scale: float = 0.1
    """After the first opacity reset, Gaussians larger than this fraction of the extent are pruned."""

    prune_screen_size: float = 20.0
    """After the first opacity reset, Gaussians with a screen radius above this many pixels
    (at the processed image size) are pruned."""

    opacity_reset_every: int = 600
    """Clamp every opacity to ``opacity_reset_value`` this often. 3DGS: 3,000 of 30,000. A reset with fewer than this
    many iterations left in the run (under a time budget: at the pace of the latest iterations) is skipped, so a
    run never ends before its Gaussians are opaque again (counted in the metrics)."""

    opacity_reset_value: float = 0.01
    """Opacity ceiling after a reset."""

    opacity_reset: bool = False
    """Whether the opacity resets happen at all (3DGS: yes). Off by default: on these short CPU schedules a reset
    costs more held-out PSNR than it cleans up, and the run ends below its best (benchmarks/results/fit.md,
    "Opacity reset")."""

    # --- evaluation and early stop -------------------------------------------------------------
    eval_every: int = 250
    """Evaluate the held-out PSNR every this many iterations (0: never, no early stop)."""

    holdout_views: int = 0
    """Train views (evenly spaced) kept out of optimization for early stopping; 0 evaluates the
    early-stop criterion on the novel views instead."""

    eval_max_views: int = 4
    """At most this many evenly spaced views are rendered per evaluation (keeps evaluation cheap)."""

    patience: int = 4
    """Stop when the held-out PSNR has not improved by ``min_psnr_gain`` for this many evaluations
    (0 disables early stopping)."""

    min_psnr_gain: float = 0.05
    """Improvement in dB that counts as progress for early stopping."""

    time_budget_seconds: float = 0.0
    """Stop after this much wall time (0: no limit)."""

    keep_best: bool = True
    """Return the state with the best held-out PSNR seen at any evaluation (including a final one
    at the last iteration) instead of the last state."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def profile(cls) -> "FitConfig":
        """The fit of a profile room (``seggaussian synth --width 160``: 160x120 images, 14 train views) in
        about 37 s of one CPU core (36.5 s with 16 views, 38.6 s with 32), chosen by the sweep in benchmarks/results/fit.md: coarser initial voxels
        (fewer, larger Gaussians), opaque-ish initial Gaussians, depth supervision from the scene's mesh,
        a short schedule with densification up to a cap and no opacity reset (the default), SH degree 3 reached by
        two thirds of the run, the best evaluated state kept. The state is chosen on 2 train views held out of
        the optimization, never on the novel views the PSNR (and the benchmark's NVA) is reported on."""
        return cls(**PROFILE_SETTINGS)

    @classmethod
    def preset(cls, name: str) -> "FitConfig":
        """``default`` (``FitConfig()``) or ``profile`` (``FitConfig.profile()``)."""
        if name not in PRESETS:
            raise ValueError(f"fit preset must be one of {', '.join(PRESETS)}, got {name!r}")
        return cls.profile() if name == "profile" else cls()

    def with_iterations(self, iterations: int) -> "FitConfig":
        """This config with ``iterations`` changed and every iteration-valued schedule field
        (SH steps, densification window and interval, opacity resets, evaluation interval) scaled by
        the same factor, so that a shorter or longer fit keeps the shape of the schedule (densification
        still ends at 60 % of the run, leaving time to recover from the last opacity reset).
        ``densify_every`` is not scaled up or down freely: the gradient statistics need about as many
        views per densification round as in the default, so it only shrinks when the densification
        window would otherwise hold fewer than 3 rounds."""
        factor = iterations / self.iterations

        def scaled(value: int) -> int:
            return max(1, int(round(value * factor)))

        return replace(
            self, iterations=int(iterations), sh_increase_every=scaled(self.sh_increase_every),
            densify_from=scaled(self.densify_from), densify_until=scaled(self.densify_until),
            densify_every=max(1, min(self.densify_every, (scaled(self.densify_until) - scaled(self.densify_from)) // 3)),
            opacity_reset_every=scaled(self.opacity_reset_every),
            depth_until=scaled(self.depth_until) if self.depth_until else 0,
            eval_every=scaled(self.eval_every) if self.eval_every else 0,
        )

    def __post_init__(self) -> None:
        checks = {
            "iterations": self.iterations >= 1,
            "downscale": self.downscale >= 1.0,
            "max_gaussians": self.max_gaussians >= 1,
            "init_voxel_size": self.init_voxel_size >= 0.0,
            "init_opacity": 0.0 < self.init_opacity < 1.0,
            "init_knn": self.init_knn >= 1,
            "sh_degree": 0 <= self.sh_degree <= 3,
            "sh_increase_every": self.sh_increase_every >= 1,
            "lambda_dssim": 0.0 <= self.lambda_dssim <= 1.0,
            "densify_every": self.densify_every >= 1,
            "split_count": self.split_count >= 2,
            "split_scale_divisor": self.split_scale_divisor > 0.0,
            "opacity_reset_value": 0.0 < self.opacity_reset_value < 1.0,
            "eval_every": self.eval_every >= 0,
            "holdout_views": self.holdout_views >= 0,
            "eval_max_views": self.eval_max_views >= 1,
            "patience": self.patience >= 0,
            "time_budget_seconds": self.time_budget_seconds >= 0.0,
            "lambda_depth": self.lambda_depth >= 0.0,
            "depth_until": self.depth_until >= 0,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"FitConfig: invalid value for {', '.join(bad)}: "
                             + ", ".join(f"{n}={getattr(self, n)!r}" for n in bad))
        if len(self.background) != 3:
            raise ValueError(f"FitConfig: background must have 3 values, got {self.background!r}")


#: ``FitConfig.profile()``: the fields it changes from the defaults.
PROFILE_SETTINGS = dict(
    iterations=320, init_voxel_size=0.08, init_opacity=0.5, max_gaussians=30_000, sh_increase_every=64,
    densify_from=50, densify_until=200, densify_every=50, lambda_depth=0.1,
    eval_every=40, patience=0, holdout_views=2,
)
#: Names of ``FitConfig.preset``.
PRESETS = ("default", "profile")
