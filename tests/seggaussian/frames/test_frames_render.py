"""The SH rotation test of the issue: an SH-3 scene rendered from a camera equals the transformed scene rendered
from the transformed camera (RGB, alpha, depth), and the per-band SH colours along the view directions agree."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from frames_common import random_gaussians, random_rotation

from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.frames.similarity import Similarity, transform_gaussians
from seggaussian.render.projection import project_gaussians
from seggaussian.render.rasterize import camera_tensors, render_gaussians
from seggaussian.render.sh import evaluate_sh

WIDTH, HEIGHT = 40, 30


def _moved_camera(camera: Camera, sim: Similarity) -> Camera:
    """The camera that sees ``sim``-moved points where ``camera`` saw the originals.

    For x' = s M x + t and y = V_R x + V_t (camera coordinates): V_R M^T (x' - t) = s V_R x, so
    viewmat' = [V_R M^T | s V_t - V_R M^T t] gives y' = s y: the same pixels (the projection divides by depth),
    depth times s. It stays orthonormal; for a reflection M it is improper, as the mirrored world needs."""
    r, t = camera.viewmat[:3, :3], camera.viewmat[:3, 3]
    viewmat = np.eye(4)
    viewmat[:3, :3] = r @ sim.rotation.T
    viewmat[:3, 3] = sim.scale * t - r @ sim.rotation.T @ sim.translation
    return Camera(camera.K, viewmat, camera.width, camera.height)


def _sims() -> dict[str, Similarity]:
    rng = np.random.default_rng(20)
    return {
        "rotation": Similarity(random_rotation(rng), rng.normal(size=3), 1.0),
        "rotation_scaled": Similarity(random_rotation(rng), rng.normal(size=3) * 3, 1.7),
        "reflection": Similarity(random_rotation(rng) @ np.diag([-1.0, 1.0, 1.0]), rng.normal(size=3), 1.0),
        "reflection_scaled": Similarity(np.diag([1.0, -1.0, 1.0]) @ random_rotation(rng), rng.normal(size=3), 0.6),
    }


@pytest.fixture(scope="module")
def scene():
    g = random_gaussians(120, 3, seed=21, spread=0.5)
    g = type(g).from_arrays(g.means, g.quats, g.log_scales - 0.5, g.opacity_logits, g.sh * 1.5, g.extras)
    camera = Camera(intrinsics(36.0, 36.0, WIDTH / 2 + 0.3, HEIGHT / 2 - 0.2),
                    look_at(np.array([0.4, -1.2, -3.0]), np.zeros(3), up=(0.0, -1.0, 0.0)), WIDTH, HEIGHT)
    return g, camera


@pytest.mark.parametrize("name", list(_sims()))
def test_transformed_scene_from_transformed_camera_renders_the_same_image(one_torch_thread, scene, name):
    g, camera = scene
    sim = _sims()[name]
    moved, moved_camera = transform_gaussians(g, sim), _moved_camera(camera, sim)
    before = render_gaussians(g, camera, backend="reference")
    after = render_gaussians(moved, moved_camera, backend="reference")
    assert before.alpha.max() > 0.9 and before.image.std() > 0.05  # a real picture, with SH colour variation
    np.testing.assert_allclose(after.image.numpy(), before.image.numpy(), atol=2e-5)
    np.testing.assert_allclose(after.alpha.numpy(), before.alpha.numpy(), atol=2e-5)
    np.testing.assert_allclose(after.depth.numpy(), sim.scale * before.depth.numpy(), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", list(_sims()))
def test_each_band_gives_the_same_colour_along_the_renderers_view_directions(one_torch_thread, scene, name):
    g, camera = scene
    sim = _sims()[name]
    moved, moved_camera = transform_gaussians(g, sim), _moved_camera(camera, sim)

    def view_dirs(gaussians, cam):
        t = gaussians.to_torch()
        viewmat, K = camera_tensors(cam)
        return project_gaussians(t["means"], t["quats"], t["log_scales"], viewmat, K, cam.width, cam.height).view_dirs

    dirs, moved_dirs = view_dirs(g, camera), view_dirs(moved, moved_camera)
    np.testing.assert_allclose(moved_dirs.numpy(), dirs.numpy() @ sim.rotation.T, atol=1e-6)
    for band in range(4):
        keep = torch.zeros(1, 16, 1, dtype=torch.float64)
        keep[:, band * band:(band + 1) ** 2] = 1.0
        sh, moved_sh = (torch.from_numpy(x.sh.astype(np.float64)) * keep for x in (g, moved))
        colour = evaluate_sh(sh, dirs, 3)
        moved_colour = evaluate_sh(moved_sh, moved_dirs, 3)
        assert band == 0 or colour.abs().max() > 0.05
        np.testing.assert_allclose(moved_colour.numpy(), colour.numpy(), atol=5e-6)


def test_unrotated_sh_would_be_wrong(one_torch_thread, scene):
    """Control: moving means and covariances but not the SH changes the picture (the test above is sensitive)."""
    g, camera = scene
    sim = _sims()["rotation"]
    moved = transform_gaussians(g, sim)
    wrong = type(g)(moved.means, moved.quats, moved.log_scales, moved.opacity_logits, g.sh)
    before = render_gaussians(g, camera, backend="reference").image.numpy()
    after = render_gaussians(wrong, _moved_camera(camera, sim), backend="reference").image.numpy()
    assert np.abs(after - before).max() > 0.05
