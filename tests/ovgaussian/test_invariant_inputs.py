"""``input_encoding="invariant"``: what the network sees of a splat does not move with how the splat was made.

Per Gaussian, exactly: the sign of the quaternion, the way one ellipsoid is written (axes permuted with their
scales), its metric size and its opacity change no input, and the copies a split makes have their parent's inputs.
Per voxel, nearly: a room of flat Gaussians on its walls and floor, densified by splitting, subsampled, with its
opacities spread otherwise or its scales shrunk (another fit's sizes), gives each voxel nearly the same pooled
inputs. The robust encoding fails the same check for the last two (the test can fail).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ovgaussian.model.config import OVGaussianNetConfig
from ovgaussian.model.network import NUM_GAUSSIAN_ATTRIBUTES, OVGaussianNet, invariant_attributes
from ovgaussian.sparse import voxelize_points
from seggaussian.core.rotations import quats_to_rotmats, rotmats_to_quats

TINY = dict(widths=(4, 4, 8, 8, 8, 8, 4, 4), blocks=(1, 1, 1, 1, 1, 1, 1, 1), stem_width=4, stem_kernel_size=3,
            embedding_width=12, voxel_size=0.1)


def _attributes(colour, opacity, scales, quats) -> torch.Tensor:
    """``[N, 11]`` in :func:`gaussian_attributes`' column order from numpy arrays."""
    return torch.from_numpy(np.concatenate([colour, opacity[:, None], scales, quats], axis=1).astype(np.float32))


def _random_gaussians(rng, n):
    colour = rng.uniform(0, 1, (n, 3))
    opacity = rng.uniform(0.05, 1, n)
    scales = np.exp(rng.normal(-4, 1, (n, 3)))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return colour, opacity, scales, quats


def test_every_column_is_the_same_for_every_way_of_writing_a_gaussian():
    rng = np.random.default_rng(0)
    colour, opacity, scales, quats = _random_gaussians(rng, 500)
    base = invariant_attributes(_attributes(colour, opacity, scales, quats))
    assert base.shape == (500, NUM_GAUSSIAN_ATTRIBUTES) and torch.isfinite(base).all()
    # axes permuted with their scales: R' = R P, s' = P^T s, the same covariance R diag(s^2) R^T
    perm = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], np.float64)  # a proper rotation (det +1)
    rot = quats_to_rotmats(quats) @ perm
    permuted_scales = scales @ perm  # column j of s' is s[:, perm^-1(j)]
    cov = quats_to_rotmats(quats) @ (scales[:, :, None] ** 2 * np.eye(3)) @ quats_to_rotmats(quats).transpose(0, 2, 1)
    cov2 = rot @ (permuted_scales[:, :, None] ** 2 * np.eye(3)) @ rot.transpose(0, 2, 1)
    np.testing.assert_allclose(cov, cov2, atol=1e-12)  # the same ellipsoids, as meant
    variants = {
        "-q": (colour, opacity, scales, -quats),
        "permuted axes": (colour, opacity, permuted_scales, rotmats_to_quats(rot)),
        "another size": (colour, opacity, scales * 0.37, quats),
        "another opacity": (colour, rng.uniform(0.01, 1, 500), scales, quats),
        "split children (scales / 1.6)": (colour, opacity, scales / 1.6, quats),
    }
    for name, arrays in variants.items():
        torch.testing.assert_close(invariant_attributes(_attributes(*arrays)), base, atol=2e-5, rtol=0, msg=name)
    # what it does keep: another colour, shape or orientation moves it
    assert not torch.allclose(invariant_attributes(_attributes(1 - colour, opacity, scales, quats)), base)
    flatter = scales.copy()
    flatter[:, 0] *= 0.1
    assert not torch.allclose(invariant_attributes(_attributes(colour, opacity, flatter, quats)), base)


