"""``load_transform`` / ``resolve_transform`` on every kind of spec, and the COLMAP model reader behind ``gsplat:``."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from frames_common import random_rotation, room_scene, write_colmap_binary, write_colmap_text

from seggaussian.core.cameras import look_at
from seggaussian.frames.axes import axes_to_rdf
from seggaussian.frames.colmap_model import ColmapModelError, read_colmap_model
from seggaussian.frames.similarity import Similarity
from seggaussian.frames.transform_spec import TransformSpecError, load_transform, resolve_transform
from seggaussian.sources.scannetpp import toolkit_transform_matrix


def _one_line_error(spec, match, **kwargs) -> str:
    with pytest.raises(ValueError, match=match) as info:
        load_transform(spec, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


# --- explicit matrices ----------------------------------------------------------------------------


def _some_similarity(seed: int = 0, reflection: bool = False) -> Similarity:
    rng = np.random.default_rng(seed)
    r = random_rotation(rng) @ (np.diag([1.0, 1.0, -1.0]) if reflection else np.eye(3))
    return Similarity(r, rng.normal(size=3), 1.3)


@pytest.mark.parametrize("reflection", [False, True])
def test_explicit_matrix_object_and_bare_list(tmp_path, reflection):
    sim = _some_similarity(1, reflection)
    (tmp_path / "t.json").write_text(json.dumps({"world_from_splat": sim.matrix.tolist()}))
    (tmp_path / "bare.json").write_text(json.dumps(sim.matrix.tolist()))
    for name in ("t.json", "bare.json"):
        frame = load_transform(name, base_dir=tmp_path)
        np.testing.assert_allclose(frame.world_from_splat.matrix, sim.matrix, atol=1e-12)
        assert frame.world_from_splat.is_reflection == reflection
        assert frame.details["reflection"] == reflection and frame.details["kind"] == "matrix"
        json.dumps(frame.details)  # JSON-safe
    assert load_transform(str(tmp_path / "t.json")).world_from_splat.scale == pytest.approx(1.3)


@pytest.mark.parametrize("content,match", [
    ({"world_from_splat": np.diag([1.0, 2.0, 1.0, 1.0]).tolist()}, r"\[world_from_splat\]: .*non-uniform scale"),
    ({"world_from_splat": np.eye(4)[:3].tolist()}, r"\[world_from_splat\]: expected a 4x4 matrix, got shape \(3, 4\)"),
    ({"world_from_splat": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}, r"\[world_from_splat\]: last row"),
    ({"world_from_splat": [["a", 0, 0, 0]] * 4}, r"\[world_from_splat\]: expected a 4x4 matrix of numbers"),
    (np.eye(3).tolist(), r"\[matrix\]: expected a 4x4 matrix"),
    ({"something": 1}, "expected exactly one of"),
    ({"world_from_splat": np.eye(4).tolist(), "chain": []}, "expected exactly one of"),
    ("just a string", "expected a JSON object or a 4x4 list"),
])
def test_bad_matrix_files_are_refused_naming_the_file_and_field(tmp_path, content, match):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(content))
    message = _one_line_error(str(path), match)
    assert message.startswith(str(path))


def test_malformed_json_and_missing_files_are_refused(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{"world_from_splat": [[1, 0, 0, 0],')
    assert _one_line_error(str(path), "not valid JSON").startswith(str(path))
    assert "no such file" in _one_line_error("nowhere.json", "no such file", base_dir=tmp_path)
    _one_line_error("", "non-empty")


# --- frame:CODE and resolve_transform --------------------------------------------------------------


def test_frame_codes():
    frame = load_transform("frame:RUB")
    np.testing.assert_array_equal(frame.world_from_splat.matrix[:3, :3], np.diag([1.0, -1.0, -1.0]))
    assert frame.details["axes"] == "RUB"
    assert load_transform("frame:ruf").world_from_splat.is_reflection
    message = _one_line_error("frame:RUX", "axes code")
    assert "frame:RUX" in message


def test_scannetpp_nerfstudio_world_is_frame_drb():
    """The ScanNet++ toolkit writes transforms.json in the mesh frame with x, y swapped and z negated: frame:DRB
    maps those camera poses back onto the COLMAP (mesh-frame) poses."""
    to_mesh = load_transform("frame:DRB").world_from_splat
    rng = np.random.default_rng(2)
    for _ in range(3):
        viewmat = look_at(rng.normal(size=3) * 2, rng.normal(size=3), up=(0.0, 0.0, 1.0))
        data_c2w = toolkit_transform_matrix(viewmat)  # OpenGL camera axes, data world
        mesh_c2w = np.linalg.inv(viewmat)
        np.testing.assert_allclose(to_mesh.apply(data_c2w[None, :3, 3])[0], mesh_c2w[:3, 3], atol=1e-12)
        np.testing.assert_allclose(to_mesh.rotation @ data_c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0]),
                                   mesh_c2w[:3, :3], atol=1e-12)


def test_resolve_transform_applies_from_frame_first(tmp_path):
    assert resolve_transform(None, None) is None
    sim = _some_similarity(3)
    (tmp_path / "t.json").write_text(json.dumps({"world_from_splat": sim.matrix.tolist()}))
    only_frame = resolve_transform(None, "RUB")
    np.testing.assert_array_equal(only_frame.world_from_splat.rotation, axes_to_rdf("RUB"))
    assert resolve_transform(None, "frame:RUB").world_from_splat.is_identity is False
    only_transform = resolve_transform("t.json", None, base_dir=tmp_path)
    np.testing.assert_allclose(only_transform.world_from_splat.matrix, sim.matrix, atol=1e-12)
    both = resolve_transform("t.json", "RUB", base_dir=tmp_path)
    raw = np.random.default_rng(4).normal(size=(5, 3))
    expected = sim.apply(raw @ axes_to_rdf("RUB").T)
    np.testing.assert_allclose(both.world_from_splat.apply(raw), expected, atol=1e-12)
    json.dumps(both.details)
    with pytest.raises(ValueError, match="--from-frame 'XYZ'"):
        resolve_transform(None, "XYZ")


# --- chains ----------------------------------------------------------------------------------------


def test_chain_applies_specs_from_the_splat_outward_with_relative_paths(tmp_path):
    sub = tmp_path / "runs"
    sub.mkdir()
    first = _some_similarity(5)
    (sub / "first.json").write_text(json.dumps({"world_from_splat": first.matrix.tolist()}))
    (sub / "chain.json").write_text(json.dumps({"chain": ["first.json", "frame:DRB"]}))
    (tmp_path / "outer.json").write_text(json.dumps({"chain": ["frame:RUB", "runs/chain.json"]}))
    frame = load_transform("runs/chain.json", base_dir=tmp_path)
    p = np.random.default_rng(6).normal(size=(4, 3))
    np.testing.assert_allclose(frame.world_from_splat.apply(p), first.apply(p) @ axes_to_rdf("DRB").T, atol=1e-12)
    assert [step["spec"] for step in frame.details["steps"]] == ["first.json", "frame:DRB"]
    outer = load_transform(str(tmp_path / "outer.json"))
    np.testing.assert_allclose(outer.world_from_splat.apply(p), frame.world_from_splat.apply(p @ axes_to_rdf("RUB").T),
                               atol=1e-12)
    json.dumps(outer.details)


def test_bad_chains_are_refused(tmp_path):
    (tmp_path / "self.json").write_text(json.dumps({"chain": ["self.json"]}))
    _one_line_error(str(tmp_path / "self.json"), "nested deeper")
    (tmp_path / "empty.json").write_text(json.dumps({"chain": []}))
    assert "[chain]" in _one_line_error(str(tmp_path / "empty.json"), "non-empty list")
    (tmp_path / "typed.json").write_text(json.dumps({"chain": ["frame:RUB", 3]}))
    assert "[chain[1]]" in _one_line_error(str(tmp_path / "typed.json"), "spec string")
    (tmp_path / "missing.json").write_text(json.dumps({"chain": ["frame:RUB", "gone.json"]}))
    assert "[chain[1]]" in _one_line_error(str(tmp_path / "missing.json"), "no such file")


# --- nerfstudio dataparser_transforms.json --------------------------------------------------------


def _nerfstudio_dataparser(c2w_opengl: np.ndarray) -> tuple[np.ndarray, float]:
    """nerfstudio's defaults (orientation 'up', centre 'poses', auto-scale), from
    nerfstudio/cameras/camera_utils.py auto_orient_and_center_poses + rotation_matrix_between and
    nerfstudio/data/dataparsers/nerfstudio_dataparser.py (scale_factor = 1 / max |oriented translation|)."""
    origins = c2w_opengl[:, :3, 3]
    translation = origins.mean(axis=0)
    up = c2w_opengl[:, :3, 1].mean(axis=0)
    a, b = up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0])
    v = np.cross(a, b)
    v = v / np.linalg.norm(v)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    theta = np.arccos(np.clip(a @ b, -1, 1))
    rotation = np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * (k @ k)
    transform = np.concatenate([rotation, rotation @ -translation[:, None]], axis=1)  # [3, 4]
    oriented = transform @ c2w_opengl
    scale = 1.0 / float(np.max(np.abs(oriented[:, :3, 3])))
    return transform, scale


def test_nerfstudio_dataparser_transforms_are_inverted(tmp_path):
    c2w, points = room_scene(seed=7)
    c2w_opengl = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])  # nerfstudio's transforms.json camera axes
    transform, scale = _nerfstudio_dataparser(c2w_opengl)
    path = tmp_path / "dataparser_transforms.json"
    path.write_text(json.dumps({"transform": transform.tolist(), "scale": scale}, indent=4))
    frame = load_transform(str(path))
    sim = frame.world_from_splat
    # a model point lives at x = scale * (transform @ [p; 1]) (nerfstudio's _load_3D_points); back to p
    model_points = scale * (np.c_[points, np.ones(len(points))] @ transform.T)
    np.testing.assert_allclose(sim.apply(model_points), points, atol=1e-9)
    # the dataparser frame is what nerfstudio promises: cameras centred, within [-1, 1], up is +z
    cams = sim.inverse().apply(c2w[:, :3, 3])
    np.testing.assert_allclose(cams.mean(axis=0), 0.0, atol=1e-9)
    assert np.abs(cams).max() == pytest.approx(1.0)
    up = sim.inverse().rotation @ c2w_opengl[:, :3, 1].mean(axis=0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0.0, 0.0, 1.0], atol=1e-9)
    assert frame.details["kind"] == "nerfstudio_dataparser" and frame.details["dataparser_scale"] == scale
    json.dumps(frame.details)


@pytest.mark.parametrize("content,match", [
    ({"transform": np.eye(4)[:3].tolist()}, r"\[scale\]: missing"),
    ({"transform": np.eye(4)[:3].tolist(), "scale": 0}, r"\[scale\]: expected a positive number"),
    ({"transform": np.eye(4)[:3].tolist(), "scale": "2"}, r"\[scale\]"),
    ({"transform": np.eye(4).tolist(), "scale": 1.0}, r"\[transform\]: expected a 3x4 matrix"),
    ({"transform": np.diag([1.0, 3.0, 1.0, 1.0])[:3].tolist(), "scale": 1.0}, r"\[transform\]: .*uniform"),
])
def test_bad_dataparser_transforms_are_refused(tmp_path, content, match):
    path = tmp_path / "dataparser_transforms.json"
    path.write_text(json.dumps(content))
    assert _one_line_error(str(path), match).startswith(str(path))


# --- gsplat:COLMAP_DIR ----------------------------------------------------------------------------


def _gsplat_steps_transcribed(camtoworlds, points, upside_down_fix=True):
    """gsplat examples/datasets/normalize.py + colmap.py Parser(normalize=True), transcribed in gsplat's own style
    (independent of seggaussian.frames.gsplat_normalization)."""
    # similarity_from_cameras(c2w, strict_scaling=False, center_method="focus")
    t = camtoworlds[:, :3, 3]
    R = camtoworlds[:, :3, :3]
    ups = np.sum(R * np.array([0, -1.0, 0]), axis=-1)
    world_up = np.mean(ups, axis=0)
    world_up /= np.linalg.norm(world_up)
    up_camspace = np.array([0.0, -1.0, 0.0])
    c = (up_camspace * world_up).sum()
    cross = np.cross(world_up, up_camspace)
    skew = np.array([[0.0, -cross[2], cross[1]], [cross[2], 0.0, -cross[0]], [-cross[1], cross[0], 0.0]])
    R_align = np.eye(3) + skew + (skew @ skew) * 1 / (1 + c) if c > -1 else np.diag([-1.0, 1.0, 1.0])
    R = R_align @ R
    fwds = np.sum(R * np.array([0, 0.0, 1.0]), axis=-1)
    t = (R_align @ t[..., None])[..., 0]
    nearest = t + (fwds * -t).sum(-1)[:, None] * fwds
    translate = -np.median(nearest, axis=0)
    T1 = np.eye(4)
    T1[:3, 3] = translate
    T1[:3, :3] = R_align
    scale = 1.0 / np.median(np.linalg.norm(t + translate, axis=-1))
    T1[:3, :] *= scale
    # transform_points, align_principal_axes
    points = points.astype(np.float32)
    points = points @ T1[:3, :3].T + T1[:3, 3]
    centroid = np.median(points, axis=0)
    eigenvalues, eigenvectors = np.linalg.eigh(np.cov(points - centroid, rowvar=False))
    eigenvectors = eigenvectors[:, eigenvalues.argsort()[::-1]]
    if np.linalg.det(eigenvectors) < 0:
        eigenvectors[:, 0] *= -1
    T2 = np.eye(4)
    T2[:3, :3] = eigenvectors.T
    T2[:3, 3] = -eigenvectors.T @ centroid
    points = points @ T2[:3, :3].T + T2[:3, 3]
    transform = T2 @ T1
    if upside_down_fix and np.median(points[:, 2]) > np.mean(points[:, 2]):
        T3 = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 0], [0, 0, 0, 1.0]])
        points = points @ T3[:3, :3].T
        transform = T3 @ transform
    return transform, points


#: room_scene seeds whose gsplat normalization is, respectively, not flipped and flipped by the upside-down fix.
SCENE_SEEDS = (0, 2)


@pytest.fixture(scope="module")
def colmap_models(tmp_path_factory):
    """Two scenes (one flipped by gsplat's upside-down fix, one not), each as text and binary models."""
    root = tmp_path_factory.mktemp("colmap")
    models = {}
    for seed in SCENE_SEEDS:
        c2w, points = room_scene(seed)
        models[seed] = (c2w, points, write_colmap_text(root / f"scene{seed}" / "sparse" / "0", c2w, points),
                        write_colmap_binary(root / f"scene{seed}_bin", c2w, points))
    return models


@pytest.mark.parametrize("seed", SCENE_SEEDS)
def test_gsplat_normalization_matches_a_transcription_of_gsplat(colmap_models, seed):
    c2w, points, text_dir, bin_dir = colmap_models[seed]
    expected, normalized_points = _gsplat_steps_transcribed(c2w, points)
    for spec in (f"gsplat:{text_dir}", f"gsplat:{text_dir.parent.parent}", f"gsplat:{bin_dir}"):
        frame = load_transform(spec)
        normalized_from_colmap = frame.world_from_splat.inverse()
        np.testing.assert_allclose(normalized_from_colmap.matrix, expected, atol=1e-9)
        assert frame.world_from_splat.compose(normalized_from_colmap).is_identity
        # the splat's means (normalized frame) go back onto the COLMAP points
        np.testing.assert_allclose(frame.world_from_splat.apply(normalized_points), points, atol=1e-5)
        json.dumps(frame.details)
    assert frame.details["colmap_format"] == "binary" and frame.details["num_points"] == len(points)


def test_gsplat_fixture_covers_both_sides_of_the_upside_down_fix(colmap_models):
    flips = {seed: load_transform(f"gsplat:{colmap_models[seed][2]}").details["upside_down_flip"]
             for seed in SCENE_SEEDS}
    assert set(flips.values()) == {True, False}


@pytest.mark.parametrize("seed", SCENE_SEEDS)
def test_gsplat_normalized_points_are_centred_scaled_and_axis_aligned(colmap_models, seed):
    c2w, points, text_dir, _ = colmap_models[seed]
    frame = load_transform(f"gsplat:{text_dir}")
    normalized = frame.world_from_splat.inverse().apply(points)
    cov = np.cov(normalized, rowvar=False)
    np.testing.assert_allclose(cov - np.diag(np.diag(cov)), 0.0, atol=1e-6)  # principal axes = coordinate axes
    assert cov[0, 0] >= cov[1, 1] >= cov[2, 2]  # x the widest spread, z the smallest
    assert np.median(normalized[:, 2]) <= np.mean(normalized[:, 2]) + 1e-9  # not upside down (gsplat >= 1.5.2)
    # the first step's frame: the median of the points of the optical axes nearest to the COLMAP origin is the new
    # origin, and the median camera distance to it is 1
    t1 = np.array(frame.details["t1"])
    centres = c2w[:, :3, 3] @ t1[:3, :3].T + t1[:3, 3]
    assert np.median(np.linalg.norm(centres, axis=1)) == pytest.approx(1.0)
    forwards = c2w[:, :3, 2] @ t1[:3, :3].T
    forwards /= np.linalg.norm(forwards, axis=1, keepdims=True)
    old_origin = t1[:3, 3]
    nearest = centres + np.sum(forwards * (old_origin - centres), axis=1, keepdims=True) * forwards
    np.testing.assert_allclose(np.median(nearest, axis=0), 0.0, atol=1e-9)
    assert frame.details["num_images"] == len(c2w)
    # and the room's floor (its largest flat part) ends up perpendicular to z: the room is z-up or z-down
    assert abs(frame.world_from_splat.rotation[2] @ [0.0, 0.0, 1.0]) > 0.99


def test_gsplat_legacy_differs_only_by_the_flip(colmap_models):
    for seed in SCENE_SEEDS:
        text_dir = colmap_models[seed][2]
        new, old = load_transform(f"gsplat:{text_dir}"), load_transform(f"gsplat-legacy:{text_dir}")
        flip = np.diag([1.0, -1.0, -1.0, 1.0]) if new.details["upside_down_flip"] else np.eye(4)
        np.testing.assert_allclose(new.world_from_splat.inverse().matrix,
                                   flip @ old.world_from_splat.inverse().matrix, atol=1e-12)
        assert old.details["upside_down_flip"] is False


def test_colmap_text_and_binary_models_read_the_same(colmap_models):
    c2w, points, text_dir, bin_dir = colmap_models[0]
    text, binary = read_colmap_model(text_dir), read_colmap_model(bin_dir)
    assert text.image_names == binary.image_names and not text.binary and binary.binary
    np.testing.assert_allclose(text.world_to_camera, binary.world_to_camera, atol=1e-12)
    np.testing.assert_allclose(text.world_to_camera, np.linalg.inv(c2w), atol=1e-9)
    np.testing.assert_array_equal(text.points, binary.points)
    np.testing.assert_allclose(text.points, points, atol=0)


def test_gsplat_sorts_images_by_name_like_gsplat(tmp_path):
    c2w, points = room_scene(3)
    names = [f"IMG_{i:04d}.JPG" for i in range(len(c2w))]
    order = np.random.default_rng(0).permutation(len(c2w))
    write_colmap_text(tmp_path / "a", c2w, points, names)
    write_colmap_text(tmp_path / "b", c2w[order], points, [names[i] for i in order])
    a, b = load_transform(f"gsplat:{tmp_path / 'a'}"), load_transform(f"gsplat:{tmp_path / 'b'}")
    np.testing.assert_allclose(a.world_from_splat.matrix, b.world_from_splat.matrix, atol=1e-12)


def test_bad_colmap_models_are_refused_in_one_line(tmp_path, colmap_models):
    assert "no such COLMAP model folder" in _one_line_error(f"gsplat:{tmp_path / 'nowhere'}", "no such COLMAP")
    (tmp_path / "empty").mkdir()
    _one_line_error(f"gsplat:{tmp_path / 'empty'}", "no COLMAP model here")
    _one_line_error("gsplat:", "needs a COLMAP folder")
    # ScanNet++-like model without 3D points (the synthetic writer's points3D.txt is empty)
    c2w, points = room_scene(4)
    no_points = write_colmap_text(tmp_path / "no_points", c2w, points[:0])
    assert "at least 2" in _one_line_error(f"gsplat:{no_points}", "gsplat normalization")
    # truncated binary model
    truncated = tmp_path / "truncated"
    shutil.copytree(colmap_models[0][3], truncated)
    data = (truncated / "points3D.bin").read_bytes()
    (truncated / "points3D.bin").write_bytes(data[:-5])
    message = _one_line_error(f"gsplat:{truncated}", "truncated")
    assert "points3D.bin" in message
    # a malformed text line names the file and the line
    bad = write_colmap_text(tmp_path / "bad", c2w, points)
    lines = (bad / "images.txt").read_text().splitlines()
    lines[2] = lines[2].replace(lines[2].split()[3], "oops", 1)
    (bad / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ColmapModelError, match=r"images.txt \[line 3 QW..TZ\]: expected numbers"):
        read_colmap_model(bad)
    assert issubclass(TransformSpecError, ValueError)
