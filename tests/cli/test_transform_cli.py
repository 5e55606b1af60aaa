"""``seggaussian import`` / ``render`` with ``--transform`` and ``--from-frame``: the splat lands in the scene's frame,
the report says which transform, and a bad transform is one line with exit status 1."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.seggaussian_cli import main
from seggaussian.frames.similarity import Similarity, transform_gaussians
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians_raw
from seggaussian.io.ply.writer import write_gaussians_ply


@pytest.fixture()
def splat(tmp_path) -> tuple[Path, Gaussians]:
    rng = np.random.default_rng(4)
    n = 300
    quats = rng.normal(size=(n, 4))
    g = Gaussians.from_arrays(rng.normal(size=(n, 3)), quats / np.linalg.norm(quats, axis=1, keepdims=True),
                              rng.normal(-3, 0.3, (n, 3)), rng.normal(0, 1, n), rng.normal(0, 0.3, (n, 16, 3)))
    path = tmp_path / "scene.ply"
    write_gaussians_ply(path, g)
    return path, g


def test_import_with_transform_moves_the_splat_and_reports_it(splat, tmp_path):
    path, g = splat
    t = np.radians(30)
    world_from_splat = Similarity(np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]]),
                                  np.array([1.0, -2.0, 0.5]), 2.5)
    spec = tmp_path / "t.json"
    spec.write_text(json.dumps({"world_from_splat": world_from_splat.matrix.tolist()}))
    result = CliRunner().invoke(main, ["import", str(path), "--out", str(tmp_path / "out"), "--transform", str(spec),
                                       "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert payload["frame"]["transform"] and payload["frame"]["scale"] == pytest.approx(2.5)
    report = json.loads((tmp_path / "out" / "scene.import.json").read_text())
    assert report["frame"]["world_from_splat"] == payload["frame"]["world_from_splat"]
    got, _ = read_gaussians_raw(tmp_path / "out" / "scene.ply")
    want = transform_gaussians(g, world_from_splat)
    np.testing.assert_allclose(got.means, want.means, atol=1e-5)
    np.testing.assert_allclose(got.log_scales, want.log_scales, atol=1e-5)
    np.testing.assert_allclose(got.sh, want.sh, atol=1e-5)


def test_from_frame_rub_negates_y_and_z(splat, tmp_path):
    path, g = splat
    result = CliRunner().invoke(main, ["import", str(path), "--out", str(tmp_path / "out"), "--from-frame", "RUB"])
    assert result.exit_code == 0, result.output
    got, _ = read_gaussians_raw(tmp_path / "out" / "scene.ply")
    np.testing.assert_allclose(got.means, g.means * np.array([1, -1, -1], np.float32), atol=1e-6)


@pytest.mark.parametrize("content,needle", [("{not json", "t.json"), (json.dumps({"world_from_splat": [[1, 2], [3, 4]]}),
                                                                      "world_from_splat"),
                                            (json.dumps(np.diag([1.0, 2.0, 3.0, 1.0]).tolist()), "t.json")])
def test_a_bad_transform_is_one_line(splat, tmp_path, content, needle):
    path, _ = splat
    spec = tmp_path / "t.json"
    spec.write_text(content)
    for command in (["import", str(path), "--out", str(tmp_path / "out")],
                    ["render", str(path), "--out", str(tmp_path / "x.png"), "--width", "32", "--height", "24"]):
        result = CliRunner().invoke(main, [*command, "--transform", str(spec)])
        assert result.exit_code == 1, result.output
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert len(lines) == 1 and needle in lines[0] and "Traceback" not in result.output, result.output
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())
    assert not (tmp_path / "x.png").exists()


def test_render_with_transform_records_and_frames_the_moved_scene(splat, tmp_path):
    path, _ = splat
    out = tmp_path / "a.png"
    result = CliRunner().invoke(main, ["render", str(path), "--out", str(out), "--width", "32", "--height", "24",
                                       "--transform", "frame:RUB", "--json"])
    assert result.exit_code == 0, result.output
    frame = json.loads(result.output)["frame"]
    assert frame["reflection"] is False and out.is_file()
    np.testing.assert_allclose(frame["world_from_splat"], np.diag([1.0, -1.0, -1.0, 1.0]), atol=1e-12)
    plain = CliRunner().invoke(main, ["render", str(path), "--out", str(tmp_path / "b.png"), "--width", "32",
                                      "--height", "24", "--json"])
    assert plain.exit_code == 0 and json.loads(plain.output)["frame"] == {"transform": None}
    # the orbit camera looks at the moved scene: its pose differs from the unmoved scene's
    assert json.loads(result.output)["camera"]["viewmat"] != json.loads(plain.output)["camera"]["viewmat"]