def test_flat_gaussians_give_their_normal_and_round_ones_none():
    up = np.array([[1.0, 0, 0, 0]])  # identity: the axes are the world's
    disc_z = invariant_attributes(_attributes(np.full((1, 3), 0.5), np.ones(1), np.array([[0.05, 0.05, 0.0005]]), up))
    disc_x = invariant_attributes(_attributes(np.full((1, 3), 0.5), np.ones(1), np.array([[0.0005, 0.05, 0.05]]), up))
    ball = invariant_attributes(_attributes(np.full((1, 3), 0.5), np.ones(1), np.array([[0.05, 0.05, 0.05]]), up))
    needle = invariant_attributes(_attributes(np.full((1, 3), 0.5), np.ones(1), np.array([[0.5, 0.005, 0.005]]), up))
    assert disc_z[0, 6] == pytest.approx(0.99) and disc_z[0, 7] == pytest.approx(0.99)  # a floor: n_z = 1
    assert disc_x[0, 7] == pytest.approx(-0.495) and disc_x[0, 8] == pytest.approx(0.99)  # a wall facing x
    assert disc_z[0, 4] == 0 and disc_z[0, 5] == pytest.approx(0.5 * math.log(0.01))  # log(s3 / s2), halved
    for no_normal in (ball, needle):
        assert torch.all(no_normal[0, 6:] == 0)
    assert ball[0, 4] == 0 and ball[0, 5] == 0 and ball[0, 3] == 1


def _flat_room(rng, n):
    """Flat Gaussians on the floor (z = 0) and two walls (x = 0, y = 0) of a 3 x 3 x 2.5 m room: colour by surface
    and a stripe pattern, the normal along the thin axis, in-plane sizes about 2 cm."""
    surface = rng.integers(0, 3, n)
    uv = rng.uniform(0, 1, (n, 2))
    means = np.zeros((n, 3))
    normal_axis = np.array([2, 0, 1])[surface]
    for k, (a, b) in enumerate([(0, 1), (1, 2), (0, 2)]):
        rows = surface == k
        means[rows, a] = uv[rows, 0] * 3.0
        means[rows, b] = uv[rows, 1] * (3.0 if b != 2 else 2.5)
    colour = np.stack([surface == 0, surface == 1, surface == 2], 1) * 0.6 + 0.2
    colour += 0.15 * np.sin(means.sum(axis=1, keepdims=True) * 7.0)
    scales = np.exp(rng.normal(np.log(0.02), 0.3, (n, 3)))
    scales[np.arange(n), normal_axis] = 0.002
    angle = rng.uniform(0, 2 * np.pi, n)  # spin about the normal: no input may see it
    quats = np.zeros((n, 4))
    quats[:, 0] = np.cos(angle / 2)
    quats[np.arange(n), 1 + normal_axis] = np.sin(angle / 2)
    opacity = rng.uniform(0.3, 1.0, n)
    return means, colour, opacity, scales, quats


def _split(rng, means, colour, opacity, scales, quats):
    """3DGS's split: two children drawn from each parent's Gaussian, scales / 1.6, the parent's rotation, colour and
    opacity."""
    from ovgaussian.data.augmentation import drawn_positions

    rot = quats_to_rotmats(quats)
    children = [drawn_positions(rng, means, rot, scales) for _ in range(2)]
    return (np.concatenate(children), np.tile(colour, (2, 1)), np.tile(opacity, 2), np.tile(scales / 1.6, (2, 1)),
            np.tile(quats, (2, 1)))


def _pooled(net: OVGaussianNet, means, colour, opacity, scales, quats) -> dict:
    """{voxel coordinates: pooled network input} as the network's voxel stage makes them."""
    attributes = _attributes(colour, opacity, scales, quats)
    means_t = torch.from_numpy(means.astype(np.float32))
    batch = torch.zeros(len(means), dtype=torch.long)
    weights = net.pool_weights(attributes)
    inputs = net.prepare_inputs(means_t, attributes, batch)
    vox = voxelize_points(means_t, inputs, batch, net.config.voxel_size, net.config.max_grid_extent, weights=weights)
    coords = vox.voxels.sites.coords.tolist()
    return {tuple(c): row for c, row in zip(coords, vox.voxels.features[:, :NUM_GAUSSIAN_ATTRIBUTES])}


def _voxel_change(a: dict, b: dict) -> float:
    """Mean absolute change of the pooled inputs over the voxels both have (the room's corner anchors the grid)."""
    common = sorted(set(a) & set(b))
    assert len(common) > 0.8 * min(len(a), len(b))
    return float(torch.stack([(a[k] - b[k]).abs().mean() for k in common]).mean())


def _anchored(arrays, anchor):
    """Prepend the anchor Gaussians (the room's min corner stays where it is, so the grid does not move)."""
    return tuple(np.concatenate([x, y]) for x, y in zip(anchor, arrays))


