"""Import validation of Gaussians: count every invalid value, then error, drop or repair, and say so.

Checks (counted per PLY property name, on every row):

* ``non_finite``: NaN or +-Inf in any float attribute (``x``, ``f_rest_7``, ``opacity``, float extras, ...).
* ``zero_norm_quaternion``: finite ``rot_0..3`` with norm <= ``QUAT_NORM_EPS`` (rotation undefined).
* ``log_scale_overflow``: finite ``scale_i`` > ``LOG_SCALE_FLOAT32_MAX`` (``exp`` overflows float32).
* ``opacity_saturated``: finite ``|opacity| > OPACITY_LOGIT_SATURATION`` (sigmoid is exactly 0 or 1 in float32).

Policies (``on_invalid``):

* ``error`` (default): ``InvalidGaussiansError`` naming the source, every offending property and its row count.
* ``drop``: every row with any problem is removed; counted per property under ``dropped``.
* ``repair``: values fixed in place where a fix is defined, rows dropped where it is not:

  ======================================  =====================================================
  problem                                 action (name in the report)
  ======================================  =====================================================
  non-finite ``x, y, z``                  row dropped (``dropped``): a position cannot be guessed
  non-finite or zero-norm ``rot_*``       quaternion set to identity (1, 0, 0, 0) (``set_identity``)
  NaN ``scale_i``                         row dropped (``dropped``)
  ``scale_i`` > max or +Inf / -Inf        clamped to +-``LOG_SCALE_FLOAT32_MAX`` (``clamped``)
  NaN ``opacity``                         row dropped (``dropped``)
  ``|opacity|`` > saturation or +-Inf     clamped to +-``OPACITY_LOGIT_SATURATION`` (``clamped``)
  non-finite ``f_dc_*`` / ``f_rest_*``    set to 0 (``zeroed``): no colour contribution
  non-finite float extra                  row dropped (``dropped``)
  ======================================  =====================================================

  Repairs are counted on the rows that are kept.
* ``report``: nothing changes; the problems are only counted (used by ``inspect``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.core.constants import LOG_SCALE_FLOAT32_MAX, OPACITY_LOGIT_SATURATION, QUAT_NORM_EPS
from seggaussian.core.gaussians import Gaussians

__all__ = ["ValidationReport", "InvalidGaussiansError", "validate_gaussians", "ON_INVALID_CHOICES"]

ON_INVALID_CHOICES = ("error", "drop", "repair", "report")
CHECKS = ("non_finite", "zero_norm_quaternion", "log_scale_overflow", "opacity_saturated")


class InvalidGaussiansError(ValueError):
    """Gaussians with invalid values under ``on_invalid="error"``; the message names source and properties."""


class ValidationReport(NamedTuple):
    """What validation found and what it did.

    Fields:
        source: file (or other origin) the Gaussians came from.
        on_invalid: the policy applied (``error``, ``drop``, ``repair``, ``report``).
        num_input: Gaussians before validation.
        num_output: Gaussians after validation (``num_input - num_dropped``).
        issues: ``{check: {ply_property: rows}}`` for the checks in ``CHECKS`` (only non-zero counts).
        actions: ``{action: {ply_property: rows}}`` with actions ``dropped``, ``set_identity``,
            ``clamped``, ``zeroed`` (only non-zero counts). A dropped row is counted under every
            property that caused it.
        num_dropped: distinct rows removed.
    """

    source: str
    on_invalid: str
    num_input: int
    num_output: int
    issues: dict
    actions: dict
    num_dropped: int

    @property
    def ok(self) -> bool:
        """True when no check found anything."""
        return not self.issues

    def describe_issues(self) -> str:
        parts = [f"{check.replace('_', ' ')}: " + ", ".join(f"{prop} ({rows} rows)" for prop, rows in props.items())
                 for check, props in self.issues.items()]
        return "; ".join(parts) if parts else "no invalid values"

    def describe_actions(self) -> str:
        parts = [f"{action.replace('_', ' ')}: " + ", ".join(f"{prop} ({rows} rows)" for prop, rows in props.items())
                 for action, props in self.actions.items()]
        if self.num_dropped:
            parts.append(f"{self.num_dropped} of {self.num_input} rows dropped in total")
        return "; ".join(parts) if parts else "nothing changed"

    def to_dict(self) -> dict:
        return {**self._asdict(), "ok": self.ok}


def _sh_property_names(num_sh_coeffs: int) -> np.ndarray:
    """``[num_sh_coeffs, 3]`` PLY names of ``sh[:, j, c]`` (channel-major ``f_rest``)."""
    names = np.empty((num_sh_coeffs, 3), dtype=object)
    for c in range(3):
        names[0, c] = f"f_dc_{c}"
        for j in range(1, num_sh_coeffs):
            names[j, c] = f"f_rest_{c * (num_sh_coeffs - 1) + j - 1}"
    return names


def _extra_property_names(name: str, column: np.ndarray) -> list[str]:
    return [name] if column.ndim == 1 else [f"{name}_{j}" for j in range(int(np.prod(column.shape[1:])))]


def _rows(mask: np.ndarray) -> np.ndarray:
    """``[N, ...]`` -> ``[N, C]`` (also for N = 0)."""
    return mask.reshape(mask.shape[0], int(np.prod(mask.shape[1:], dtype=np.int64)))


def _count(counts: dict, check: str, names, bad: np.ndarray) -> None:
    """Add per-column counts of the ``[N, C]`` mask ``bad`` under ``counts[check][name]``."""
    if not bad.any():  # the common case: nothing to count, skip the per-column reduction
        return
    per_column = _rows(bad).sum(axis=0)
    for name, rows in zip(names, per_column):
        if rows:
            counts.setdefault(check, {})[name] = counts.get(check, {}).get(name, 0) + int(rows)


def validate_gaussians(gaussians: Gaussians, on_invalid: str = "error", source: str = "<gaussians>"):
    """Run the checks, apply ``on_invalid`` -> ``(Gaussians, ValidationReport)``. See the module docstring."""
    if on_invalid not in ON_INVALID_CHOICES:
        raise ValueError(f"on_invalid must be one of {ON_INVALID_CHOICES}, got {on_invalid!r}")
    g = gaussians
    n = len(g)
    k = g.num_sh_coeffs
    issues: dict[str, dict[str, int]] = {}

    # --- detection ---------------------------------------------------------------------------
    means_bad = ~np.isfinite(g.means)                                    # [N, 3]
    quats_bad = ~np.isfinite(g.quats)                                    # [N, 4]
    scales_nan = np.isnan(g.log_scales)                                  # [N, 3]
    scales_inf = np.isinf(g.log_scales)
    opacity_nan = np.isnan(g.opacity_logits)                             # [N]
    opacity_inf = np.isinf(g.opacity_logits)
    # [N, num_sh_coeffs, 3]; the SH block is most of the data: a one-pass sum proves "all finite" in the common case
    # (a non-finite sum, including an overflow of large finite values, falls back to the exact mask)
    with np.errstate(over="ignore", invalid="ignore"):
        sh_all_finite = bool(np.isfinite(g.sh.sum()))
    sh_bad = np.zeros(g.sh.shape, dtype=bool) if sh_all_finite else ~np.isfinite(g.sh)
    _count(issues, "non_finite", ["x", "y", "z"], means_bad)
    sh_names = _sh_property_names(k)
    _count(issues, "non_finite", list(sh_names.reshape(-1)), sh_bad)
    _count(issues, "non_finite", ["opacity"], (opacity_nan | opacity_inf)[:, None])
    _count(issues, "non_finite", [f"scale_{i}" for i in range(3)], scales_nan | scales_inf)
    _count(issues, "non_finite", [f"rot_{i}" for i in range(4)], quats_bad)
    extras_bad_rows = np.zeros(n, dtype=bool)
    for name, column in g.extras.items():
        if column.dtype.kind == "f":
            bad = _rows(~np.isfinite(column))
            _count(issues, "non_finite", _extra_property_names(name, column), bad)
            extras_bad_rows |= bad.any(axis=1)

    quat_rows_finite = ~quats_bad.any(axis=1)
    norms = np.linalg.norm(np.where(quats_bad, 0.0, g.quats).astype(np.float64), axis=1)
    zero_quat = quat_rows_finite & (norms <= QUAT_NORM_EPS)              # [N]
    if zero_quat.any():
        issues.setdefault("zero_norm_quaternion", {})["rot"] = int(zero_quat.sum())
    with np.errstate(invalid="ignore"):
        scale_over = np.isfinite(g.log_scales) & (g.log_scales > LOG_SCALE_FLOAT32_MAX)
        opacity_sat = np.isfinite(g.opacity_logits) & (np.abs(g.opacity_logits) > OPACITY_LOGIT_SATURATION)
    _count(issues, "log_scale_overflow", [f"scale_{i}" for i in range(3)], scale_over)
    _count(issues, "opacity_saturated", ["opacity"], opacity_sat[:, None])

    def report(out: Gaussians, actions: dict, dropped: int) -> ValidationReport:
        return ValidationReport(source, on_invalid, n, len(out), issues, actions, dropped)

    if not issues or on_invalid == "report":
        return g, report(g, {}, 0)
    if on_invalid == "error":
        raise InvalidGaussiansError(
            f"{source}: invalid values in {n} Gaussians: {report(g, {}, 0).describe_issues()} "
            f"(use --on-invalid drop or repair, or on_invalid='drop'/'repair')"
        )

    actions: dict[str, dict[str, int]] = {}
    if on_invalid == "drop":
        row_bad = (means_bad.any(1) | quats_bad.any(1) | scales_nan.any(1) | scales_inf.any(1) | opacity_nan
                   | opacity_inf | _rows(sh_bad).any(1) | extras_bad_rows | zero_quat
                   | scale_over.any(1) | opacity_sat)
        for props in issues.values():
            for prop, rows in props.items():
                actions.setdefault("dropped", {})[prop] = actions.get("dropped", {}).get(prop, 0) + rows
        out = g.subset(~row_bad)
        return out, report(out, actions, int(row_bad.sum()))

    # --- repair --------------------------------------------------------------------------------
    row_drop = means_bad.any(1) | scales_nan.any(1) | opacity_nan | extras_bad_rows
    _count(actions, "dropped", ["x", "y", "z"], means_bad)
    _count(actions, "dropped", [f"scale_{i}" for i in range(3)], scales_nan)
    _count(actions, "dropped", ["opacity"], opacity_nan[:, None])
    for name, column in g.extras.items():
        if column.dtype.kind == "f":
            _count(actions, "dropped", _extra_property_names(name, column), _rows(~np.isfinite(column)))
    keep = ~row_drop
    quats = g.quats[keep].copy()
    log_scales = g.log_scales[keep].copy()
    opacity_logits = g.opacity_logits[keep].copy()
    sh = g.sh[keep].copy()

    identity = (quats_bad.any(1) | zero_quat)[keep]
    _count(actions, "set_identity", ["rot"], identity[:, None])
    quats[identity] = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    clamp_scale = (scale_over | scales_inf)[keep]
    _count(actions, "clamped", [f"scale_{i}" for i in range(3)], clamp_scale)
    log_scales[clamp_scale] = np.clip(log_scales[clamp_scale], -LOG_SCALE_FLOAT32_MAX, LOG_SCALE_FLOAT32_MAX)
    clamp_opacity = (opacity_sat | opacity_inf)[keep]
    _count(actions, "clamped", ["opacity"], clamp_opacity[:, None])
    opacity_logits[clamp_opacity] = np.clip(opacity_logits[clamp_opacity], -OPACITY_LOGIT_SATURATION,
                                            OPACITY_LOGIT_SATURATION)
    zero_sh = sh_bad[keep]
    _count(actions, "zeroed", list(sh_names.reshape(-1)), zero_sh)
    sh[zero_sh] = 0.0
    out = Gaussians(g.means[keep], quats, log_scales, opacity_logits, sh,
                    {name: column[keep] for name, column in g.extras.items()})
    return out, report(out, actions, int(row_drop.sum()))
