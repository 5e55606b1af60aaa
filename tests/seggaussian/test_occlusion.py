"""Occluded label points (seggaussian.labels.occlusion) and the transfer stage that drops them.

The scene: a wall (the plane y = 0, facing -y) with a window 2 cm in front of it, a box standing on the floor, and
cameras on the -y side looking at the wall. The wall behind the window and the floor under the box are looked at and
never seen; everything else the cameras look at is seen; what no camera looks at keeps its label.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from seggaussian.build.config import BuildConfig
from seggaussian.build.stages import transfer as transfer_stage
from seggaussian.build.stages.transfer import occluded_label_points
from seggaussian.core.cameras import Camera, look_at
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.scene import Scene, View
from seggaussian.labels.config import TransferConfig
from seggaussian.labels.occlusion import occluded_points, occluded_points_reference, points_in_image
from seggaussian.labels.transfer import densify_labelled_mesh, transfer_labels

WALL, WINDOW, FLOOR, BOX = 1, 2, 3, 4


def _quad(corner, u, v):
    corner, u, v = (np.asarray(a, np.float64) for a in (corner, u, v))
    return np.stack([corner, corner + u, corner + u + v, corner + v]), np.array([[0, 1, 2], [0, 2, 3]])


def _assemble(parts):
    """``[((vertices, faces), label), ...]`` -> one mesh: (vertices, faces, face labels)."""
    vertices, faces, labels, offset = [], [], [], 0
    for (v, f), label in parts:
        vertices.append(v)
        faces.append(f + offset)
        labels += [label] * len(f)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces), np.array(labels)


def _scene_mesh():
    """(vertices, faces, face labels): wall x in [-2, 2], z in [0, 3] at y = 0; window x in [-0.5, 0.5], z in
    [1, 2] at y = -0.02; floor y in [-3, 0]; a closed-top box of 0.4 m on the floor (its top and four sides)."""
    parts = [(_quad((-2, 0, 0), (4, 0, 0), (0, 0, 3)), WALL),
             (_quad((-0.5, -0.02, 1), (1, 0, 0), (0, 0, 1)), WINDOW),
             (_quad((-2, -3, 0), (4, 0, 0), (0, 3, 0)), FLOOR)]
    lo, hi = np.array([0.8, -1.6, 0.0]), np.array([1.2, -1.2, 0.4])
    parts += [(_quad((lo[0], lo[1], hi[2]), (0.4, 0, 0), (0, 0.4, 0)), BOX),
              (_quad((lo[0], lo[1], 0), (0.4, 0, 0), (0, 0, 0.4)), BOX),
              (_quad((lo[0], hi[1], 0), (0.4, 0, 0), (0, 0, 0.4)), BOX),
              (_quad((lo[0], lo[1], 0), (0, 0.4, 0), (0, 0, 0.4)), BOX),
              (_quad((hi[0], lo[1], 0), (0, 0.4, 0), (0, 0, 0.4)), BOX)]
    return _assemble(parts)


def _camera(eye, target=(0.0, 0.0, 1.5), size=(64, 48), focal=60.0):
    K = np.array([[focal, 0, size[0] / 2], [0, focal, size[1] / 2], [0, 0, 1.0]])
    return Camera(K, look_at(np.array(eye, float), np.array(target, float)), *size)


CAMERAS = (_camera((0.0, -3.0, 1.5)), _camera((-1.0, -2.8, 1.8)), _camera((1.5, -2.9, 1.4), (1.0, -1.0, 0.2)))


def test_behind_the_window_and_under_the_box_is_occluded_the_rest_is_not():
    vertices, faces, _ = _scene_mesh()
    points = np.array([
        [0.0, 0.0, 1.5],  # wall behind the window: occluded
        [0.2, 0.0, 1.2],  # wall behind the window: occluded
        [1.5, 0.0, 1.5],  # wall beside the window: seen
        [0.0, -0.02, 1.5],  # the window itself: seen
        [1.0, -1.4, 0.0],  # floor under the box: occluded
        [1.0, -1.4, 0.4],  # the box's top: seen
        [-1.5, -2.5, 0.0],  # floor, in no camera's image: not looked at, so kept
        [0.0, 0.0, 2.95],  # wall above every image: not looked at, so kept
    ])
    expected = np.array([True, True, False, False, True, False, False, False])
    assert not points_in_image(points[6:], CAMERAS[0]).any()  # the last two are outside the images, as meant
    assert np.array_equal(occluded_points(vertices, faces, points, CAMERAS), expected)
    assert np.array_equal(occluded_points_reference(vertices, faces, points, CAMERAS), expected)


def test_fast_path_matches_the_reference_on_surface_samples():
    vertices, faces, _ = _scene_mesh()
    rng = np.random.default_rng(0)
    tri = rng.integers(0, len(faces), 300)
    bary = rng.dirichlet(np.ones(3), 300)
    points = np.einsum("nk,nkd->nd", bary, vertices[faces[tri]])
    points = np.concatenate([points, rng.uniform([-2, -3, 0], [2, 0, 3], (100, 3))])  # off-surface points too
    fast = occluded_points(vertices, faces, points, CAMERAS)
    slow = occluded_points_reference(vertices, faces, points, CAMERAS)
    assert np.array_equal(fast, slow)
    assert 0 < fast.sum() < len(points)


def test_tolerance_decides_a_point_just_behind_a_surface():
    vertices, faces, _ = _scene_mesh()
    point = np.array([[0.0, -0.01, 1.5]])  # 1 cm behind the window's glass, 1 cm in front of the wall
    for tolerance, hidden in ((0.005, True), (0.015, False)):
        assert occluded_points(vertices, faces, point, CAMERAS, tolerance)[0] == hidden
        assert occluded_points_reference(vertices, faces, point, CAMERAS, tolerance)[0] == hidden


def test_degenerate_inputs():
    vertices, faces, _ = _scene_mesh()
    points = np.array([[0.0, 0.0, 1.5]])
    assert not occluded_points(vertices, faces, points, ()).any()  # no camera: nothing is looked at
    assert not occluded_points(vertices, np.zeros((0, 3), np.int64), points, CAMERAS).any()  # nothing can hide it
    assert occluded_points(vertices, faces, np.zeros((0, 3)), CAMERAS).shape == (0,)
    behind = _camera((0.0, 2.0, 1.5), (0.0, 5.0, 1.5))  # looks away from every point
    assert not occluded_points(vertices, faces, points, (behind,)).any()
    with pytest.raises(ValueError, match="points hold NaN"):
        occluded_points(vertices, faces, np.array([[np.nan, 0, 0]]), CAMERAS)
    with pytest.raises(ValueError, match="tolerance"):
        occluded_points(vertices, faces, points, CAMERAS, -0.01)
    with pytest.raises(ValueError, match=r"faces must be \[F, 3\]"):
        occluded_points(vertices, faces[:, :2], points, CAMERAS)
    with pytest.raises(ValueError, match="faces index vertices outside"):
        occluded_points(vertices, faces + len(vertices), points, CAMERAS)


def _scene(vertices, faces, face_labels, views):
    vertex_labels = np.zeros(len(vertices), np.int32)
    for f, label in zip(faces, face_labels):
        vertex_labels[f] = label
    return Scene("s", "synthetic", vertices, np.zeros((len(vertices), 3), np.uint8), vertex_labels,
                 np.zeros(len(vertices), np.int32), faces, views=views)


def test_transfer_labels_a_gaussian_on_the_window_window_only_without_the_hidden_wall():
    vertices, faces, face_labels = _scene_mesh()
    views = tuple(View(f"v{i}", c, None, "train") for i, c in enumerate(CAMERAS))
    scene = _scene(vertices, faces, face_labels, views)
    # label points as the stage makes them: the vertices plus samples on the faces (every quad has its own
    # vertices, so a sample takes its face's label)
    samples, (labels,) = densify_labelled_mesh(vertices, faces, 0.05, scene.semantic)
    points = np.concatenate([vertices, samples])
    semantic = np.concatenate([scene.semantic, labels]).astype(np.int32)
    instance = np.zeros(len(points), np.int32)
    behind_window = np.flatnonzero((labels == WALL) & (np.abs(samples[:, 0]) < 0.2) & (np.abs(samples[:, 2] - 1.5) < 0.2))
    x, _, z = samples[behind_window[0]]
    gaussian = np.array([[x, -0.006, z]])  # on the window, fitted 14 mm too deep: 6 mm from a hidden wall sample
    config = TransferConfig(max_distance=0.1)
    before = transfer_labels(gaussian, points, semantic, instance, None, config).semantic
    occluded = occluded_label_points(scene, points, config.occlusion_tolerance)
    after = transfer_labels(gaussian, points[~occluded], semantic[~occluded], instance[~occluded], None,
                            config).semantic
    assert before[0] == WALL and after[0] == WINDOW
    # no train view, or the option off: nothing is dropped
    assert occluded_label_points(_scene(vertices, faces, face_labels, ()), points, 0.01) is None
    assert occluded_label_points(scene, points, None) is None
    novel_only = tuple(View(v.name, v.camera, None, "novel") for v in views)
    assert occluded_label_points(_scene(vertices, faces, face_labels, novel_only), points, 0.01) is None



def _small_gaussians(means):
    """Small round Gaussians at ``means`` (what the transfer stage reads is their centres)."""
    n = len(means)
    return Gaussians.from_arrays(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), log_scales=np.full((n, 3), -4.0),
                                 opacity_logits=np.zeros(n), sh=np.zeros((n, 1, 3)))


def _stage_config(tmp_path):
    """A build config for ``run_transfer`` on a hand-made scene (no placement refusal: the scene is a few quads)."""
    config = BuildConfig(source="synthetic", root=tmp_path, out=tmp_path / "out")
    return replace(config, transfer=replace(config.transfer, min_on_mesh_share=0.0))


def test_transfer_stage_drops_occluded_points_and_counts_them(tmp_path):
    vertices, faces, face_labels = _scene_mesh()
    views = tuple(View(f"v{i}", c, None, "train") for i, c in enumerate(CAMERAS))
    scene = _scene(vertices, faces, face_labels, views)
    samples, (labels,) = densify_labelled_mesh(vertices, faces, TransferConfig().mesh_sample_spacing, scene.semantic)
    behind_window = np.flatnonzero((labels == WALL) & (np.abs(samples[:, 0]) < 0.2) & (np.abs(samples[:, 2] - 1.5) < 0.2))
    means = samples[behind_window] + np.array([0.0, -0.006, 0.0])  # window Gaussians fitted 14 mm too deep
    n = len(means)
    gaussians, config = _small_gaussians(means), _stage_config(tmp_path)
    truth = np.full(n, WINDOW, np.int32)
    labelled, facts = transfer_stage.run_transfer(scene, gaussians, truth, config)
    assert (labelled.extras["semantic"] == WINDOW).all()
    assert facts["transfer"]["occluded_points"] > 0 and facts["label_accuracy"]["accuracy"] == 1.0
    kept = replace(config, transfer=replace(config.transfer, occlusion_tolerance=None))
    labelled, facts = transfer_stage.run_transfer(scene, gaussians, truth, kept)
    assert (labelled.extras["semantic"] == WALL).all() and facts["transfer"]["occluded_points"] is None


def test_fitted_label_accuracy_is_scored_against_the_surfaces_the_views_see(tmp_path):
    """With no known truth (a fit), the stage scores its labels against the closest mesh triangle; with the occlusion
    test on, triangles whose corners are all occluded are left out, so window Gaussians fitted too deep are scored
    against the window, not against the wall behind it. The wall here is a grid of 10 cm cells, as a room's is."""
    cells = []
    for i in range(40):
        for k in range(30):
            cells.append((_quad((-2 + 0.1 * i, 0, 0.1 * k), (0.1, 0, 0), (0, 0, 0.1)), WALL))
    cells.append((_quad((-0.5, -0.02, 1), (1, 0, 0), (0, 0, 1)), WINDOW))
    vertices, faces, labels = _assemble(cells)
    views = tuple(View(f"v{i}", c, None, "train") for i, c in enumerate(CAMERAS[:2]))
    scene = _scene(vertices, faces, labels, views)
    rng = np.random.default_rng(1)
    means = np.column_stack([rng.uniform(-0.3, 0.3, 50), np.full(50, -0.006), rng.uniform(1.2, 1.8, 50)])
    gaussians, config = _small_gaussians(means), _stage_config(tmp_path)
    labelled, facts = transfer_stage.run_transfer(scene, gaussians, None, config)
    assert (labelled.extras["semantic"] == WINDOW).all()
    assert facts["label_accuracy"] == {"scored": 50, "correct": 50, "accuracy": 1.0}
