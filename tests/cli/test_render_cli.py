"""``seggaussian render`` and the rasterizer on real 3DGS files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cli.seg_render import command
from seggaussian.core.gaussians import Gaussians
from seggaussian.render import rasterize
from seggaussian.render.quicklook import QuicklookConfig, orbit_camera
from test_render_common import GEOMETRY, random_scene
from shared_data import REALDATA



pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture()
def scene_ply(tmp_path) -> Path:
    from seggaussian.io.ply.writer import write_gaussians_ply

    scene = random_scene(200, 41, sh_degree=1)
    scene["log_scales"] += 1.0
    path = tmp_path / "scene.ply"
    write_gaussians_ply(path, Gaussians.from_arrays(*(scene[k] for k in (*GEOMETRY, "sh"))))
    return path


def read_png(path: Path) -> np.ndarray:
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def test_render_orbit_camera(scene_ply, tmp_path):
    out = tmp_path / "look.png"
    res = CliRunner().invoke(command, [str(scene_ply), "--out", str(out), "--look-at", "--width", "64",
                                       "--height", "48", "--json"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.output)
    assert info["num_gaussians"] == 200 and info["covered_fraction"] > 0.2
    image = read_png(out)
    assert image.shape == (48, 64, 3) and image.max() > 50
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


def test_render_camera_json_and_errors(scene_ply, tmp_path):
    cam = orbit_camera(np.random.default_rng(0).normal(size=(50, 3)),
                       QuicklookConfig(ply=scene_ply, out=tmp_path / "x.png", width=40, height=30))
    cam_path = tmp_path / "cam.json"
    cam_path.write_text(json.dumps({"K": cam.K.tolist(), "viewmat": cam.viewmat.tolist(), "width": 40, "height": 30}))
    out = tmp_path / "cam.png"
    res = CliRunner().invoke(command, [str(scene_ply), "--camera", str(cam_path), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert res.output.strip().splitlines()[-1].startswith(str(out))
    assert read_png(out).shape == (30, 40, 3)

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"K": [[1, 0], [0, 1]], "viewmat": cam.viewmat.tolist(), "width": 40, "height": 30}))
    res = CliRunner().invoke(command, [str(scene_ply), "--camera", str(bad), "--out", str(tmp_path / "b.png")])
    assert res.exit_code != 0
    assert "bad.json" in res.output and "'K'" in res.output
    assert not (tmp_path / "b.png").exists()
    bad.write_text(json.dumps({"K": cam.K.tolist(), "viewmat": cam.viewmat.tolist(), "width": 0, "height": 30}))
    res = CliRunner().invoke(command, [str(scene_ply), "--camera", str(bad), "--out", str(tmp_path / "b.png")])
    assert res.exit_code != 0 and "'width'" in res.output


@pytest.mark.skipif(not (REALDATA / "v3dg_donut_fused_sh0.ply").exists(), reason="shared real data not available")
def test_fast_matches_reference_on_real_gaussians():
    """3,000 Gaussians of a trained scene (real scale, rotation and opacity distributions)."""
    from seggaussian.io.ply.reader import read_gaussians_ply

    gaussians, _ = read_gaussians_ply(REALDATA / "v3dg_donut_fused_sh0.ply")
    rng = np.random.default_rng(0)
    subset = gaussians.subset(np.sort(rng.choice(len(gaussians), 3000, replace=False)))
    cam = orbit_camera(gaussians.means, QuicklookConfig(ply=Path("-"), out=Path("-"), width=40, height=30))
    viewmat, K = torch.from_numpy(cam.viewmat), torch.from_numpy(cam.K)
    t = subset.to_torch()
    results = {}
    for backend in ("reference", "fast"):
        leaves = {k: v.clone().requires_grad_(True) for k, v in t.items()}
        out = rasterize(*(leaves[k] for k in GEOMETRY), viewmat, K, 40, 30, sh=leaves["sh"], backend=backend)
        g = torch.randn(out.image.shape, generator=torch.Generator().manual_seed(1))
        ((out.image * g).sum() + out.alpha.sum()).backward()
        results[backend] = (out, {k: v.grad for k, v in leaves.items()})
    (ref, ref_g), (fast, fast_g) = results["reference"], results["fast"]
    assert float(ref.alpha.detach().mean()) > 0.2
    assert float((ref.image - fast.image).detach().abs().max()) <= 1e-4
    for name in (*GEOMETRY, "sh"):
        scale = float(ref_g[name].abs().max())
        assert scale > 0 and float((ref_g[name] - fast_g[name]).abs().max()) <= 1e-3 * scale, name