def _changes(encoding: str) -> dict:
    """Mean per-voxel change of the pooled inputs under each way of remaking the room (same draws per encoding)."""
    rng = np.random.default_rng(1)
    room = _flat_room(rng, 20_000)
    anchor = (np.zeros((1, 3)),) + tuple(x[:1] for x in room[1:])
    net = OVGaussianNet(OVGaussianNetConfig(**TINY, input_encoding=encoding))
    base = _pooled(net, *_anchored(room, anchor))
    means, colour, opacity, scales, quats = room
    keep = rng.random(len(means)) < 0.5
    logits = np.log(opacity / (1 - opacity))
    return {
        "split": _voxel_change(base, _pooled(net, *_anchored(_split(rng, *room), anchor))),
        "subsample": _voxel_change(base, _pooled(net, *_anchored(tuple(x[keep] for x in room), anchor))),
        "opacity": _voxel_change(base, _pooled(net, *_anchored(
            (means, colour, 1 / (1 + np.exp(-(2.5 * logits - 1.0))), scales, quats), anchor))),
        "size": _voxel_change(base, _pooled(net, *_anchored((means, colour, opacity, scales * 0.35, quats), anchor))),
    }


def test_per_voxel_inputs_under_densify_subsample_opacity_and_size():
    """What is left of the invariant encoding's change comes from Gaussians that move between voxels (a split's
    children are drawn around their parent; a subsample leaves other Gaussians in each voxel) and from the pooling
    weights; the robust encoding also sees the sizes and opacities themselves."""
    invariant, robust = _changes("invariant"), _changes("robust")
    bounds = {"split": 0.05, "subsample": 0.02, "opacity": 0.01, "size": 1e-4}
    for name, bound in bounds.items():
        assert invariant[name] < bound, (name, invariant)
        assert invariant[name] < 0.3 * robust[name], (name, invariant, robust)
    assert robust["size"] > 0.05 and robust["split"] > 0.05, robust


def test_the_network_runs_on_the_invariant_encoding_and_pools_by_opacity():
    net = OVGaussianNet(OVGaussianNetConfig(**TINY, input_encoding="invariant", use_coordinates=True))
    rng = np.random.default_rng(2)
    room = _flat_room(rng, 3000)
    means = torch.from_numpy(room[0].astype(np.float32))
    attributes = _attributes(*room[1:])
    out = net(means, attributes, torch.zeros(len(means), dtype=torch.long))
    assert out.shape == (3000, net.config.semantic_width) and torch.isfinite(out).all()
    weights = net.pool_weights(attributes)
    torch.testing.assert_close(weights, attributes[:, 3].clamp_min(1e-3))
    with pytest.raises(ValueError, match="input_encoding"):
        OVGaussianNetConfig(**TINY, input_encoding="scaled")
    assert math.isfinite(float(out.sum()))


def test_lattice_voxels_stay_put_when_a_point_is_added_outside():
    """With ``lattice=k`` the grid's origin is a multiple of k voxels: a point added beyond the scene's corner shifts
    the integer coordinates by a multiple of k or not at all, and every other point keeps its voxel's neighbours and
    its offset inside it; with the minimum-corner origin (None) the offsets of every point move."""
    rng = np.random.default_rng(3)
    points = torch.from_numpy(rng.uniform(0.37, 3.2, (2000, 3)))
    outside = torch.cat([points, torch.tensor([[0.37 - 0.43, 0.37 - 0.03, 0.3]], dtype=torch.float64)])
    feats = torch.ones(2001, 1)
    batch = torch.zeros(2001, dtype=torch.long)
    for lattice in (1, 16):
        a = voxelize_points(points, feats[:2000], batch[:2000], 0.1, 4096, lattice=lattice)
        b = voxelize_points(outside, feats, batch, 0.1, 4096, lattice=lattice)
        shift = b.voxels.sites.coords[b.point_to_voxel[:2000]] - a.voxels.sites.coords[a.point_to_voxel]
        assert (shift == shift[0]).all() and bool((shift[0] % lattice == 0).all())
        torch.testing.assert_close(a.point_offsets, b.point_offsets[:2000])
    a = voxelize_points(points, feats[:2000], batch[:2000], 0.1, 4096)
    b = voxelize_points(outside, feats, batch, 0.1, 4096)
    assert not torch.allclose(a.point_offsets, b.point_offsets[:2000])
    with pytest.raises(ValueError, match="lattice"):
        voxelize_points(points, feats[:2000], batch[:2000], 0.1, 4096, lattice=0)


