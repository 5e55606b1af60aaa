"""The one in-memory type for a 3D Gaussian Splatting scene.

Numpy on the data side (what files hold), with a cheap conversion to torch tensors for rendering and
training. Parametrization follows the Inria 3DGS files: quaternions ``w,x,y,z`` as stored (not assumed
unit), scales as logs, opacity as logits, colour as real spherical-harmonic coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Mapping

import numpy as np

from seggaussian.core.constants import MAX_SH_DEGREE, QUAT_NORM_EPS, SH_C0
from seggaussian.core.rotations import quats_to_rotmats

if TYPE_CHECKING:  # torch is heavy: imported only where tensors are asked for
    import torch


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    """SH degree d such that (d + 1)^2 == num_coeffs; ValueError otherwise."""
    degree = int(round(np.sqrt(num_coeffs))) - 1
    if degree < 0 or (degree + 1) ** 2 != num_coeffs or degree > MAX_SH_DEGREE:
        raise ValueError(
            f"{num_coeffs} SH coefficients per channel is not (d+1)^2 for a degree d in 0..{MAX_SH_DEGREE}"
        )
    return degree


@dataclass(frozen=True, eq=False)
class Gaussians:
    """N Gaussians. Arrays are float32 unless noted; ``extras`` holds named per-Gaussian columns.

    Fields:
        means: ``[N, 3]`` centres, world frame, metres.
        quats: ``[N, 4]`` rotations as stored, order ``w, x, y, z``; normalized on use.
        log_scales: ``[N, 3]`` natural logs of the per-axis standard deviations.
        opacity_logits: ``[N]`` logits of the opacity (opacity = sigmoid(logit)).
        sh: ``[N, K, 3]`` SH coefficients, K = (degree + 1)^2; ``sh[:, 0]`` is ``f_dc``.
        extras: named ``[N]`` (or ``[N, ...]``) columns such as ``semantic``, ``instance``,
            ``transfer_distance``; any dtype.
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    extras: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "log_scales": (self.log_scales, (n, 3)),
            "opacity_logits": (self.opacity_logits, (n,)),
        }
        for name, (array, shape) in expected.items():
            if not isinstance(array, np.ndarray):
                raise TypeError(f"Gaussians.{name} must be a numpy array, got {type(array).__name__}")
            if array.shape != shape or n < 0:
                raise ValueError(f"Gaussians.{name} has shape {array.shape}, expected {shape}")
            if array.dtype != np.float32:
                raise TypeError(f"Gaussians.{name} has dtype {array.dtype}, expected float32")
        if not isinstance(self.sh, np.ndarray) or self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh has shape {getattr(self.sh, 'shape', None)}, expected ({n}, num_sh_coeffs, 3)")
        if self.sh.dtype != np.float32:
            raise TypeError(f"Gaussians.sh has dtype {self.sh.dtype}, expected float32")
        sh_degree_from_coeffs(self.sh.shape[1])
        for name, column in self.extras.items():
            if not isinstance(column, np.ndarray) or column.ndim < 1 or column.shape[0] != n:
                raise ValueError(
                    f"Gaussians.extras[{name!r}] has shape {getattr(column, 'shape', None)}, expected ({n}, ...)"
                )
        object.__setattr__(self, "extras", dict(self.extras))

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        means,
        quats,
        log_scales,
        opacity_logits,
        sh,
        extras: Mapping[str, np.ndarray] | None = None,
    ) -> "Gaussians":
        """Build from array-likes (numpy or torch), casting the attributes to float32."""

        def as_f32(x) -> np.ndarray:
            if hasattr(x, "detach"):
                x = x.detach().cpu().numpy()
            return np.ascontiguousarray(np.asarray(x, dtype=np.float32))

        sh = as_f32(sh)
        if sh.ndim == 2:  # colours given as DC only: [N, 3]
            sh = sh[:, None, :]
        return cls(as_f32(means), as_f32(quats), as_f32(log_scales), as_f32(opacity_logits).reshape(-1), sh,
                   dict(extras or {}))

    @classmethod
    def empty(cls, sh_degree: int = 0) -> "Gaussians":
        k = (sh_degree + 1) ** 2
        z = lambda *s: np.zeros(s, np.float32)  # noqa: E731
        return cls(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, k, 3))

    # --- sizes -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_sh_coeffs(self) -> int:
        return int(self.sh.shape[1])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    # --- derived values ----------------------------------------------------------------------
    def normalized_quats(self) -> np.ndarray:
        """``[N, 4]`` unit quaternions (w, x, y, z); zero-norm rows become the identity ``(1,0,0,0)``.

        Zero-norm rows are reported by import validation; this method never returns NaN.
        """
        norms = np.linalg.norm(self.quats.astype(np.float64), axis=1, keepdims=True)
        out = np.where(norms > QUAT_NORM_EPS, self.quats / np.maximum(norms, QUAT_NORM_EPS), 0.0)
        out[norms[:, 0] <= QUAT_NORM_EPS, 0] = 1.0
        return out.astype(np.float32)

    def scales(self) -> np.ndarray:
        """``[N, 3]`` per-axis standard deviations, ``exp(log_scales)``."""
        return np.exp(self.log_scales)

    def opacities(self) -> np.ndarray:
        """``[N]`` opacities in (0, 1), ``sigmoid(opacity_logits)``, computed without overflow."""
        x = self.opacity_logits.astype(np.float64)
        return (0.5 * (1.0 + np.tanh(0.5 * x))).astype(np.float32)

    def dc_colors(self) -> np.ndarray:
        """``[N, 3]`` view-independent colours ``0.5 + SH_C0 * f_dc`` (not clamped)."""
        return 0.5 + SH_C0 * self.sh[:, 0, :]

    def rotation_matrices(self) -> np.ndarray:
        """``[N, 3, 3]`` rotation matrices of the normalized quaternions."""
        return quats_to_rotmats(self.normalized_quats())

    def covariances(self) -> np.ndarray:
        """``[N, 3, 3]`` world-frame covariances ``R diag(s^2) R^T``."""
        r = self.rotation_matrices().astype(np.float64)
        m = r * self.scales().astype(np.float64)[:, None, :]
        return np.einsum("nij,nkj->nik", m, m).astype(np.float32)

    # --- editing -----------------------------------------------------------------------------
    def subset(self, index) -> "Gaussians":
        """Gaussians selected by a boolean mask or integer index array, extras included."""
        return Gaussians(
            self.means[index], self.quats[index], self.log_scales[index], self.opacity_logits[index],
            self.sh[index], {k: v[index] for k, v in self.extras.items()},
        )

    def with_extras(self, **columns: np.ndarray) -> "Gaussians":
        """A copy sharing the attribute arrays, with ``columns`` added to (or replacing) the extras."""
        extras = dict(self.extras)
        extras.update(columns)
        return Gaussians(self.means, self.quats, self.log_scales, self.opacity_logits, self.sh, extras)

    def to_torch(self, device: "str | torch.device" = "cpu") -> dict[str, "torch.Tensor"]:
        """Tensors named as the fields: means, quats, log_scales, opacity_logits, sh.

        Zero-copy on the CPU for writeable arrays; read-only arrays (e.g. memory-mapped or Arrow-backed
        shards) are copied, since torch tensors must be writeable.
        """
        import torch

        def tensor(array: np.ndarray) -> "torch.Tensor":
            return torch.from_numpy(array if array.flags.writeable else array.copy()).to(device)

        return {name: tensor(getattr(self, name)) for name in ("means", "quats", "log_scales", "opacity_logits", "sh")}
