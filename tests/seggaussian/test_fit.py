"""Tests of CPU 3DGS fitting (seggaussian.fit.optimize, seggaussian.fit.losses, cli/seg_fit.py)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.core.constants import SH_C0
from seggaussian.fit.optimize import fit_scene, needs_fit
from seggaussian.fit.densify import densify_and_prune, reset_opacity
from seggaussian.fit.initialize import initialize_gaussians, voxel_downsample
from seggaussian.fit.params import GaussianParameters
from seggaussian.fit.views import FitInputError
from seggaussian.fit.config import FitConfig
from seggaussian.core.gaussians import Gaussians
from seggaussian.fit.losses import fitting_loss, l1_loss, psnr, ssim, ssim_reference
from seggaussian.core.scene import Scene, View

WIDTH, HEIGHT = 32, 24


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: one thread avoids OpenMP start-up and spin costs on the shared 2-core machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# --- a tiny scene: two coloured planes seen by a ring of cameras ----------------------------------


def _plane_gaussians(spacing=0.15) -> Gaussians:
    """Ground truth: a floor (z = 0) and a back wall (y = 1) tiled with coloured flat Gaussians."""
    s = np.arange(-1.0, 1.0 + 1e-9, spacing)
    a, b = np.meshgrid(s, s, indexing="ij")
    a, b = a.ravel(), b.ravel()
    floor = np.stack([a, b, np.zeros_like(a)], 1)
    wall = np.stack([a, np.ones_like(a), b + 1.0], 1)
    means = np.concatenate([floor, wall])
    checker = ((np.floor(means[:, 0] * 2.5) + np.floor(means[:, 1] * 2.5 + means[:, 2] * 2.5)) % 2)[:, None]
    colors = np.where(checker > 0, [0.9, 0.3, 0.2], [0.2, 0.5, 0.8]) * (0.6 + 0.4 * (means[:, 2:3] > 0))
    n = means.shape[0]
    log_scales = np.full((n, 3), np.log(spacing * 0.6))
    log_scales[: floor.shape[0], 2] = np.log(spacing * 0.05)
    log_scales[floor.shape[0]:, 1] = np.log(spacing * 0.05)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    return Gaussians.from_arrays(means, quats, log_scales, np.full(n, 4.0), ((colors - 0.5) / SH_C0)[:, None, :])


def _cameras(count=8):
    k = intrinsics(27.0, 27.0, WIDTH / 2, HEIGHT / 2)
    cams = []
    for i in range(count):
        angle = -0.6 + 1.2 * i / max(count - 1, 1)
        eye = np.array([2.2 * np.sin(angle), 1.0 - 2.6 * np.cos(angle), 1.2])
        cams.append(Camera(k, look_at(eye, np.array([0.0, 0.6, 0.3])), WIDTH, HEIGHT))
    return cams


def _render_np(gaussians: Gaussians, camera: Camera) -> np.ndarray:
    from seggaussian import render

    t = gaussians.to_torch()
    with torch.no_grad():
        out = render.rasterize(
            t["means"], t["quats"], t["log_scales"], t["opacity_logits"],
            torch.from_numpy(camera.viewmat.astype(np.float32)), torch.from_numpy(camera.K.astype(np.float32)),
            camera.width, camera.height, sh=t["sh"], sh_degree=0, background=torch.zeros(3),
        )
    return (out.image.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)


def make_scene(folder: Path, *, num_views=8, novel_every=4, point_noise=0.03, seed=0) -> Scene:
    import cv2

    gt = _plane_gaussians()
    rng = np.random.default_rng(seed)
    views = []
    for i, cam in enumerate(_cameras(num_views)):
        path = folder / f"view{i:02d}.png"
        cv2.imwrite(str(path), _render_np(gt, cam)[:, :, ::-1])
        views.append(View(path.name, cam, path, "novel" if i % novel_every == novel_every - 1 else "train"))
    pts = gt.means.astype(np.float64)[::2] + rng.normal(scale=point_noise, size=(gt.means[::2].shape[0], 3))
    colors = np.clip(gt.dc_colors()[::2] * 255 + rng.normal(scale=25, size=(pts.shape[0], 3)), 0, 255).astype(np.uint8)
    p = pts.shape[0]
    return Scene("tiny", "synthetic", pts, colors, np.zeros(p, np.int32), np.zeros(p, np.int32), views=views)


def small_config(**overrides) -> FitConfig:
    base = dict(iterations=50, init_voxel_size=0.0, sh_degree=1, sh_increase_every=20, densify_from=10,
                densify_until=40, densify_every=10, opacity_reset_every=1000, eval_every=25, patience=0,
                max_gaussians=5000)
    base.update(overrides)
    return FitConfig(**base)


# --- losses and metrics ----------------------------------------------------------------------------


def test_ssim_separable_matches_reference_forward_and_backward():
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(19, 23, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    b = torch.rand(19, 23, 3, generator=gen, dtype=torch.float64)
    fast, ref = ssim(a, b), ssim_reference(a, b)
    torch.testing.assert_close(fast, ref, rtol=1e-10, atol=1e-12)
    (g_fast,) = torch.autograd.grad(fast, a)
    (g_ref,) = torch.autograd.grad(ref, a)
    torch.testing.assert_close(g_fast, g_ref, rtol=1e-9, atol=1e-12)
    small = a[:6, :7, :2].detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: ssim(x, b[:6, :7, :2]), (small,))


def test_ssim_and_psnr_values():
    img = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(1))
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(img, 1.0 - img)) < 0.0  # anti-correlated
    assert float(psnr(img, img)) == pytest.approx(100.0)  # capped by PSNR_MSE_FLOOR, not inf
    assert float(psnr(img, img + 0.1)) == pytest.approx(20.0, abs=1e-4)
    assert float(l1_loss(img, img + 0.25)) == pytest.approx(0.25, abs=1e-6)
    loss = fitting_loss(img, img + 0.25, 0.2)
    assert float(loss) == pytest.approx(0.8 * 0.25 + 0.2 * (1 - float(ssim(img, img + 0.25))), abs=1e-6)
    with pytest.raises(ValueError, match="shape"):
        ssim(img, img[:8])


# --- view-space gradient ------------------------------------------------------------------------------


def test_view_space_gradient_matches_projected_centre_gradient():
    """Recovered from the 3D means' gradient, the NDC gradient equals the true gradient w.r.t. the
    projected centres (rasterizer projection) when the loss depends on the centres only."""
    from seggaussian.fit.densify import view_space_stats
    from seggaussian.fit.views import ViewData
    from seggaussian.render import project_gaussians

    cam = _cameras(3)[1]
    rng = np.random.default_rng(0)
    n = 30
    means = torch.tensor(rng.uniform([-0.8, 0.2, 0.1], [0.8, 0.9, 0.9], size=(n, 3)), requires_grad=True)
    quats = torch.tensor(np.tile([1.0, 0, 0, 0], (n, 1)))
    log_scales = torch.full((n, 3), np.log(0.01), dtype=torch.float64)
    viewmat, K = torch.from_numpy(cam.viewmat), torch.from_numpy(cam.K)
    proj = project_gaussians(means, quats, log_scales, viewmat, K, WIDTH, HEIGHT)
    assert bool(proj.valid.all())
    weights = torch.tensor(rng.normal(size=(n, 2)))
    (grad,) = torch.autograd.grad((proj.means2d * weights).sum(), means)
    view = ViewData("v", cam, torch.zeros(HEIGHT, WIDTH, 3), viewmat.float(), K.float())
    gnorm, visible, radius = view_space_stats(means.detach().float(), grad.float(), log_scales.float(), view)
    expected = (weights * torch.tensor([WIDTH / 2, HEIGHT / 2], dtype=torch.float64)).norm(dim=1)
    torch.testing.assert_close(gnorm.double(), expected, rtol=1e-4, atol=1e-6)
    assert bool(visible.all()) and bool((radius > 0).all())
    # behind the camera: not visible, no radius
    behind = torch.from_numpy(cam.center.astype(np.float32))[None] - 0.5 * torch.from_numpy(
        cam.viewmat[2, :3].astype(np.float32))[None]
    _, vis_b, rad_b = view_space_stats(behind, torch.ones(1, 3), torch.zeros(1, 3), view)
    assert not bool(vis_b[0]) and float(rad_b[0]) == 0.0


# --- initialization ---------------------------------------------------------------------------------


def test_voxel_downsample_and_initialization():
    pts = np.array([[0.0, 0, 0], [0.01, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0], [1.0, 1.0, 0]])
    cols = np.array([[0, 0, 0], [100, 100, 100], [255, 0, 0], [0, 255, 0], [0, 255, 0]], dtype=np.uint8)
    p, c = voxel_downsample(pts, cols, 0.5)
    assert p.shape == (3, 3)
    np.testing.assert_allclose(p[0], [0.005, 0, 0])
    np.testing.assert_allclose(c[0], [50, 50, 50])
    config = FitConfig(init_voxel_size=0.5, sh_degree=2, init_knn=2)
    g, stats = initialize_gaussians(pts, cols, config, np.random.default_rng(0))
    assert len(g) == 3 and g.sh_degree == 2 and stats["voxel_points"] == 3
    # duplicates merged: scale = mean distance to the 2 nearest others, finite
    nn = np.array([(0.995 + np.hypot(0.995, 1)) / 2, (0.995 + 1.0) / 2, (1 + np.hypot(0.995, 1)) / 2])
    np.testing.assert_allclose(np.exp(g.log_scales[:, 0]), nn, rtol=1e-5)
    np.testing.assert_allclose(g.opacities(), 0.1, rtol=1e-5)
    np.testing.assert_allclose(g.dc_colors(), c / 255.0, atol=1e-6)
    np.testing.assert_array_equal(g.sh[:, 1:], 0)
    np.testing.assert_array_equal(g.quats, np.tile([1, 0, 0, 0], (3, 1)))
    # duplicate points without voxels: scales stay finite
    g2, _ = initialize_gaussians(np.zeros((4, 3)), np.zeros((4, 3), np.uint8), FitConfig(init_voxel_size=0.0),
                                 np.random.default_rng(0))
    assert np.isfinite(g2.log_scales).all()
    # the cap subsamples, counted
    g3, stats3 = initialize_gaussians(np.random.default_rng(1).normal(size=(50, 3)), np.zeros((50, 3), np.uint8),
                                      FitConfig(init_voxel_size=0.0, max_gaussians=20), np.random.default_rng(0))
    assert len(g3) == 20 and stats3["subsampled_away"] == 30


# --- densification keeps everything aligned -----------------------------------------------------------


def _params_with_state(n=40, seed=0):
    rng = np.random.default_rng(seed)
    g = Gaussians.from_arrays(rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 3)) - 3,
                              rng.normal(size=n), rng.normal(size=(n, 4, 3)))
    config = small_config(max_gaussians=1000, split_count=2)
    params = GaussianParameters(g, config, extent=1.0)
    # one Adam step creates the state; then tag every row of every moment with its Gaussian's id
    loss = sum(p.sum() for p in params.params.values())
    loss.backward()
    params.optimizer.step()
    ids = torch.arange(n, dtype=torch.float32)
    for p in params.params.values():
        st = params.optimizer.state[p]
        shape = (n,) + (1,) * (p.dim() - 1)
        st["exp_avg"] = ids.reshape(shape).expand_as(p).clone()
        st["exp_avg_sq"] = (ids.reshape(shape) + 0.5).expand_as(p).clone()
    params.stats["grad_accum"] = ids.clone()
    params.stats["grad_count"] = torch.ones(n)
    params.stats["max_radius"] = ids.clone()
    return params, config


def _assert_aligned(params: GaussianParameters):
    n = len(params)
    for name, p in params.params.items():
        assert p.shape[0] == n, name
        group = next(g for g in params.optimizer.param_groups if g["name"] == name)
        assert group["params"][0] is p, f"optimizer group {name} does not hold the live parameter"
        st = params.optimizer.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape, name
    assert len(params.optimizer.state) == len(params.params)  # no stale state of swapped-out tensors
    for key, value in params.stats.items():
        assert value.shape == (n,), key


def test_select_and_append_keep_tensors_and_adam_state_aligned():
    params, _ = _params_with_state()
    before = {k: v.detach().clone() for k, v in params.params.items()}
    keep = torch.tensor([3, 5, 7, 11, 13])
    params.select(keep)
    _assert_aligned(params)
    for name, p in params.params.items():
        torch.testing.assert_close(p.detach(), before[name][keep])
        ea = params.optimizer.state[p]["exp_avg"].reshape(5, -1)
        assert (ea == keep.float()[:, None]).all(), name
    extra = {k: v[:2] * 0 + 1 for k, v in params.params.items()}
    params.append(extra)
    _assert_aligned(params)
    for p in params.params.values():
        st = params.optimizer.state[p]
        assert (st["exp_avg"][5:] == 0).all() and (st["exp_avg_sq"][5:] == 0).all()
        assert (st["exp_avg"][:5].reshape(5, -1) == keep.float()[:, None]).all()
    assert (params.stats["grad_accum"][5:] == 0).all()
    # the optimizer still steps on the swapped tensors
    sum(p.sum() for p in params.params.values()).backward()
    params.optimizer.step()


def test_densify_and_prune_alignment_and_counts():
    params, config = _params_with_state(n=40)
    n0 = len(params)
    # every Gaussian gets a high view-space gradient; small ones clone, large ones split
    params.stats["grad_accum"] = torch.full((n0,), 1.0)
    with torch.no_grad():
        params.params["log_scales"][:20] = np.log(0.001)  # small: clone
        params.params["log_scales"][20:] = np.log(0.05)  # large: split
        params.params["opacity_logits"][:] = 2.0
        params.params["opacity_logits"][0] = -10.0  # transparent: pruned (its clone too)
    means_before = params.params["means"].detach().clone()
    counts = densify_and_prune(params, config, extent=1.0, prune_large=False,
                               generator=torch.Generator().manual_seed(0))
    _assert_aligned(params)
    assert counts["cloned"] == 20 and counts["split"] == 20
    assert counts["gaussians"] == 20 + 20 + 40 - 2  # originals kept 20, clones 20, children 40, minus 2 transparent
    # split children have parent scales / 1.6, and lie near their parent
    children = params.params["log_scales"].detach().exp()
    assert torch.isclose(children, torch.tensor(0.05 / 1.6)).all(dim=1).sum() == 40
    assert ((params.params["means"].detach()[-40:] - means_before[20:].repeat(2, 1)).norm(dim=1) < 0.05 * 6).all()
    # statistics were reset
    assert (params.stats["grad_accum"] == 0).all()


def test_densify_respects_cap_and_prunes_large():
    params, _ = _params_with_state(n=40)
    config = small_config(max_gaussians=45)
    params.stats["grad_accum"] = torch.linspace(1.0, 2.0, 40)
    with torch.no_grad():
        params.params["log_scales"][:] = np.log(0.001)
        params.params["opacity_logits"][:] = 2.0
        params.params["log_scales"][39] = np.log(5.0)  # oversized in world space
    counts = densify_and_prune(params, config, extent=1.0, prune_large=True, generator=torch.Generator())
    _assert_aligned(params)
    assert counts["cloned"] == 4 and counts["split"] == 1  # 5 free slots, strongest first: the large one (split) + 4
    assert counts["gaussians"] <= 45


def test_opacity_reset_zeroes_its_state():
    params, _ = _params_with_state()
    reset_opacity(params, 0.01)
    _assert_aligned(params)
    p = params.params["opacity_logits"]
    assert float(torch.sigmoid(p.detach()).max()) <= 0.01 + 1e-6
    assert (params.optimizer.state[p]["exp_avg"] == 0).all()


# --- the fit -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("tiny"))


def test_fit_loss_falls_and_psnr_rises(tiny_scene):
    result = fit_scene(tiny_scene, small_config(iterations=50, eval_every=10), seed=0, progress=False)
    m = result.metrics
    assert m["iterations"] == 50 and m["early_stop_reason"] == "completed all iterations"
    hist = result.history
    assert [h["iteration"] for h in hist] == [0, 10, 20, 30, 40, 50]
    assert hist[-1]["loss"] < 0.8 * hist[1]["loss"]  # mean training loss of the last 10 steps vs the first 10
    assert hist[-1]["heldout_psnr"] > hist[0]["heldout_psnr"] + 2.0  # held-out (novel) views
    assert m["novel_psnr"] == pytest.approx(hist[-1]["heldout_psnr"], abs=1e-4)
    assert 0.0 < m["novel_ssim"] <= 1.0 and m["novel_views"] == 2 and m["train_views"] == 6
    assert np.isfinite(result.gaussians.means).all() and len(result.gaussians) > 0
    assert result.gaussians.sh_degree == 1
    assert any(d["cloned"] + d["split"] > 0 for d in m["densification"])


def test_same_seed_same_ply_bytes(tiny_scene, tmp_path):
    from seggaussian.io.ply.writer import write_gaussians_ply

    config = small_config(iterations=15, eval_every=0)  # densification at 10 included
    paths = []
    for i, seed in enumerate((7, 7, 8)):
        r = fit_scene(tiny_scene, config, seed=seed, progress=False)
        paths.append(tmp_path / f"out{i}.ply")
        write_gaussians_ply(paths[-1], r.gaussians)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    assert paths[0].read_bytes() != paths[2].read_bytes()


def test_early_stop_reason(tiny_scene):
    config = small_config(iterations=400, eval_every=5, patience=2, min_psnr_gain=100.0, densify_until=10,
                          densify_from=5, densify_every=5)
    r = fit_scene(tiny_scene, config, seed=0, progress=False)
    assert r.metrics["early_stop_reason"].startswith("early stop")
    assert r.metrics["iterations"] == 15  # first eval sets best; 2 evals without gain after densification


def test_holdout_views_and_time_budget(tiny_scene):
    r = fit_scene(tiny_scene, small_config(iterations=10, eval_every=5, holdout_views=2), seed=0, progress=False)
    assert r.metrics["holdout_views"] == 2 and r.metrics["train_views"] == 4
    r = fit_scene(tiny_scene, small_config(iterations=10_000, time_budget_seconds=1e-9), seed=0, progress=False)
    assert r.metrics["iterations"] == 1 and r.metrics["early_stop_reason"].startswith("time budget")


# --- bad input ---------------------------------------------------------------------------------------


def test_bad_inputs(tmp_path):
    import cv2

    scene = make_scene(tmp_path, num_views=4)
    config = small_config(iterations=2, eval_every=0)
    no_views = Scene("s", "synthetic", scene.points, scene.colors, scene.semantic, scene.instance, views=())
    with pytest.raises(FitInputError, match="no train views"):
        fit_scene(no_views, config, seed=0, progress=False)
    no_points = Scene("s", "synthetic", np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32),
                      np.zeros(0, np.int32), views=scene.views)
    with pytest.raises(FitInputError, match="no initial points"):
        fit_scene(no_points, config, seed=0, progress=False)
    nan_points = scene.points.copy()
    nan_points[3] = np.nan
    with pytest.raises(FitInputError, match="non-finite"):
        fit_scene(Scene("s", "synthetic", nan_points, scene.colors, scene.semantic, scene.instance,
                        views=scene.views), config, seed=0, progress=False)
    # a non-finite pose (Camera refuses it at construction; a camera built around that check still fails here)
    cam = scene.views[0].camera
    bad_cam = Camera(cam.K, cam.viewmat, cam.width, cam.height)
    vm = bad_cam.viewmat.copy()
    vm[0, 3] = np.inf
    object.__setattr__(bad_cam, "viewmat", vm)
    bad_view = View("bad", bad_cam, scene.views[0].image_path)
    with pytest.raises(FitInputError, match="bad.*not finite"):
        fit_scene(Scene("s", "synthetic", scene.points, scene.colors, scene.semantic, scene.instance,
                        views=(bad_view,) + scene.views[1:]), config, seed=0, progress=False)
    with pytest.raises(ValueError, match="NaN/Inf"):
        Camera(cam.K, vm, cam.width, cam.height)
    # wrong image size
    wrong = tmp_path / "wrong.png"
    cv2.imwrite(str(wrong), np.zeros((HEIGHT + 2, WIDTH, 3), np.uint8))
    views = (View("w", cam, wrong),) + scene.views[1:]
    with pytest.raises(FitInputError, match=r"wrong\.png.*32x26.*32x24"):
        fit_scene(Scene("s", "synthetic", scene.points, scene.colors, scene.semantic, scene.instance, views=views),
                  config, seed=0, progress=False)
    # missing / unreadable image
    for path in (tmp_path / "missing.png", tmp_path / "garbage.png"):
        if path.name == "garbage.png":
            path.write_bytes(b"not an image")
        views = (View("m", cam, path),) + scene.views[1:]
        with pytest.raises(FitInputError, match=path.name):
            fit_scene(Scene("s", "synthetic", scene.points, scene.colors, scene.semantic, scene.instance,
                            views=views), config, seed=0, progress=False)
    with pytest.raises(ValueError, match="iterations"):
        FitConfig(iterations=0)


def test_needs_fit(tmp_path):
    ply = tmp_path / "trained.ply"
    ply.write_bytes(b"ply\n")
    assert needs_fit("auto", None) is True
    assert needs_fit("auto", ply) is False
    assert needs_fit("always", ply) is True
    assert needs_fit("never", None) is False
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        needs_fit("auto", tmp_path / "nope.ply")
    with pytest.raises(ValueError, match="fit mode"):
        needs_fit("sometimes", None)


# --- command line ------------------------------------------------------------------------------------


def test_cli_fit_writes_ply_and_metrics(tmp_path):
    from click.testing import CliRunner

    from cli.seggaussian_cli import main
    from seggaussian.io.ply.reader import read_gaussians_ply
    from seggaussian.sources.synthetic import generate as synthetic
    raw = tmp_path / "raw"
    (scene_id,) = synthetic.synthesize(raw / "scannetpp", 1, 0, "scannetpp",
                                       synthetic.SynthConfig(width=48, num_views=9, max_edge=0.25))
    out = tmp_path / "fit" / f"{scene_id}.ply"
    args = ["fit", "--source", "synthetic", "--root", str(raw), "--scene", scene_id, "--out", str(out),
            "--iterations", "2", "--max-gaussians", "1000", "--seed", "1"]
    result = CliRunner().invoke(main, args + ["--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert payload["iterations"] == 2 and payload["gaussians"] == 1000
    assert payload["init"]["subsampled_away"] > 0  # the cap subsampled the initial points, counted
    assert payload["novel_psnr"] > 5.0 and payload["novel_views"] == 2
    stored = json.loads((tmp_path / "fit" / f"{scene_id}.fit.json").read_text())
    assert stored["metrics"]["novel_psnr"] == pytest.approx(payload["novel_psnr"])
    assert stored["config"]["iterations"] == 2 and stored["ply"] == out.name
    gaussians, _ = read_gaussians_ply(out)
    assert len(gaussians) == 1000 and gaussians.sh_degree == 3
    assert sorted(p.name for p in out.parent.iterdir()) == sorted([out.name, f"{scene_id}.fit.json"])  # no temp
    # text mode ends with the one-line summary
    text = CliRunner().invoke(main, args + ["--no-progress"])
    assert text.exit_code == 0 and text.output.strip().splitlines()[-1].startswith(f"{out}: scene {scene_id}")
    # a scene that is not there: a clear error, no traceback
    bad = CliRunner().invoke(main, ["fit", "--root", str(raw), "--scene", "nope", "--out", str(tmp_path / "x.ply")])
    assert bad.exit_code != 0 and "no scene 'nope'" in bad.output and "Traceback" not in bad.output


def test_config_with_iterations_scales_the_schedule():
    base = FitConfig()
    short = base.with_iterations(300)
    assert short.iterations == 300
    assert short.densify_until == round(base.densify_until / 10) and short.opacity_reset_every == 60
    assert short.sh_increase_every == 30 and short.eval_every == 25
    assert short.densify_every == (short.densify_until - short.densify_from) // 3  # at least 3 rounds
    assert base.with_iterations(1000).densify_every == base.densify_every  # rounds keep their view count
    assert short.densify_until / short.iterations == pytest.approx(base.densify_until / base.iterations)
    tiny = base.with_iterations(1)
    assert tiny.densify_every >= 1 and tiny.opacity_reset_every >= 1 and tiny.sh_increase_every >= 1
    assert base.with_iterations(base.iterations) == base


# --- keep the best held-out state ---------------------------------------------------------------------


def test_early_stop_returns_the_best_heldout_state(tiny_scene, monkeypatch):
    """Means that jump far every step make the held-out PSNR fall after the start: early stop must hand
    back the snapshot taken at the best evaluation, its novel metrics and its iteration, not the last state."""
    snapshots = []
    original = GaussianParameters.snapshot

    def recording(self):
        snap = original(self)
        snapshots.append({k: v.clone() for k, v in snap.items()})
        return snap

    monkeypatch.setattr(GaussianParameters, "snapshot", recording)
    config = small_config(iterations=200, eval_every=5, patience=3, min_psnr_gain=0.0, densify_from=5,
                          densify_until=10, densify_every=5, lr_means_init=0.05, lr_means_final=0.05)
    r = fit_scene(tiny_scene, config, seed=0, progress=False)
    m, hist = r.metrics, r.history
    assert m["early_stop_reason"].startswith("early stop")
    psnrs = [h["heldout_psnr"] for h in hist]
    best = int(np.argmax(psnrs))
    assert psnrs[best] > psnrs[-1] + 1.0  # the held-out PSNR really degraded
    assert m["returned_iteration"] == hist[best]["iteration"] < m["iterations"]
    assert m["best_heldout_psnr"] == pytest.approx(psnrs[best])
    # the novel views are the held-out views here: the returned state scores the best PSNR again
    assert m["novel_psnr"] == pytest.approx(psnrs[best], abs=1e-4)
    snap = snapshots[-1]  # snapshots are taken on improvements only: the last one is the best
    np.testing.assert_array_equal(r.gaussians.means, snap["means"].numpy())
    np.testing.assert_array_equal(r.gaussians.opacity_logits, snap["opacity_logits"].numpy())
    np.testing.assert_array_equal(r.gaussians.sh[:, :1], snap["f_dc"].numpy())


def test_keep_best_off_returns_the_last_state(tiny_scene):
    config = small_config(iterations=30, eval_every=5, densify_from=5, densify_until=10, densify_every=5,
                          lr_means_init=0.05, lr_means_final=0.05, keep_best=False)
    r = fit_scene(tiny_scene, config, seed=0, progress=False)
    assert r.metrics["returned_iteration"] == 30
    assert r.metrics["novel_psnr"] == pytest.approx(r.history[-1]["heldout_psnr"], abs=1e-4)


def test_no_opacity_reset_when_turned_off(tiny_scene):
    # lr_opacity 0: what the reset at iteration 10 sets stays to the end; the one due at 20 has no iteration left to
    # recover in, so it goes
    config = small_config(iterations=20, eval_every=0, opacity_reset_every=10, densify_until=40, init_opacity=0.5,
                          lr_opacity=0.0)
    opacity, metrics = {}, {}
    for reset in (True, False):
        r = fit_scene(tiny_scene, replace(config, opacity_reset=reset), seed=0, progress=False)
        opacity[reset] = float((1.0 / (1.0 + np.exp(-r.gaussians.opacity_logits))).max())
        metrics[reset] = r.metrics
    assert opacity[True] <= 0.01 + 1e-6  # clamped at 10
    assert metrics[True]["opacity_resets"] == [10] and metrics[True]["skipped_opacity_resets"] == [20]
    assert opacity[False] > 0.3
    assert metrics[False]["opacity_resets"] == [] and metrics[False]["skipped_opacity_resets"] == []


def test_a_reset_needs_a_whole_interval_left_in_the_iterations_and_the_time_budget():
    from seggaussian.fit.optimize import iterations_left

    config = small_config(iterations=3000, opacity_reset_every=600)
    times = [0.0, 0.1, 0.2, 0.3]  # 0.1 s per iteration
    assert iterations_left(600, config, 5.0, times) == 2400  # no budget: the iterations alone
    assert iterations_left(2500, config, 5.0, times) == 500
    budget = replace(config, time_budget_seconds=90.0)
    assert iterations_left(600, budget, 60.0, times) == pytest.approx(300.0)  # 30 s left at 0.1 s per iteration
    assert iterations_left(600, budget, 95.0, times) == 0.0  # over budget
    assert iterations_left(600, budget, 10.0, times) == pytest.approx(800.0)  # 80 s left
    assert iterations_left(600, budget, 10.0, [0.0, 0.01, 0.02]) == 2400  # the iterations bind first
    assert iterations_left(600, budget, 10.0, [0.0]) == 2400  # no pace measured yet
    assert iterations_left(600, budget, 10.0, [1.0, 1.0]) == 2400  # a clock that did not move


# --- depth supervision ------------------------------------------------------------------------------


def _depth_loss_loop(depth, target, mask):
    total, count = 0.0, 0
    for i in range(depth.shape[0]):
        for j in range(depth.shape[1]):
            if target[i, j] > 0 and (mask is None or mask[i, j]):
                total += abs(float(depth[i, j]) - float(target[i, j])) / float(target[i, j])
                count += 1
    return total / count if count else 0.0


def test_depth_loss_matches_loop_reference_and_gradient():
    from seggaussian.fit.losses import depth_loss

    g = torch.Generator().manual_seed(0)
    target = torch.rand(7, 9, generator=g) * 3.0 + 0.5
    target[torch.rand(7, 9, generator=g) < 0.3] = 0.0  # misses
    mask = torch.rand(7, 9, generator=g) > 0.2
    depth = (torch.rand(7, 9, generator=g) * 4.0).requires_grad_(True)
    for m in (None, mask):
        loss = depth_loss(depth, target, m)
        assert float(loss) == pytest.approx(_depth_loss_loop(depth.detach(), target, m), rel=1e-5)
    loss = depth_loss(depth, target, mask)
    loss.backward()
    known = (target > 0) & mask
    expected = torch.where(known, torch.sign(depth.detach() - target) / target.clamp_min(1e-9), torch.zeros_like(target))
    torch.testing.assert_close(depth.grad, expected / known.sum(), rtol=1e-5, atol=1e-7)
    assert float(depth_loss(depth, torch.zeros_like(target))) == 0.0


def test_mesh_depth_of_views_matches_reference_raycaster(tiny_scene):
    """The fit's depth targets are the mesh's camera z per pixel centre (the slow reference caster agrees)."""
    from seggaussian.fit.views import load_views, with_mesh_depth
    from seggaussian.sources.raycast import cast_rays_reference

    points = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0],
                       [-1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    views = load_views(tiny_scene.views_with_role("train")[:2], 1.0)
    assert all(v.depth is None for v in with_mesh_depth(views, points, None))
    for view in with_mesh_depth(views, points, faces):
        ref = cast_rays_reference(points, faces, view.camera).depth
        np.testing.assert_allclose(view.depth.numpy(), ref, rtol=1e-4, atol=1e-4)
        assert (view.depth > 0).float().mean() > 0.5


def test_depth_term_runs_and_pulls_rendered_depth_to_the_mesh(tiny_scene):
    import dataclasses

    points = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0],
                       [-1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    # the two planes of the tiny scene as a mesh; the scene's points stay the noisy initial cloud
    init_pts = tiny_scene.points
    mesh_scene = dataclasses.replace(tiny_scene, points=np.concatenate([init_pts, points]),
                                     colors=np.concatenate([tiny_scene.colors, np.full((8, 3), 128, np.uint8)]),
                                     faces=faces + init_pts.shape[0],
                                     instance=np.zeros(init_pts.shape[0] + 8, np.int32),
                                     semantic=np.zeros(init_pts.shape[0] + 8, np.int32))
    r = fit_scene(mesh_scene, small_config(iterations=20, eval_every=10, lambda_depth=0.5), seed=0, progress=False)
    assert r.metrics["depth_views"] == r.metrics["train_views"] == 6
    assert np.isfinite(r.metrics["novel_psnr"])


def test_presets():
    profile = FitConfig.profile()
    assert FitConfig.preset("profile") == profile and FitConfig.preset("default") == FitConfig()
    assert profile.sh_degree == 3 and not profile.opacity_reset and profile.lambda_depth > 0 and profile.keep_best
    assert profile.densify_until < profile.iterations
    with pytest.raises(ValueError, match="preset"):
        FitConfig.preset("fast")
