"""Training augmentation of OVGaussian: a random similarity applied to the network's input Gaussians.

A similarity ``A`` (random uniform scale, rotation about the up axis z, mirror of x and/or y) maps means to
``A x`` and covariances to ``A Sigma A^T`` (quaternions and log-scales updated). It is applied to the
network input only: applying the same ``A`` to the camera would leave the rendered image unchanged (a
similarity of scene and camera together does not change any pixel), so the blend weights computed on the
stored geometry stay exact and ``M = W S`` needs no re-rasterization.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ovgaussian.run.config import DataConfig
from ovgaussian.model.surface import weighted_plane
from seggaussian.core.constants import QUAT_NORM_EPS, SH_C0
from seggaussian.core.knn import nearest_neighbours
from seggaussian.core.rotations import quats_to_rotmats, rotmats_to_quats


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
    log-scales grow by ``log s``. Done on the quaternions (:func:`_rotated_quats`: a product with ``R_z``'s
    quaternion, then the reflections' sign changes), not through ``[N, 3, 3]`` matrices
    (:func:`augment_gaussians_reference`), about 10x less time per 1,000,000 Gaussians.
    """
    linear = augmentation.linear
    new_means = (means.astype(np.float64) @ linear.T).astype(np.float32)
    new_quats = _rotated_quats(quats, augmentation).astype(np.float32)
    new_log_scales = (log_scales + np.float32(np.log(augmentation.scale))).astype(np.float32)
    return new_means, new_quats, new_log_scales


def _rotated_quats(quats: np.ndarray, augmentation: Augmentation) -> np.ndarray:  # [N, 4] w x y z -> float64
    """Quaternions of ``F R_z R D`` (:func:`augment_gaussians`) for the rotations ``R`` of ``quats``.

    ``p = r q`` with ``r = (cos a/2, 0, 0, sin a/2)`` is ``R_z R``. A single mirror (``det F = -1``): ``D`` is the
    mirror of x, and ``D X D`` for a rotation ``X`` of quaternion ``(w, x, y, z)`` has quaternion
    ``(w, x, -y, -z)``; ``F D`` is then the identity (``F`` mirrors x) or the half turn about z (``F`` mirrors y).
    Two mirrors: ``F`` is that half turn. The half turn about z multiplies on the left by ``(0, 0, 0, 1)``.
    """
    q = quats.astype(np.float64)
    c, s = np.cos(0.5 * augmentation.angle), np.sin(0.5 * augmentation.angle)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out = np.empty_like(q)
    out[:, 0] = c * w - s * z  # (c, 0, 0, s) (w, x, y, z)
    out[:, 1] = c * x - s * y
    out[:, 2] = c * y + s * x
    out[:, 3] = c * z + s * w
    fx, fy = augmentation.flip[0] < 0, augmentation.flip[1] < 0
    if fx != fy:  # one mirror: D (R_z R) D
        out[:, 2:] *= -1.0
    if fy:  # F D (one mirror, of y) or F (two mirrors) is the half turn about z: (0, 0, 0, 1) p
        out = np.stack([-out[:, 3], -out[:, 2], out[:, 1], out[:, 0]], axis=1)
    return out


def augment_gaussians_reference(means, quats, log_scales, augmentation: Augmentation):
    """:func:`augment_gaussians` through rotation matrices: ``F R_z`` times each ``[3, 3]`` rotation, the mirror
    ``D`` applied to the first column, back to quaternions (the slow, obviously-correct form)."""
    linear = augmentation.linear
    new_means = (means.astype(np.float64) @ linear.T).astype(np.float32)
    orthogonal = linear / augmentation.scale  # F R_z, det = det F
    rotmats = np.einsum("ij,njk->nik", orthogonal, quats_to_rotmats(quats.astype(np.float64)))
    if float(np.prod(augmentation.flip)) < 0:
        rotmats[:, :, 0] *= -1.0  # R D with D = diag(-1, 1, 1): proper again, same covariance
    new_quats = rotmats_to_quats(rotmats).astype(np.float32)
    new_log_scales = (log_scales.astype(np.float64) + np.log(augmentation.scale)).astype(np.float32)
    return new_means, new_quats, new_log_scales


#: ``DataConfig.splat_augment``: probability that a training sample gets fitted-splat statistics.
SPLAT_AUGMENT_PROBABILITY = 0.5
#: Redrawn opacity logits ~ N(mean, std): a CPU fit of a synthetic room has opacity median 0.13 and p95 0.52
#: (issue #27's table): logit -1.9 +- 1.3 gives median 0.13 and p95 0.55.
SPLAT_OPACITY_LOGIT = (-1.9, 1.3)
#: Per-axis log-scale noise std (anisotropy a fit develops on flat surfaces and thin edges).
SPLAT_LOG_SCALE_STD = 0.6
#: Colour noise std (RGB units; a fit's DC colour trades against view-dependent SH and leaves [0, 1]).
SPLAT_COLOUR_STD = 0.08
#: Floaters added, as a share of the scene's Gaussians: uniform in the scene's box, labels ignored.
SPLAT_FLOATER_SHARE = 0.05


