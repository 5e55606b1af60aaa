"""Occluded label points (seggaussian.labels.occlusion) and the transfer stage that drops them.

The scene: a wall (the plane y = 0, facing -y) with a window 2 cm in front of it, a box standing on the floor, and
cameras on the -y side looking at the wall. The wall behind the window and the floor under the box are looked at and
never seen; everything else the cameras look at is seen; what no camera looks at keeps its label.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.stages import transfer as transfer_stage
from seggaussian.pipeline.stages.transfer import occluded_label_points
from seggaussian.core.cameras import Camera, look_at
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.scene import Scene, View
from seggaussian.labels.config import TransferConfig
from seggaussian.labels.occlusion import (
    NEAR_PLANE, PointCells, occluded_points, occluded_points_reference, points_in_image,
)
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


# --- Gaussians that lie on a hidden surface keep its label --------------------------------------------------------
def _grid_wall_scene(hidden_label=WALL):
    """The scene of the last test (a wall of 10 cm cells, a window 2 cm in front of it) plus the floor and the box;
    the cells behind the window's middle are labelled ``hidden_label`` (IGNORE_LABEL: an unlabelled hidden patch)."""
    cells = []
    for i in range(40):
        for k in range(30):
            x, z = -2 + 0.1 * i, 0.1 * k
            behind = -0.3 <= x < 0.3 and 1.2 <= z < 1.8
            cells.append((_quad((x, 0, z), (0.1, 0, 0), (0, 0, 0.1)), hidden_label if behind else WALL))
    vertices, faces, labels = _scene_mesh()
    mesh_v, mesh_f, mesh_l = _assemble(cells)
    keep = labels != WALL
    v = np.concatenate([mesh_v, vertices])
    f = np.concatenate([mesh_f, faces[keep] + len(mesh_v)])
    return v, f, np.concatenate([mesh_l, labels[keep]])


def _labels_at_positions(vertices, vertex_labels):
    """``[V]`` sets: the labels of every vertex at each vertex's position (a quad mesh repeats its corners)."""
    _, inverse = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    groups: dict[int, set] = {}
    for group, label in zip(inverse, vertex_labels):
        groups.setdefault(int(group), set()).add(int(label))
    return [groups[int(g)] for g in inverse]


def test_gaussians_at_every_vertex_keep_their_vertex_label_with_few_views(tmp_path):
    """One view: the wall behind the window (a labelled and an unlabelled patch) is never seen. A Gaussian at each vertex keeps that vertex's label, an unlabelled one stays ignore, and a window
    Gaussian fitted 14 mm deep is still window."""
    from seggaussian.core.constants import IGNORE_LABEL

    vertices, faces, face_labels = _grid_wall_scene(hidden_label=IGNORE_LABEL)
    views = (View("v0", CAMERAS[0], None, "train"),)
    scene = _scene(vertices, faces, face_labels, views)
    semantic = scene.semantic.copy()
    for f, label in zip(faces, face_labels):  # _scene gives the last face's label; ignore wins at a shared corner
        if label == IGNORE_LABEL:
            semantic[f] = IGNORE_LABEL
    scene = Scene("s", "synthetic", vertices, scene.colors, semantic, scene.instance, faces, views=views)
    deep_window = np.array([[0.05, -0.006, 1.45], [-0.15, -0.006, 1.65]])
    means = np.concatenate([vertices, deep_window])
    config = _stage_config(tmp_path)
    labelled, facts = transfer_stage.run_transfer(scene, _small_gaussians(means), None, config)
    got = labelled.extras["semantic"]
    allowed = _labels_at_positions(vertices, semantic)
    hidden_ignore = (np.abs(vertices[:, 0]) < 0.25) & (vertices[:, 1] == 0) & (np.abs(vertices[:, 2] - 1.5) < 0.25)
    assert hidden_ignore.sum() > 20 and all(allowed[i] == {IGNORE_LABEL} for i in np.flatnonzero(hidden_ignore))
    wrong = [i for i in range(len(vertices)) if int(got[i]) not in allowed[i]]
    assert wrong == [], f"{len(wrong)} vertex Gaussians changed label, e.g. {vertices[wrong[:3]]}"
    assert (got[: len(vertices)][hidden_ignore] == IGNORE_LABEL).all()
    assert (got[len(vertices):] == WINDOW).all()
    assert facts["transfer"]["on_hidden_surface"] > hidden_ignore.sum() and facts["transfer"]["occluded_points"] > 0
    # without the hidden-surface rule, the occlusion test alone relabelled them (what this test guards against)
    alone = transfer_labels(means, vertices, semantic, scene.instance, None, config.transfer,
                            hidden=occluded_label_points(scene, vertices, config.transfer.occlusion_tolerance))
    assert sum(int(alone.semantic[i]) not in allowed[i] for i in range(len(vertices))) > 20


