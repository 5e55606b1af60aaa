"""The trainable Gaussians of a fit: per-Gaussian tensors, their Adam state and densification statistics,
kept row-aligned (``GaussianParameters``), and their differentiable render in one view.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from seggaussian import render
from seggaussian.core.constants import QUAT_NORM_EPS
from seggaussian.fit.config import FitConfig
from seggaussian.fit.views import ViewData
from seggaussian.core.gaussians import Gaussians

if TYPE_CHECKING:
    import torch

#: Floor of an opacity before taking its logit (keeps the logit finite).
OPACITY_LOGIT_EPS = 1e-6
#: Adam's denominator epsilon (3DGS: 1e-15); the moments of Gaussians outside every view stay 0 and
#: their update 0/(0 + eps) = 0.
ADAM_EPS = 1e-15
PARAMETER_NAMES = ("means", "quats", "log_scales", "opacity_logits", "f_dc", "f_rest")


class GaussianParameters:
    """The trainable per-Gaussian tensors, their Adam optimizer and the densification statistics,
    kept row-aligned by ``select`` and ``append``."""

    def __init__(self, gaussians: Gaussians, config: FitConfig, extent: float):
        import torch

        t = gaussians.to_torch()
        values = {
            "means": t["means"], "quats": t["quats"], "log_scales": t["log_scales"],
            "opacity_logits": t["opacity_logits"], "f_dc": t["sh"][:, :1], "f_rest": t["sh"][:, 1:],
        }
        lrs = {
            "means": config.lr_means_init * extent, "quats": config.lr_quats, "log_scales": config.lr_scales,
            "opacity_logits": config.lr_opacity, "f_dc": config.lr_f_dc, "f_rest": config.lr_f_rest,
        }
        self.params = {name: torch.nn.Parameter(values[name].clone().contiguous()) for name in PARAMETER_NAMES}
        self.optimizer = torch.optim.Adam(
            [{"params": [self.params[name]], "lr": lrs[name], "name": name} for name in PARAMETER_NAMES],
            lr=0.0, eps=ADAM_EPS, fused=True,
        )
        self.stats = {}
        self.reset_stats()

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def reset_stats(self) -> None:
        import torch

        n = len(self)
        self.stats = {
            "grad_accum": torch.zeros(n),  # summed view-space gradient norm
            "grad_count": torch.zeros(n),  # views in which the Gaussian was visible
            "max_radius": torch.zeros(n),  # largest screen radius in pixels
        }

    def sh(self) -> "torch.Tensor":
        import torch

        return torch.cat([self.params["f_dc"], self.params["f_rest"]], dim=1)

    def set_lr(self, name: str, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def _swap(self, name: str, new_value: "torch.Tensor", new_state: dict | None) -> None:
        import torch

        old = self.params[name]
        param = torch.nn.Parameter(new_value.contiguous())
        state = self.optimizer.state.pop(old, None)
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["params"][0] = param
        if state is not None and new_state is not None:
            state = dict(state)
            state.update(new_state)
            self.optimizer.state[param] = state
        self.params[name] = param

    def select(self, index: "torch.Tensor") -> None:
        """Keep the Gaussians ``index`` (bool mask or int64 rows) in every tensor and Adam state."""
        for name in PARAMETER_NAMES:
            old = self.params[name]
            state = self.optimizer.state.get(old)
            new_state = None
            if state:
                new_state = {key: state[key][index].clone() for key in ("exp_avg", "exp_avg_sq")}
            self._swap(name, old.detach()[index].clone(), new_state)
        self.stats = {key: value[index].clone() for key, value in self.stats.items()}

    def append(self, values: dict) -> None:
        """Add Gaussians (``values[name]`` rows for every parameter) with zero Adam moments and stats."""
        import torch

        count = int(values["means"].shape[0])
        for name in PARAMETER_NAMES:
            old = self.params[name]
            state = self.optimizer.state.get(old)
            new_state = None
            if state:
                new_state = {key: torch.cat([state[key], torch.zeros_like(values[name])], dim=0)
                             for key in ("exp_avg", "exp_avg_sq")}
            self._swap(name, torch.cat([old.detach(), values[name].detach()], dim=0), new_state)
        self.stats = {key: torch.cat([value, torch.zeros(count, dtype=value.dtype)]) for key, value in self.stats.items()}

    def replace(self, name: str, value: "torch.Tensor") -> None:
        """Set parameter ``name`` to ``value`` and zero its Adam moments (opacity reset)."""
        import torch

        old = self.params[name]
        state = self.optimizer.state.get(old)
        new_state = None
        if state:
            new_state = {key: torch.zeros_like(state[key]) for key in ("exp_avg", "exp_avg_sq")}
        self._swap(name, value.detach().clone(), new_state)

    def snapshot(self) -> dict:
        """A detached copy of every parameter tensor (what ``restore`` takes back)."""
        return {name: self.params[name].detach().clone() for name in PARAMETER_NAMES}

    def restore(self, snapshot: dict) -> None:
        """Set every parameter to ``snapshot``'s copy; Adam moments and densification statistics start afresh."""
        for name in PARAMETER_NAMES:
            self._swap(name, snapshot[name].clone(), None)
        self.reset_stats()

    def to_gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians.from_arrays(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], self.sh())


def normalized(quats: "torch.Tensor") -> "torch.Tensor":
    return quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_NORM_EPS)


def render_view(params: GaussianParameters, view: ViewData, sh_degree: int, background: "torch.Tensor"):
    """RenderOutput of the current Gaussians in ``view`` (differentiable)."""
    p = params.params
    return render.rasterize(
        p["means"], normalized(p["quats"]), p["log_scales"], p["opacity_logits"].reshape(-1),
        view.viewmat, view.K, view.camera.width, view.camera.height,
        sh=params.sh(), sh_degree=sh_degree, background=background,
    )
