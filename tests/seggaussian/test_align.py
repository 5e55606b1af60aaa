"""seggaussian align: a splat moved into a trainer's frame (gsplat-like, nerfstudio-like) is registered back onto its
synthetic room within centimetres, the transform round-trips through JSON and the frames machinery, and an
unrelated splat or a bad input is refused with one line and no file."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
from click.testing import CliRunner

from cli.seg_align import command
from seggaussian.align.registration import _axis_turns, _cube_rotations, align_gaussians, similarity_parts
from seggaussian.align.target import AlignError, load_target
from seggaussian.labels.config import OracleConfig, TransferConfig
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.labels.oracle import sample_oracle_gaussians
from seggaussian.sources.layout import find_scene_layout, reader
from seggaussian.sources.synthetic.generate import SynthConfig, synthesize
from frames_common import axis_rotation

#: Oracle Gaussians of the test room (enough to fix the pose to millimetres, few enough for a fast test).
NUM_GAUSSIANS = 20_000
#: The recovered transform must put every moved Gaussian back within this of where it was (metres), and the
#: scale within this relative error.
MAX_ERROR_M = 0.03
MAX_SCALE_ERROR = 0.01


def _similarity(scale: float, rotation: np.ndarray, centre: np.ndarray, offset) -> np.ndarray:
    """4x4 ``x -> scale * rotation (x - centre) + offset`` (splat_from_world)."""
    m = np.eye(4)
    m[:3, :3] = scale * rotation
    m[:3, 3] = np.asarray(offset, float) - scale * rotation @ centre
    return m


def _moved(g: Gaussians, m: np.ndarray) -> Gaussians:
    """``g`` with its centres moved by ``m`` (the other attributes do not take part in the registration)."""
    means = g.means.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    return Gaussians(means.astype(np.float32), g.quats, g.log_scales, g.opacity_logits, g.sh)


def _apply(m, x):
    return np.asarray(x, np.float64) @ np.asarray(m)[:3, :3].T + np.asarray(m)[:3, 3]


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A synthetic ScanNet++ room, its oracle Gaussians and the splat moved gsplat-like (recentred, scaled by 0.33,
    turned 90 degrees about one axis and 37 about another), written as a 3DGS PLY."""
    root = tmp_path_factory.mktemp("align")
    (scene_id,) = synthesize(root / "raw" / "scannetpp", 1, 0, "scannetpp", SynthConfig(width=96, num_views=8))
    domain, layout_root = find_scene_layout(root / "raw", scene_id)
    scene = reader(domain).read_scene(layout_root, scene_id)
    g, _ = sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces,
                                   OracleConfig(num_gaussians=NUM_GAUSSIANS), np.random.default_rng(0),
                                   tuple(v.camera for v in scene.views))
    rotation = axis_rotation([0.0, 1.0, 0.0], 37.0) @ axis_rotation([1.0, 2.0, 3.0], 90.0)
    splat_from_world = _similarity(0.33, rotation, g.means.astype(np.float64).mean(axis=0), [0.0, 0.0, 0.0])
    splat = root / "gsplat_frame.ply"
    write_gaussians_ply(splat, _moved(g, splat_from_world))
    return {"root": root, "raw": root / "raw", "scene_id": scene_id, "scene": scene, "gaussians": g,
            "splat": splat, "splat_from_world": splat_from_world}


@pytest.fixture(scope="module")
def cli_run(room):
    """``seggaussian align SPLAT --to RAW --scene ID --out T.json --json``, once for the tests that read it."""
    out = room["root"] / "out" / "transform.json"
    result = CliRunner().invoke(command, [str(room["splat"]), "--to", str(room["raw"]), "--scene", room["scene_id"],
                                          "--out", str(out), "--json"])
    return result, out


def _check_recovered(world_from_splat: np.ndarray, scale: float, room: dict, splat_from_world: np.ndarray) -> None:
    original = room["gaussians"].means.astype(np.float64)
    back = _apply(world_from_splat, _apply(splat_from_world, original))
    error = np.linalg.norm(back - original, axis=1)
    assert error.max() < MAX_ERROR_M, (np.median(error), error.max())
    true_scale = 1.0 / np.cbrt(np.linalg.det(splat_from_world[:3, :3]))
    assert abs(scale / true_scale - 1.0) < MAX_SCALE_ERROR, (scale, true_scale)


def test_cli_recovers_a_gsplat_like_similarity(room, cli_run):
    result, out = cli_run
    assert result.exit_code == 0, result.output
    printed = json.loads(result.output)
    written = json.loads(out.read_text())
    assert printed["out"] == str(out) and printed["world_from_splat"] == written["world_from_splat"]
    m = np.array(written["world_from_splat"])
    assert m.shape == (4, 4) and np.allclose(m[3], [0, 0, 0, 1])
    _check_recovered(m, written["scale"], room, room["splat_from_world"])
    np.testing.assert_allclose(m[:3, :3], written["scale"] * np.array(written["rotation"]), atol=1e-12)
    transfer = TransferConfig()
    assert written["on_mesh_share"] >= transfer.min_on_mesh_share
    assert written["surface_covered_share"] >= transfer.min_surface_covered_share
    assert written["fitness"] > 0.95 and 0 <= written["residual_m"] < 0.01  # oracle Gaussians lie on the mesh
    assert written["placement"]["local_offset"] <= transfer.max_local_offset
    assert written["splat"] == str(room["splat"]) and written["to"] == str(room["raw"])
    assert written["scene"] == room["scene_id"]
    summary = printed["summary"]
    assert "\n" not in summary and "residual" in summary and f"--transform {out}" in summary
    assert f"{100 * written['on_mesh_share']:.1f} %" in summary