def test_gaussians_on_hidden_surfaces_between_vertices_keep_their_label(tmp_path):
    """Two views: Gaussians on the hidden faces themselves (the wall behind the window, the floor under the box; not
    at vertices) keep their face's label; 2 mm and 6 mm off the hidden wall, in front of it, they take the window's
    (a fitted Gaussian near a hidden surface is no scan vertex: ``DEFAULT_ON_SURFACE_TOLERANCE``)."""
    vertices, faces, face_labels = _grid_wall_scene()
    views = (View("v0", CAMERAS[0], None, "train"), View("v2", CAMERAS[2], None, "train"))
    scene = _scene(vertices, faces, face_labels, views)
    rng = np.random.default_rng(2)
    n = 200
    on_wall = np.column_stack([rng.uniform(-0.45, 0.45, n), np.zeros(n), rng.uniform(1.05, 1.95, n)])
    on_floor = np.column_stack([rng.uniform(0.82, 1.18, n), rng.uniform(-1.58, -1.22, n), np.zeros(n)])
    in_front = rng.choice([-0.002, -0.006], n)  # 2 and 6 mm in front of the hidden wall
    off_wall = np.column_stack([rng.uniform(-0.45, 0.45, n), in_front, rng.uniform(1.05, 1.95, n)])
    means = np.concatenate([on_wall, on_floor, off_wall])
    labelled, facts = transfer_stage.run_transfer(scene, _small_gaussians(means), None, _stage_config(tmp_path))
    got = labelled.extras["semantic"]
    assert (got[:n] == WALL).all() and (got[n:2 * n] == FLOOR).all() and (got[2 * n:] == WINDOW).all()
    assert facts["transfer"]["on_hidden_surface"] == 2 * n
    assert facts["label_accuracy"]["accuracy"] == 1.0


def test_on_hidden_surface_fast_path_matches_the_reference():
    from seggaussian.labels.occlusion import on_hidden_surface, on_hidden_surface_reference

    vertices, faces, _ = _grid_wall_scene()
    rng = np.random.default_rng(3)
    behind_window = np.flatnonzero((np.abs(vertices[faces].mean(axis=1)[:, 0]) < 0.5)
                                   & (np.abs(vertices[faces].mean(axis=1)[:, 2] - 1.5) < 0.5))
    tri = np.concatenate([rng.integers(0, len(faces), 150), rng.choice(behind_window, 150)])
    bary = rng.dirichlet(np.ones(3), 300)
    on = np.einsum("nk,nkd->nd", bary, vertices[faces[tri]])
    normal_offsets = rng.choice([-1.0, 1.0], (300, 1)) * rng.choice([0.0, 0.001, 0.002, 0.006, 0.05], (300, 1))
    off = on + normal_offsets * rng.normal(size=(300, 3)) / np.sqrt(3)  # some within, some beyond 3 mm
    corners = vertices[rng.choice(len(vertices), 100, replace=False)]
    means = np.concatenate([on, off, corners, [[np.nan, 0, 0], [np.inf, 1, 1]]])
    for cameras in (CAMERAS[:1], CAMERAS):
        fast = on_hidden_surface(means, vertices, faces, cameras)
        slow = on_hidden_surface_reference(means, vertices, faces, cameras)
        assert np.array_equal(fast.rows, slow.rows) and len(fast.rows) > 20
        # the label vertex: the same, or (a point on a shared edge or corner) one at the same position
        assert np.allclose(vertices[fast.vertex], vertices[slow.vertex])
        np.testing.assert_allclose(fast.distances, slow.distances, atol=2e-6)
        assert fast.distances.max() <= 0.003
    empty = on_hidden_surface(means, vertices, faces, ())
    assert len(empty.rows) == 0 and len(on_hidden_surface(np.zeros((0, 3)), vertices, faces, CAMERAS).rows) == 0
    with pytest.raises(ValueError, match="on_surface_tolerance"):
        on_hidden_surface(means, vertices, faces, CAMERAS, on_surface_tolerance=-1.0)
    with pytest.raises(ValueError, match=r"gaussian means must be \[N, 3\]"):
        on_hidden_surface(means[:, :2], vertices, faces, CAMERAS)