@pytest.mark.parametrize("anchor", ["lattice", "min"])
def test_predictions_do_not_move_with_two_faint_floaters_on_the_lattice(anchor):
    """A room predicted twice, the second time with two faint Gaussians a few centimetres beyond its opposite corners
    (the bounding box and its centre move, the room does not): on the lattice the room's Gaussians keep their semantic
    vectors but for those whose neighbourhood holds a floater; from the minimum corner nearly all move (what runs
    before the lattice did)."""
    from ovgaussian.predict.query import ModelPredictor
    from ovgaussian.run.config import TextConfig
    from seggaussian.core.constants import SH_C0
    from seggaussian.core.gaussians import Gaussians

    rng = np.random.default_rng(4)
    means, colour, opacity, scales, quats = _flat_room(rng, 3000)
    means = means + np.array([12.34, -5.67, 0.89])  # a room away from the frame's origin
    net = OVGaussianNet(OVGaussianNetConfig(**TINY, input_encoding="invariant", grid_anchor=anchor))
    predictor = ModelPredictor(net, TextConfig())

    def splat(m, c, o, s, q):
        return Gaussians.from_arrays(m, q, np.log(s), np.log(o / (1 - o)), ((c - 0.5) / SH_C0)[:, None, :])

    lo, hi = means.min(axis=0) - 0.037, means.max(axis=0) + 0.071
    extra = (np.stack([lo, hi]), colour[:2], np.full(2, 0.01), scales[:2], quats[:2])
    base = predictor.encode_gaussians(splat(means, colour, opacity, scales, quats))
    more = predictor.encode_gaussians(splat(*(np.concatenate([x, y]) for x, y in
                                              zip((means, colour, opacity, scales, quats), extra))))[:3000]
    moved = float((np.abs(more - base).max(axis=1) > 1e-3).mean())
    assert moved < 0.1 if anchor == "lattice" else moved > 0.5


def test_rendition_keeps_rows_labels_and_the_room():
    """``rendition``: the first N rows are still the N Gaussians (moved within their own extent), second children
    are appended with their parent's label, colour and rotation, and the same rng gives the same rendition."""
    from ovgaussian.data.augmentation import RENDITION_SPLIT_DIVISOR, rendition

    rng = np.random.default_rng(5)
    means, colour, opacity, scales, quats = _flat_room(rng, 4000)
    labels = rng.integers(0, 5, 4000)
    args = (means.astype(np.float32), quats.astype(np.float32), np.log(scales).astype(np.float32),
            np.log(opacity / (1 - opacity)).astype(np.float32), colour.astype(np.float32), labels)
    out = rendition(np.random.default_rng(7), *args)
    again = rendition(np.random.default_rng(7), *args)
    for a, b in zip(out, again):
        np.testing.assert_array_equal(a, b)
    n = len(means)
    extra = len(out.means) - n
    assert 0 <= extra <= n and len(out.labels) == len(out.means) == len(out.quats)
    np.testing.assert_array_equal(out.labels[:n], labels)
    np.testing.assert_array_equal(out.sh_dc[:n], colour.astype(np.float32))
    # every Gaussian stays within a few of its own largest scales of where it was
    reach = np.linalg.norm(out.means[:n] - means, axis=1) / scales.max(axis=1)
    assert np.quantile(reach, 0.999) < 5.0
    # sizes: one global shift, split ones divided by 1.6 on top
    shift = out.log_scales[:n] - np.log(scales)
    assert np.ptp(np.round(shift - shift.min(), 4)) <= np.log(RENDITION_SPLIT_DIVISOR) + 1e-3
    # the appended children copy a parent: same label, colour and rotation as some original row
    if extra:
        parents = {tuple(np.round(q, 5)) + (int(l),) for q, l in zip(quats.astype(np.float32), labels)}
        assert all(tuple(np.round(q, 5)) + (int(l),) in parents for q, l in zip(out.quats[n:], out.labels[n:]))
    empty = rendition(np.random.default_rng(0), *(a[:0] for a in args))
    assert all(len(a) == 0 for a in empty)