class SplatStatistics(NamedTuple):
    """Per-Gaussian arrays after :func:`splat_statistics` (the added floaters are the last rows)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    labels: np.ndarray


def splat_statistics(rng: np.random.Generator, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray,
                     opacity_logits: np.ndarray, sh_dc: np.ndarray, labels: np.ndarray,
                     ignore_label: int) -> SplatStatistics:
    """What a fit does to a scene's Gaussians, drawn from ``rng``: opacities redrawn (``SPLAT_OPACITY_LOGIT``),
    per-axis log-scale noise, colour noise, and ``SPLAT_FLOATER_SHARE`` floaters (uniform in the box of the means,
    random orientation and opacity, label ``ignore_label``). Only the network input changes: the floaters are
    appended after the existing rows, so pixel blend weights computed on the stored Gaussians still index them."""
    n = means.shape[0]
    mean, std = SPLAT_OPACITY_LOGIT
    opacity = rng.normal(mean, std, n).astype(np.float32)
    scales = (log_scales + rng.normal(0.0, SPLAT_LOG_SCALE_STD, (n, 3))).astype(np.float32)
    sh = (sh_dc + rng.normal(0.0, SPLAT_COLOUR_STD / SH_C0, (n, 3))).astype(np.float32)
    k = int(round(SPLAT_FLOATER_SHARE * n)) if n else 0
    if k:
        lo, hi = means.min(axis=0), means.max(axis=0)
        f_means = rng.uniform(lo, hi, (k, 3)).astype(np.float32)
        f_quats = rng.normal(size=(k, 4))
        f_quats = (f_quats / np.linalg.norm(f_quats, axis=1, keepdims=True)).astype(np.float32)
        pick = rng.integers(0, n, k)
        f_scales = scales[pick] + rng.normal(0.0, 1.0, (k, 3)).astype(np.float32)
        f_opacity = rng.normal(mean - 1.0, std, k).astype(np.float32)
        f_sh = rng.normal(0.0, 0.3 / SH_C0, (k, 3)).astype(np.float32)
        means = np.concatenate([means, f_means])
        quats = np.concatenate([quats, f_quats])
        scales = np.concatenate([scales, f_scales])
        opacity = np.concatenate([opacity, f_opacity])
        sh = np.concatenate([sh, f_sh])
        labels = np.concatenate([labels, np.full(k, ignore_label, labels.dtype)])
    return SplatStatistics(means, quats, scales, opacity, sh, labels)


#: ``DataConfig.rendition_augment``: probability that a training sample is remade as another rendition of its splat.
RENDITION_PROBABILITY = 0.5
#: Share of the Gaussians split in two is drawn uniformly from this range (0: only moved and rescaled).
RENDITION_SPLIT_SHARE = (0.0, 1.0)
#: Every Gaussian moves by a draw from its own Gaussian times a factor drawn from this range (a refit places the
#: same surface's Gaussians elsewhere on it); split children are drawn at factor 1, as 3DGS draws them.
RENDITION_JITTER = (0.0, 1.0)
#: Global log-scale shift (another fit's sizes: the default preset's Gaussians are about 2.5x smaller than the profile's).
RENDITION_LOG_SCALE_SHIFT = (float(np.log(0.35)), float(np.log(1.2)))
#: Opacity logits are remapped to ``a * logit + b`` with ``a`` and ``b`` drawn from these ranges (another spread).
RENDITION_OPACITY_GAIN = (0.5, 2.0)
RENDITION_OPACITY_BIAS = (-1.5, 1.5)
#: Children of a split get their parent's scales divided by this (3DGS: 1.6).
RENDITION_SPLIT_DIVISOR = 1.6


def drawn_positions(rng: np.random.Generator, means: np.ndarray, rotmats: np.ndarray, scales: np.ndarray,
                    factor: float | np.ndarray = 1.0) -> np.ndarray:  # [N, 3] float64
    """One position drawn from each Gaussian, as 3DGS draws a split's children: ``mean + R (factor * s * z)`` with
    ``z ~ N(0, I)`` (``means [N, 3]``, ``rotmats [N, 3, 3]``, ``scales [N, 3]`` in metres, ``factor`` a number or
    ``[N]``)."""
    local = rng.normal(size=(len(means), 3)) * scales * np.reshape(factor, (-1, 1))
    return means.astype(np.float64) + np.einsum("nij,nj->ni", rotmats, local)


def rendition(rng: np.random.Generator, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray,
              opacity_logits: np.ndarray, sh_dc: np.ndarray, labels: np.ndarray) -> SplatStatistics:
    """The same room as another splat would give it, drawn from ``rng``: a share of the Gaussians split in two as
    3DGS splits (children drawn from the parent, scales divided by ``RENDITION_SPLIT_DIVISOR``, the parent's rotation,
    colour, opacity and label), every Gaussian moved within its own extent, all sizes shifted and the opacity spread
    remapped. Row ``i < N`` is still Gaussian ``i`` (its first child where it was split) and second children are
    appended, so pixel blend weights computed on the stored Gaussians still index the right rows."""
    n = means.shape[0]
    if not n:
        return SplatStatistics(means, quats, log_scales, opacity_logits, sh_dc, labels)
    rotmats = quats_to_rotmats(quats.astype(np.float64) / np.linalg.norm(quats, axis=1, keepdims=True)
                               .clip(QUAT_NORM_EPS))
    scales = np.exp(log_scales.astype(np.float64))

    split = rng.random(n) < rng.uniform(*RENDITION_SPLIT_SHARE)
    jitter = rng.uniform(*RENDITION_JITTER)
    new_means = drawn_positions(rng, means, rotmats, scales, np.where(split, 1.0, jitter))
    new_log_scales = log_scales.astype(np.float64) - np.where(split, np.log(RENDITION_SPLIT_DIVISOR), 0.0)[:, None]
    rows = np.flatnonzero(split)
    children = drawn_positions(rng, means[rows], rotmats[rows], scales[rows])
    shift = rng.uniform(*RENDITION_LOG_SCALE_SHIFT)
    gain, bias = rng.uniform(*RENDITION_OPACITY_GAIN), rng.uniform(*RENDITION_OPACITY_BIAS)
    opacity = opacity_logits.astype(np.float64) * gain + bias
    return SplatStatistics(
        np.concatenate([new_means, children]).astype(np.float32),
        np.concatenate([quats, quats[rows]]).astype(np.float32),
        (np.concatenate([new_log_scales, new_log_scales[rows]]) + shift).astype(np.float32),
        np.concatenate([opacity, opacity[rows]]).astype(np.float32),
        np.concatenate([sh_dc, sh_dc[rows]]).astype(np.float32),
        np.concatenate([labels, labels[rows]]),
    )



#: ``DataConfig.off_surface_augment``: probability that a training sample gets Gaussians off its surfaces.
OFF_SURFACE_PROBABILITY = 0.5
#: Share of the Gaussians copied off their surface, drawn uniformly from this range (a default-preset CPU fit without
#: depth supervision has about a fifth of its Gaussians 5 cm or more from the mesh, benchmarks/results/renditions.md).
OFF_SURFACE_SHARE = (0.05, 0.4)
#: A copy moves ``|N(0, sigma)|`` metres along its surface's normal, to either side, ``sigma`` drawn per sample from
#: this range (a fit's off-surface Gaussians lie along the normal: median |cos| 0.96 against 0.50 at random).
OFF_SURFACE_SIGMA = (0.02, 0.08)
#: Neighbouring centres whose principal axes give a Gaussian's surface normal (the axis of least spread).
OFF_SURFACE_NEIGHBOURS = 16


def surface_normals(means: np.ndarray, neighbours: int = OFF_SURFACE_NEIGHBOURS) -> np.ndarray:  # [N, 3] float64
    """``[N, 3]`` unit normal of the surface around each centre of ``means [N, 3]``: the least-spread axis
    (``weighted_plane``, weights 1) of its ``neighbours`` nearest centres (itself included), sign arbitrary."""
    pts = means.astype(np.float64)
    k = min(neighbours, len(pts))
    _, index = nearest_neighbours(pts, "scipy")(pts, k)
    return weighted_plane(pts[index], np.ones(index.shape))[1]


def off_surface(rng: np.random.Generator, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray,
                opacity_logits: np.ndarray, sh_dc: np.ndarray, labels: np.ndarray,
                normals: np.ndarray | None = None) -> SplatStatistics:
    """The scene with Gaussians off its surfaces, as a photometric fit leaves them (thick shells in front of and
    behind its surfaces), drawn from ``rng``: a share of the Gaussians is copied and each copy moved a half-normal
    distance along its surface's normal (:func:`surface_normals`) to a random side, with its source's shape, colour,
    opacity and label (the nearest surface's, as the label transfer gives it). Copies are appended, so rows ``i < N``
    are unchanged and pixel blend weights computed on the stored Gaussians still index the right rows. ``normals``
    ``[N, 3]``: the :func:`surface_normals` of ``means`` when known (the trainer keeps them per scene)."""
    n = means.shape[0]
    k = int(round(rng.uniform(*OFF_SURFACE_SHARE) * n)) if n > 1 else 0
    if not k:
        return SplatStatistics(means, quats, log_scales, opacity_logits, sh_dc, labels)
    rows = np.sort(rng.choice(n, size=k, replace=False))
    normals = (surface_normals(means) if normals is None else np.asarray(normals, np.float64))[rows]
    distance = rng.normal(0.0, rng.uniform(*OFF_SURFACE_SIGMA), k)  # the sign picks the side
    moved = means[rows].astype(np.float64) + normals * distance[:, None]
    return SplatStatistics(
        np.concatenate([means, moved.astype(means.dtype)]), np.concatenate([quats, quats[rows]]),
        np.concatenate([log_scales, log_scales[rows]]), np.concatenate([opacity_logits, opacity_logits[rows]]),
        np.concatenate([sh_dc, sh_dc[rows]]), np.concatenate([labels, labels[rows]]),
    )


#: ``DataConfig.colour_augment``: probability that a training sample's colours are recoloured.
COLOUR_AUGMENT_PROBABILITY = 0.5
#: A recoloured sample's hue turn (radians about the grey axis of RGB), drawn uniformly from this range.
COLOUR_HUE_TURN = (-np.pi, np.pi)
#: Its saturation factor (the chroma, colour minus its grey, scaled), drawn uniformly from this range.
COLOUR_SATURATION = (0.5, 1.5)
#: Its brightness gain (every channel scaled), drawn uniformly from this range.
COLOUR_GAIN = (0.8, 1.2)


def colour_matrix(hue_turn: float, saturation: float, gain: float) -> np.ndarray:  # [3, 3] float64
    """The linear map of RGB that turns the chroma by ``hue_turn`` radians about the grey axis ``(1, 1, 1)``,
    scales it by ``saturation`` and then every channel by ``gain``: ``gain (G + saturation R (I - G))`` with ``G``
    the projection on the grey axis and ``R`` the rotation (Rodrigues). Greys keep their level times ``gain``."""
    axis = np.full(3, 1.0 / np.sqrt(3.0))
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    rotation = np.eye(3) + np.sin(hue_turn) * cross + (1.0 - np.cos(hue_turn)) * (cross @ cross)
    grey = np.outer(axis, axis)
    return gain * (grey + saturation * rotation @ (np.eye(3) - grey))


def recolour(rng: np.random.Generator, sh_dc: np.ndarray) -> np.ndarray:  # [N, 3] float32
    """``sh_dc [N, 3]`` (colour = 0.5 + SH_C0 sh_dc) of a scene whose colours all went through one
    :func:`colour_matrix` drawn from ``rng`` (hue, saturation, gain in ``COLOUR_*``): another palette of the same
    room, as cross-domain rooms have (other floors, walls and furniture colours), with every colour contrast of the
    scene kept in order. The network clamps colours to [0, 1]; nothing is clamped here."""
    matrix = colour_matrix(rng.uniform(*COLOUR_HUE_TURN), rng.uniform(*COLOUR_SATURATION), rng.uniform(*COLOUR_GAIN))
    rgb = 0.5 + SH_C0 * sh_dc.astype(np.float64)
    return ((rgb @ matrix.T - 0.5) / SH_C0).astype(np.float32)


def recolour_reference(rgb: np.ndarray, hue_turn: float, saturation: float, gain: float) -> np.ndarray:
    """:func:`colour_matrix` applied colour by colour, in the terms of its definition (slow, obviously correct):
    each colour split into its grey ``m (1, 1, 1)`` and chroma ``c``; ``c`` turned about the unit grey axis ``k`` by
    Rodrigues' formula ``c cos t + (k x c) sin t + k (k . c)(1 - cos t)``, scaled by ``saturation``, the grey added
    back, the sum scaled by ``gain``."""
    k = np.full(3, 1.0 / np.sqrt(3.0))
    out = np.empty((len(rgb), 3))
    for i, colour in enumerate(np.asarray(rgb, np.float64)):
        grey = np.full(3, colour.mean())
        chroma = colour - grey
        turned = (chroma * np.cos(hue_turn) + np.cross(k, chroma) * np.sin(hue_turn)
                  + k * np.dot(k, chroma) * (1.0 - np.cos(hue_turn)))
        out[i] = gain * (grey + saturation * turned)
    return out