def test_closest_point_reference_against_a_dense_sampling():
    from seggaussian.labels.occlusion import closest_points_on_triangles_reference

    rng = np.random.default_rng(4)
    a, b, c = rng.normal(size=(3, 20, 3))
    c[0] = a[0] + 2 * (b[0] - a[0])  # a degenerate (collinear) triangle
    i, j = np.meshgrid(np.arange(201), np.arange(201), indexing="ij")
    keep = i + j <= 200
    w = np.stack([200 - i[keep] - j[keep], i[keep], j[keep]], axis=1) / 200.0
    for point in rng.normal(scale=2.0, size=(10, 3)):
        closest, weights = closest_points_on_triangles_reference(point, a, b, c)
        assert np.allclose(weights.sum(axis=1), 1.0) and (weights >= -1e-12).all()
        assert np.allclose(weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c, closest)
        for f in range(20):
            samples = w[:, :1] * a[f] + w[:, 1:2] * b[f] + w[:, 2:] * c[f]
            dense = np.linalg.norm(samples - point, axis=1).min()
            exact = np.linalg.norm(closest[f] - point)
            assert exact <= dense + 1e-12 and dense - exact < 0.05


def test_a_synthetic_scannetpp_room_turned_into_vertex_gaussians_keeps_every_label(tmp_path):
    """The defect as seen: a ScanNet++-layout room with a Gaussian at every mesh vertex and two train views. With
    the occlusion test on, every Gaussian keeps its vertex's label and unlabelled vertices stay ignore."""
    from seggaussian.core.constants import IGNORE_LABEL
    from seggaussian.sources.layout import find_scene_layout, reader
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    (scene_id,) = synthesize(tmp_path / "raw" / "scannetpp", 1, 0, "scannetpp", SynthConfig(width=64, num_views=8))
    domain, layout_root = find_scene_layout(tmp_path / "raw", scene_id)
    scene = reader(domain).read_scene(layout_root, scene_id)
    scene = replace(scene, views=tuple(v for v in scene.views if v.role == "train")[:2])
    labelled, facts = transfer_stage.run_transfer(scene, _small_gaussians(scene.points), None, _stage_config(tmp_path))
    got = labelled.extras["semantic"]
    allowed = _labels_at_positions(scene.points, scene.semantic)
    wrong = sum(int(got[i]) not in allowed[i] for i in range(len(got)))
    assert wrong == 0 and facts["transfer"]["occluded_points"] > 1000 and facts["transfer"]["on_hidden_surface"] > 1000
    unlabelled = np.array([s == {IGNORE_LABEL} for s in allowed])
    assert unlabelled.any() and (got[unlabelled] == IGNORE_LABEL).all()


@pytest.mark.parametrize("cell_size", [0.05, 0.25, 1.0])
def test_cells_of_a_view_hold_every_point_the_exact_test_accepts(cell_size):
    """``PointCells.maybe_in_image`` is conservative: every point ``points_in_image`` accepts is in a kept cube, for
    points on the image borders and the near plane included (back-projected there), yet most cubes are culled."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-4, 4, size=(20_000, 3))
    cells = PointCells(points, cell_size)
    for trial in range(6):
        eye = rng.uniform(-3, 3, 3)
        width, height = (64, 48) if trial % 2 else (876, 584)
        K = np.array([[rng.uniform(40, 700), rng.uniform(-2, 2), width * rng.uniform(0.3, 0.7)],
                      [0, rng.uniform(40, 700), height * rng.uniform(0.3, 0.7)], [0, 0, 1.0]])
        camera = Camera(K, look_at(eye, eye + rng.normal(size=3)), width, height)
        # points on the edges of the image (u = 0 or just below width, v likewise) and just beyond the near plane
        u = np.concatenate([np.zeros(50), np.full(50, np.nextafter(width, 0)), rng.uniform(0, width, 100)])
        v = np.concatenate([rng.uniform(0, height, 100), np.where(rng.random(100) < 0.5, 0.0, np.nextafter(height, 0))])
        depth = np.concatenate([np.full(100, NEAR_PLANE * 1.0001), rng.uniform(0.01, 5, 100)])
        pixels = np.stack([u, v, np.ones_like(u)], axis=1) @ np.linalg.inv(K).T * depth[:, None]
        edge = (pixels - camera.viewmat[:3, 3]) @ camera.viewmat[:3, :3]  # camera -> world (rotation: R^T)
        probe = np.concatenate([points, edge])
        probe_cells = PointCells(probe, cell_size)
        exact = points_in_image(probe, camera)
        kept = probe_cells.maybe_in_image(camera)[probe_cells.cell_of_point]
        assert exact[len(points):].sum() > 20  # many edge points are inside (rounding puts others just outside)
        assert not (exact & ~kept).any()
        # the compiled search finds exactly the points the exact test accepts, less the skipped ones, edges included
        skip = rng.random(len(probe)) < 0.3
        rows = probe_cells.rows_in_image(camera, skip)
        assert len(np.unique(rows)) == len(rows)
        assert np.array_equal(np.sort(rows), np.flatnonzero(exact & ~skip))
        if cell_size < 1.0:
            assert cells.maybe_in_image(camera).mean() < 0.8  # the cubes behind or beside the camera are culled