@pytest.mark.parametrize("augment", ["rendition_augment", "off_surface_augment"])
def test_the_training_data_remakes_splats_only_when_asked(augment):
    """The trainer's data path applies the rendition and off-surface augments (opt-in): some samples then hold more
    Gaussians than the scene (appended children or copies), with a label for each; without it every sample holds the
    scene's Gaussians."""
    from ovgaussian.data.scene_source import InMemorySource
    from ovgaussian.data.training_data import TrainingData
    from ovgaussian.run.config import DataConfig
    from ovgaussian.text.vocabulary import training_vocabulary
    from test_train import make_scene

    scene = make_scene(0)
    n = len(scene.gaussians.means)
    for flag in (False, True):
        data = TrainingData(InMemorySource([scene]), DataConfig(**{augment: flag}, pixels_per_view=64),
                            training_vocabulary(20))
        samples = [data.sample(scene.scene_id, np.random.default_rng(s)) for s in range(8)]
        assert all(len(x.labels) == len(x.means) == len(x.opacity_logits) for x in samples)
        grew = sum(len(x.means) > n for x in samples)
        assert (grew > 0) if flag else (grew == 0)


def test_surface_normals_of_planes_and_a_sphere():
    """The normal of a centre is its neighbourhood's axis of least spread: the plane's own normal on a tilted plane,
    the radius on a sphere (checked against the analytic normal, sign free)."""
    from ovgaussian.data.augmentation import surface_normals

    rng = np.random.default_rng(3)
    uv = rng.uniform(-1, 1, (3000, 2))
    normal = np.array([1.0, 2.0, 2.0]) / 3.0
    u = np.cross(normal, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    plane = uv[:, :1] * u + uv[:, 1:] * v
    assert np.abs(surface_normals(plane) @ normal).min() > 0.999
    sphere = rng.normal(size=(4000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    assert np.median(np.abs(np.sum(surface_normals(sphere) * sphere, axis=1))) > 0.99
    assert surface_normals(plane[:1]).shape == (1, 3)  # fewer centres than neighbours: all of them


def test_off_surface_copies_move_along_the_normal_and_keep_their_source():
    """The first N rows are the scene unchanged; each appended copy is some row's shape, colour, opacity and label,
    moved along that row's surface normal only (on a plane: off it, not along it), to both sides; seeded."""
    from ovgaussian.data.augmentation import OFF_SURFACE_SHARE, off_surface

    rng = np.random.default_rng(5)
    n = 3000
    means = np.c_[rng.uniform(0, 2, (n, 2)), np.zeros(n)].astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    log_scales = rng.normal(-3, 0.3, (n, 3)).astype(np.float32)
    opacity = rng.normal(0, 1, n).astype(np.float32)
    colour = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    labels = rng.integers(0, 9, n)
    args = (means, quats, log_scales, opacity, colour, labels)
    out = off_surface(np.random.default_rng(1), *args)
    again = off_surface(np.random.default_rng(1), *args)
    for a, b in zip(out, again):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(out, args):
        np.testing.assert_array_equal(a[:n], b)
    k = len(out.means) - n
    assert OFF_SURFACE_SHARE[0] * n - 1 <= k <= OFF_SURFACE_SHARE[1] * n + 1
    moved = out.means[n:]
    source = {tuple(np.round(r, 5)) for r in np.c_[means[:, :2], log_scales, opacity, colour, labels]}
    assert all(tuple(np.round(r, 5)) in source
               for r in np.c_[moved[:, :2], out.log_scales[n:], out.opacity_logits[n:], out.sh_dc[n:], out.labels[n:]])
    assert (moved[:, 2] > 0.005).sum() > k // 4 and (moved[:, 2] < -0.005).sum() > k // 4
    assert np.abs(moved[:, 2]).max() < 0.5
    empty = off_surface(np.random.default_rng(0), *(a[:0] for a in args))
    assert all(len(a) == 0 for a in empty)


def test_surface_normals_turn_with_the_training_similarity():
    """The trainer keeps each scene's normals and turns them with the sample's similarity (scale, rotation about z,
    mirrors) instead of recomputing them: the same axes as the normals of the moved centres, sign free."""
    from ovgaussian.data.augmentation import Augmentation, augment_gaussians, surface_normals

    rng = np.random.default_rng(11)
    means = rng.normal(size=(2500, 3)) * [1.0, 0.6, 0.3]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (len(means), 1))
    aug = Augmentation(1.07, 0.8, np.array([-1.0, 1.0, 1.0]))
    moved, _, _ = augment_gaussians(means, quats, np.zeros((len(means), 3)), aug)
    turned = surface_normals(means) @ aug.linear.T
    turned /= np.linalg.norm(turned, axis=1, keepdims=True)
    assert np.abs(np.sum(turned * surface_normals(moved), axis=1)).min() > 0.999
