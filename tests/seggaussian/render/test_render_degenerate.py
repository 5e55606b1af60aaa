"""Degenerate inputs to seggaussian.render give finite outputs and gradients, on every backend."""

from __future__ import annotations

import math

import pytest
import torch

from seggaussian.render import compute_blend_weights, rasterize
from test_render_common import GEOMETRY, HEIGHT, WIDTH, camera, random_scene


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def camera_centre(viewmat: torch.Tensor) -> torch.Tensor:
    r = viewmat[:3, :3]
    return -(r.T @ viewmat[:3, 3]).float()


def edited_scene(kind: str) -> dict:
    scene = random_scene(20, 21)
    viewmat, _ = camera()
    centre = camera_centre(viewmat)
    forward = viewmat[2, :3].float()  # camera z axis in world coordinates
    if kind == "zero_scales":
        scene["log_scales"][:5] = -math.inf
        scene["log_scales"][5:10, 0] = -100.0
    elif kind == "huge_scales":
        scene["log_scales"][:3] = 88.0
        scene["log_scales"][3:6, 1] = math.inf
        scene["log_scales"][6:9] = 40.0
    elif kind == "saturated_opacity":
        scene["opacity_logits"][::2] = 50.0
        scene["opacity_logits"][1::2] = -50.0
        scene["opacity_logits"][:2] = torch.tensor([math.inf, -math.inf])
    elif kind == "odd_quats":
        scene["quats"][:4] = 0.0
        scene["quats"][4:8] *= 1e6
        scene["quats"][8:12] *= 1e-9
    elif kind == "behind_and_on_camera_plane":
        scene["means"][:4] = centre  # at the camera centre
        scene["means"][4:8] = centre + torch.randn(4, 3) * 0.5 - 2.0 * forward  # behind
        plane = torch.randn(4, 3)
        plane = plane - (plane @ forward)[:, None] * forward  # exactly on the camera plane z = 0
        scene["means"][8:12] = centre + plane
    elif kind == "one_point":
        scene["means"][:] = torch.tensor([0.1, 0.2, -0.1])
    elif kind == "sees_nothing":
        scene["means"] = centre - 3.0 * forward + 0.1 * torch.randn(20, 3)
    return scene


KINDS = ["zero_scales", "huge_scales", "saturated_opacity", "odd_quats", "behind_and_on_camera_plane", "one_point",
         "sees_nothing"]


def run(scene: dict, backend: str, num: int | None = None):
    viewmat, K = camera()
    leaves = {k: (v[:num] if num is not None else v).clone().requires_grad_(True) for k, v in scene.items()}
    out = rasterize(*(leaves[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, sh=leaves["sh"],
                    background=torch.tensor([0.2, 0.3, 0.4]), backend=backend)
    (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
    grads = {k: v.grad for k, v in leaves.items() if k != "features"}
    return out, grads


@pytest.mark.parametrize("kind", KINDS)
def test_degenerate_scene_is_finite_and_backends_agree(kind):
    scene = edited_scene(kind)
    results = {backend: run(scene, backend) for backend in ("reference", "fast")}
    for backend, (out, grads) in results.items():
        for name, x in zip(out._fields, out):
            assert torch.isfinite(x).all(), f"{backend} {kind}: {name} not finite"
        for name, g in grads.items():
            assert g is not None and torch.isfinite(g).all(), f"{backend} {kind}: grad {name} not finite"
    (ref, ref_grads), (fast, fast_grads) = results["reference"], results["fast"]
    assert float((ref.image - fast.image).detach().abs().max()) <= 1e-4
    for name in ref_grads:
        scale = float(ref_grads[name].abs().max()) or 1.0
        assert float((ref_grads[name] - fast_grads[name]).abs().max()) <= 1e-3 * scale, name
    if kind == "sees_nothing":
        assert float(fast.alpha.max()) == 0.0
        assert torch.allclose(fast.image, torch.tensor([0.2, 0.3, 0.4]).expand(HEIGHT, WIDTH, 3))
        assert float(fast.depth.abs().max()) == 0.0
    if kind == "huge_scales":  # a huge Gaussian covers the whole image
        assert float(fast.alpha.detach().min()) > 0.0


@pytest.mark.parametrize("num", [0, 1])
@pytest.mark.parametrize("backend", ["reference", "fast", "torch"])
def test_zero_and_one_gaussian(num, backend):
    scene = random_scene(3, 22)
    scene["means"][0] = 0.0
    scene["log_scales"][0] = -1.0
    out, grads = run(scene, backend, num=num)
    assert out.image.shape == (HEIGHT, WIDTH, 3)
    assert torch.isfinite(out.image).all() and torch.isfinite(out.depth).all()
    assert all(torch.isfinite(g).all() for g in grads.values())
    if num == 0:
        assert float(out.alpha.max()) == 0.0
    else:
        assert float(out.alpha.max()) > 0.1


def test_blend_weights_on_degenerate_scenes():
    viewmat, K = camera()
    for kind in KINDS:
        scene = edited_scene(kind)
        bw = compute_blend_weights(*(scene[k] for k in GEOMETRY), viewmat, K, WIDTH, HEIGHT, top_k=4)
        assert torch.isfinite(bw.weights).all() and torch.isfinite(bw.residual_alpha).all(), kind
        assert int(bw.ids.max()) < 20
