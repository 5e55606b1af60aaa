"""Camera conventions: COLMAP quaternions, the toolkit's transform_matrix, pixel-centre rays."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from seggaussian.core.cameras import Camera, intrinsics, invert_rigid, look_at
from seggaussian.sources import scannetpp
from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources.raycast import MeshRaycaster, cast_rays_reference


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    rotations = [_random_rotation(rng) for _ in range(200)]
    rotations += [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]  # trace <= 0 branches
    for rot in rotations:
        q = scannetpp.rotation_to_quaternion(rot)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(scannetpp.quaternion_to_rotation(*q), rot, atol=1e-12)
    # COLMAP quaternions need not be unit on disk
    np.testing.assert_allclose(scannetpp.quaternion_to_rotation(2.0, 0, 0, 0), np.eye(3))


def _toolkit_convert_frame(w2c: np.ndarray) -> np.ndarray:
    """The ScanNet++ toolkit's convert_frames, step by step as written there (independent of the reader)."""
    c2w = np.linalg.inv(w2c)
    c2w[0:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
    c2w = c2w[np.array([1, 0, 2, 3]), :]  # swap world x and y
    c2w[2, :] *= -1  # flip world z
    return c2w


def test_toolkit_transform_matches_and_inverts():
    rng = np.random.default_rng(1)
    for _ in range(50):
        w2c = np.eye(4)
        w2c[:3, :3] = _random_rotation(rng)
        w2c[:3, 3] = rng.normal(size=3) * 3
        tm = _toolkit_convert_frame(w2c)
        np.testing.assert_allclose(scannetpp.toolkit_transform_matrix(w2c), tm, atol=1e-12)
        np.testing.assert_allclose(scannetpp.undo_toolkit_transform(tm), w2c, atol=1e-12)
        assert np.abs(tm - np.linalg.inv(w2c)).max() > 1e-3  # the nerfstudio pose is NOT the mesh-frame c2w


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("conv")
    ids = synthetic.synthesize(root, 1, 11, "scannetpp", synthetic.SynthConfig(width=64, num_views=9, max_edge=0.15))
    return root, ids[0]


def test_reader_recovers_mesh_frame_pose_from_toolkit_transforms(scene_root, tmp_path):
    root, scene_id = scene_root
    _, cameras = synthetic.build_scene(11, 0, "scannetpp", synthetic.SynthConfig(width=64, num_views=9, max_edge=0.15))
    # transforms_undistorted.json rebuilt here the toolkit's way, from the true mesh-frame poses
    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    tpath = copy / "data" / scene_id / scannetpp.TRANSFORMS_FILE
    doc = json.loads(tpath.read_text())
    poses = {f"DSC{i + 1:05d}.JPG": cam.viewmat for i, cam in enumerate(cameras)}
    for key in ("frames", "test_frames"):
        for frame in doc[key]:
            frame["transform_matrix"] = _toolkit_convert_frame(poses[frame["file_path"]]).tolist()
    tpath.write_text(json.dumps(doc))
    with_colmap = scannetpp.read_scene(copy, scene_id)
    assert with_colmap.stats["pose_source"] == "colmap" and with_colmap.stats["pose_disagreements"] == 0
    (copy / "data" / scene_id / scannetpp.COLMAP_IMAGES_FILE).unlink()
    without = scannetpp.read_scene(copy, scene_id)
    assert without.stats["pose_source"].startswith("transform_matrix")
    for scene in (with_colmap, without):
        for view in scene.views:
            np.testing.assert_allclose(view.camera.viewmat, poses[view.name], atol=1e-9)
    # novel views: the test list of train_test_lists.json
    assert sorted(v.name for v in with_colmap.views if v.role == "novel") == ["DSC00001.JPG", "DSC00009.JPG"]


def test_reader_flags_a_transform_matrix_used_as_mesh_pose(scene_root, tmp_path):
    root, scene_id = scene_root
    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    tpath = copy / "data" / scene_id / scannetpp.TRANSFORMS_FILE
    doc = json.loads(tpath.read_text())
    for frame in doc["frames"]:  # the common mistake: plain c2w written into transform_matrix
        frame["transform_matrix"] = invert_rigid(scannetpp.undo_toolkit_transform(np.array(frame["transform_matrix"]))).tolist()
    tpath.write_text(json.dumps(doc))
    assert scannetpp.read_scene(copy, scene_id).stats["pose_disagreements"] == len(doc["frames"])


def test_resized_images_scale_intrinsics(scene_root, tmp_path):
    import cv2

    root, scene_id = scene_root
    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    dslr = copy / "data" / scene_id / "dslr"
    shutil.rmtree(dslr / "undistorted_images")  # the release's resized copies are the fallback
    shutil.rmtree(dslr / "undistorted_anon_masks")
    for image in (dslr / "resized_undistorted_images").iterdir():
        cv2.imwrite(str(image), cv2.resize(cv2.imread(str(image)), (32, 24)))
    for mask in (dslr / "resized_undistorted_masks").iterdir():
        cv2.imwrite(str(mask), cv2.resize(cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE), (32, 24),
                                          interpolation=cv2.INTER_NEAREST))
    original = scannetpp.read_scene(root, scene_id).views[0].camera
    view = scannetpp.read_scene(copy, scene_id).views[0].camera
    assert (view.width, view.height) == (32, 24)
    np.testing.assert_allclose(view.K[:2], original.K[:2] * 0.5)


def test_raycaster_matches_reference_and_pixel_centres():
    rng = np.random.default_rng(2)
    points = rng.uniform(-1, 1, size=(12, 3)) + [0, 0, 3]
    faces = rng.integers(0, 12, size=(8, 3))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    cam = Camera(intrinsics(9.0, 9.0, 6.0, 5.0), look_at([0.1, 0.2, 0], [0, 0, 3], up=(0, -1, 0)), 12, 10)
    fast = MeshRaycaster(points, faces).cast(cam)
    slow = cast_rays_reference(points, faces, cam)
    assert (fast.face_ids >= 0).sum() > 10
    np.testing.assert_array_equal(fast.face_ids, slow.face_ids)
    np.testing.assert_allclose(fast.depth, slow.depth, atol=1e-5)
    np.testing.assert_allclose(fast.barycentric, slow.barycentric, atol=1e-4)
    # a hit point reprojects onto the centre of its pixel (+0.5 convention)
    y, x = np.argwhere(fast.face_ids >= 0)[0]
    tri = points[faces[fast.face_ids[y, x]]]
    u, v = fast.barycentric[y, x]
    hit = (1 - u - v) * tri[0] + u * tri[1] + v * tri[2]
    uv, z = cam.project(hit[None])
    np.testing.assert_allclose(uv[0], [x + 0.5, y + 0.5], atol=1e-3)
    np.testing.assert_allclose(z[0], fast.depth[y, x], atol=1e-5)


def test_raycaster_empty_view_and_nan_free():
    points = np.array([[0.0, 0, 5], [1, 0, 5], [0, 1, 5]])
    cam = Camera(intrinsics(10.0, 10.0, 4.0, 4.0), look_at([0, 0, 0], [0, 0, -1], up=(0, 1, 0)), 8, 8)  # looks away
    hits = MeshRaycaster(points, np.array([[0, 1, 2]])).cast(cam)
    assert (hits.face_ids == -1).all() and (hits.depth == 0).all() and np.isfinite(hits.barycentric).all()