def test_written_transform_is_what_the_frames_machinery_applies(room, cli_run):
    _, out = cli_run
    if importlib.util.find_spec("seggaussian.frames.transform_spec") is None:
        pytest.skip("seggaussian.frames.transform_spec is not there yet")
    from seggaussian.frames.transform_spec import load_transform

    written = np.array(json.loads(out.read_text())["world_from_splat"])
    applied = np.asarray(load_transform(str(out)).world_from_splat.matrix)
    np.testing.assert_allclose(applied, written, rtol=0, atol=1e-9)


def test_library_recovers_a_nerfstudio_like_similarity_onto_a_mesh_file(room, tmp_path):
    """A mesh PLY as --to (open3d reads it), a 0.1-scale frame turned about a slanted axis and moved off centre."""
    import open3d as o3d

    scene = room["scene"]
    mesh_path = tmp_path / "room_mesh.ply"
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(scene.points),
                                     o3d.utility.Vector3iVector(scene.faces.astype(np.int32)))
    assert o3d.io.write_triangle_mesh(str(mesh_path), mesh)
    target = load_target(mesh_path)
    assert target.faces is not None and len(target.faces) == len(scene.faces)
    splat_from_world = _similarity(0.1, axis_rotation([0.3, -1.0, 0.5], 140.0), np.array([1.0, -2.0, 0.5]),
                                   [0.2, 0.1, -0.3])
    result = align_gaussians(_moved(room["gaussians"], splat_from_world), target)
    assert result.failure is None, result.failure
    _check_recovered(result.world_from_splat, result.scale, room, splat_from_world)
    assert result.num_registered <= result.num_opaque <= result.num_gaussians == NUM_GAUSSIANS


def test_unrelated_splat_is_refused_and_nothing_is_written(room, tmp_path):
    rng = np.random.default_rng(1)
    n = 5_000
    noise = Gaussians.from_arrays(rng.uniform(-1.0, 1.0, (n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)),
                                  np.full((n, 3), -4.0), np.full(n, 3.0), np.zeros((n, 1, 3)))
    splat = tmp_path / "noise.ply"
    write_gaussians_ply(splat, noise)
    out = tmp_path / "out" / "transform.json"
    result = CliRunner().invoke(command, [str(splat), "--to", str(room["raw"]), "--scene", room["scene_id"],
                                          "--out", str(out)])
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and str(splat) in errors[0] and "did not converge" in errors[0], result.output
    assert "Traceback" not in result.output
    assert not out.exists() and not out.parent.exists()


@pytest.mark.parametrize("case", ["missing splat", "missing target", "tree without --scene", "--scene with a file",
                                  "no such scene"])
def test_bad_inputs_are_one_line_errors_naming_the_path(room, tmp_path, case):
    splat, raw, out = room["splat"], room["raw"], tmp_path / "t.json"
    argv, named = {
        "missing splat": ([str(tmp_path / "none.ply"), "--to", str(raw), "--scene", room["scene_id"]],
                          tmp_path / "none.ply"),
        "missing target": ([str(splat), "--to", str(tmp_path / "none_mesh.ply")], tmp_path / "none_mesh.ply"),
        "tree without --scene": ([str(splat), "--to", str(raw)], raw),
        "--scene with a file": ([str(splat), "--to", str(splat), "--scene", room["scene_id"]], splat),
        "no such scene": ([str(splat), "--to", str(raw), "--scene", "nope"], raw),
    }[case]
    result = CliRunner().invoke(command, argv + ["--out", str(out)])
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and str(named) in errors[0], result.output
    assert not out.exists()


def test_too_transparent_splat_is_refused_before_registering(room):
    g = room["gaussians"]
    clear = Gaussians(g.means, g.quats, g.log_scales, np.full(len(g), -8.0, np.float32), g.sh)  # opacity 3e-4
    target = load_target(room["raw"], room["scene_id"])
    with pytest.raises(AlignError, match=r"^splat: only 0 of 20000 Gaussians are opaque"):
        align_gaussians(clear, target)


def test_similarity_parts_and_the_rotation_sets():
    rot = axis_rotation([1.0, 2.0, 3.0], 90.0)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = 2.5 * rot, [1.0, 2.0, 3.0]
    scale, r, t = similarity_parts(m)
    assert scale == pytest.approx(2.5) and np.allclose(r, rot) and np.allclose(t, [1, 2, 3])
    mirror = m.copy()
    mirror[:3, 0] *= -1
    with pytest.raises(ValueError, match="not a proper similarity"):
        similarity_parts(mirror)
    cube = _cube_rotations()
    assert len(cube) == 24 and np.allclose(cube[0], np.eye(3))
    assert len({tuple(np.round(r).astype(int).ravel()) for r in cube}) == 24
    assert all(np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0) for r in cube)
    turns = _axis_turns()
    assert len(turns) == 9 and all(np.isclose(np.trace(r), 1.0) or np.isclose(np.trace(r), -1.0) for r in turns)
