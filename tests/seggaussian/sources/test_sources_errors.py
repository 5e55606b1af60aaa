"""Bad input: a SourceError naming the file and the field, never a traceback from numpy/plyfile."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from seggaussian.sources import replica, scannetpp

from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources._common import EmptySceneError, SourceError

SMALL = synthetic.SynthConfig(width=48, num_views=3, max_edge=0.2)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    base = tmp_path_factory.mktemp("pristine")
    s_ids = synthetic.synthesize(base / "s", 1, 5, "scannetpp", SMALL)
    r_ids = synthetic.synthesize(base / "r", 1, 5, "replica", SMALL)
    return base, s_ids[0], r_ids[0]


@pytest.fixture
def trees(pristine, tmp_path):
    base, s_id, r_id = pristine
    shutil.copytree(base / "s", tmp_path / "s")
    shutil.copytree(base / "r", tmp_path / "r")
    return tmp_path / "s", s_id, tmp_path / "s" / "data" / s_id, tmp_path / "r", r_id, tmp_path / "r" / r_id


def _expect(call, *fragments, kind=SourceError):
    with pytest.raises(kind) as info:
        call()
    for fragment in fragments:
        assert fragment in str(info.value), (fragment, str(info.value))
    return info.value


def test_pristine_trees_read(trees):
    s_root, s_id, _, r_root, r_id, _ = trees
    assert scannetpp.read_scene(s_root, s_id).views
    assert replica.read_scene(r_root, r_id).views


def test_missing_and_corrupt_json(trees):
    s_root, s_id, s_dir, r_root, r_id, r_dir = trees
    (s_dir / scannetpp.ANNOTATION_FILE).unlink()
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "segments_anno.json", "missing")
    (s_dir / scannetpp.SEGMENTS_FILE).write_text('{"segIndices": [1, 2,')
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "segments.json", "corrupt JSON")
    (r_dir / replica.INFO_FILE).write_text("not json")
    _expect(lambda: replica.read_scene(r_root, r_id), "info_semantic.json", "corrupt JSON")
    (r_dir / replica.INFO_FILE).write_text(json.dumps({"classes": [], "objects": []}))
    _expect(lambda: replica.read_scene(r_root, r_id), "info_semantic.json", "[id_to_label]", "missing")


def test_label_absent_from_the_map(trees):
    s_root, s_id, s_dir, *_ = trees
    path = s_dir / scannetpp.ANNOTATION_FILE
    doc = json.loads(path.read_text())
    doc["segGroups"][3]["label"] = "flux capacitor"
    path.write_text(json.dumps(doc))
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "segments_anno.json", "segGroups[3].label", "flux capacitor", "map_benchmark.csv")
    scene = scannetpp.read_scene(s_root, s_id, on_unknown_label="ignore")
    assert scene.stats["unknown_labels"] == 1


def test_segments_length_differs_from_mesh(trees):
    s_root, s_id, s_dir, *_ = trees
    path = s_dir / scannetpp.SEGMENTS_FILE
    doc = json.loads(path.read_text())
    doc["segIndices"] = doc["segIndices"][:-5]
    path.write_text(json.dumps(doc))
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "segments.json", "[segIndices]", "vertices")


def test_missing_images(trees):
    s_root, s_id, s_dir, r_root, r_id, r_dir = trees
    (s_dir / "dslr/undistorted_images/DSC00002.JPG").unlink()
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "DSC00002.JPG", "missing")
    (r_dir / "results/frame000001.jpg").unlink()
    _expect(lambda: replica.read_scene(r_root, r_id), "frame000001.jpg", "missing")


def test_nan_poses(trees):
    s_root, s_id, s_dir, r_root, r_id, r_dir = trees
    images = s_dir / scannetpp.COLMAP_IMAGES_FILE
    original = images.read_text()
    lines = original.splitlines()
    i = next(k for k, line in enumerate(lines) if line and not line.startswith("#"))
    parts = lines[i].split()
    parts[5] = "nan"
    lines[i] = " ".join(parts)
    images.write_text("\n".join(lines) + "\n")
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "images.txt", "TX", "not finite")
    images.write_text(original)
    tpath = s_dir / scannetpp.TRANSFORMS_FILE
    doc = json.loads(tpath.read_text())
    doc["frames"][0]["transform_matrix"][0][3] = float("nan")
    tpath.write_text(json.dumps(doc))
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "transforms_undistorted.json", "frames[0].transform_matrix", "NaN")
    traj = r_dir / replica.NICE_SLAM_TRAJ
    rows = traj.read_text().splitlines()
    rows[1] = " ".join(["nan"] + rows[1].split()[1:])
    traj.write_text("\n".join(rows) + "\n")
    _expect(lambda: replica.read_scene(r_root, r_id), "traj.txt", "line 2", "not finite")


def test_bad_frames_are_skipped_and_counted(trees):
    s_root, s_id, s_dir, *_ = trees
    tpath = s_dir / scannetpp.TRANSFORMS_FILE
    doc = json.loads(tpath.read_text())
    doc["frames"][0]["is_bad"] = True
    bad_name = doc["frames"][0]["file_path"]
    tpath.write_text(json.dumps(doc))
    scene = scannetpp.read_scene(s_root, s_id)
    assert scene.stats["bad_frames"] == 1
    assert bad_name not in {v.name for v in scene.views} and len(scene.views) == SMALL.num_views - 1


def test_corrupt_mesh_and_out_of_range_ids(trees):
    s_root, s_id, s_dir, r_root, r_id, r_dir = trees
    mesh = s_dir / scannetpp.MESH_FILE
    mesh.write_bytes(mesh.read_bytes()[:300])
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "mesh_aligned_0.05.ply", "unreadable PLY")
    (s_dir / scannetpp.MASK_FILE)  # unchanged
    info_path = r_dir / replica.INFO_FILE
    info = json.loads(info_path.read_text())
    info["id_to_label"] = info["id_to_label"][:3]
    info_path.write_text(json.dumps(info))
    _expect(lambda: replica.read_scene(r_root, r_id), "mesh_semantic.ply", "face.object_id", "out of range")


def test_mask_with_bad_vertex_id(trees):
    s_root, s_id, s_dir, *_ = trees
    (s_dir / scannetpp.MASK_FILE).write_text("3\n99999999\n")
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "mesh_aligned_0.05_mask.txt", "out of range")


def test_empty_scenes_raise_a_countable_error(trees):
    s_root, s_id, s_dir, r_root, r_id, r_dir = trees
    path = s_dir / scannetpp.ANNOTATION_FILE
    doc = json.loads(path.read_text())
    for group in doc["segGroups"]:
        group["label"] = "object"  # dropped by the map
    path.write_text(json.dumps(doc))
    err = _expect(lambda: scannetpp.read_scene(s_root, s_id), "no vertex", kind=EmptySceneError)
    assert isinstance(err, SourceError) and isinstance(err, ValueError)
    info_path = r_dir / replica.INFO_FILE
    info = json.loads(info_path.read_text())
    info["id_to_label"] = [-1] * len(info["id_to_label"])
    info_path.write_text(json.dumps(info))
    _expect(lambda: replica.read_scene(r_root, r_id), "no vertex", kind=EmptySceneError)


def test_fisheye_only_scene_says_what_to_run(trees):
    # a download before undistortion: distorted data (fisheye transforms.json, resized_images/) only
    s_root, s_id, s_dir, *_ = trees
    dslr = s_dir / "dslr"
    (dslr / "nerfstudio/transforms_undistorted.json").unlink()
    for folder in ("undistorted_images", "undistorted_anon_masks", "resized_undistorted_images", "resized_undistorted_masks"):
        shutil.rmtree(dslr / folder)
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "OPENCV_FISHEYE", "dslr.undistort", "resized_images")


def test_split_files_and_listing(trees, tmp_path):
    s_root, s_id, *_ = trees
    assert scannetpp.list_scenes(s_root) == [s_id]
    assert scannetpp.list_scenes(s_root, "nvs_sem_train") == [s_id]
    (s_root / "splits/nvs_sem_val.txt").write_text("0123456789\n")
    _expect(lambda: scannetpp.list_scenes(s_root, "nvs_sem_val"), "nvs_sem_val.txt", "line 1", "0123456789")
    _expect(lambda: scannetpp.list_scenes(tmp_path / "nowhere"), "missing")
    _expect(lambda: replica.list_scenes(tmp_path / "nowhere"), "missing")


def test_replica_renders_into_the_cache_never_the_raw_tree(trees, tmp_path):
    *_, r_root, r_id, r_dir = trees
    (r_dir / replica.NICE_SLAM_TRAJ).unlink()
    before = sorted(p for p in r_root.rglob("*"))
    assert replica.read_scene(r_root, r_id).stats["views_source"] == "none"
    _expect(lambda: replica.read_scene(r_root, r_id, cache_dir=r_dir / "cache"), "inside the raw tree")
    scene = replica.read_scene(r_root, r_id, cache_dir=tmp_path / "cache")
    assert scene.stats["views_source"] == "rendered" and len(scene.views) == replica.RENDER_VIEWS
    assert sum(v.role == "novel" for v in scene.views) == replica.RENDER_VIEWS // 8
    assert all(v.image_path.is_file() and v.semantic_path.is_file() for v in scene.views)
    assert sorted(p for p in r_root.rglob("*")) == before
    from seggaussian.sources._common import read_image

    labels = np.concatenate([read_image(v.semantic_path, "gt", unchanged=True).ravel() for v in scene.views[:8]])
    assert len(set(labels.tolist()) & set(scene.semantic.tolist())) >= 5
    mtime = scene.views[0].image_path.stat().st_mtime_ns
    replica.read_scene(r_root, r_id, cache_dir=tmp_path / "cache")  # cached: not rendered again
    assert scene.views[0].image_path.stat().st_mtime_ns == mtime


def test_mask_as_per_vertex_flags_and_bad_label_types(trees):
    s_root, s_id, s_dir, *_ = trees
    n = len(scannetpp.read_scene(s_root, s_id).points)
    flags = np.zeros(n, dtype=int)
    flags[[5, 6, 7]] = 1
    (s_dir / scannetpp.MASK_FILE).write_text("".join(f"{f}\n" for f in flags))
    scene = scannetpp.read_scene(s_root, s_id)
    assert scene.stats["mask_format"] == "per-vertex flags" and scene.stats["masked_vertices"] == 3
    assert (scene.semantic[[5, 6, 7]] == 65535).all()
    path = s_dir / scannetpp.ANNOTATION_FILE
    doc = json.loads(path.read_text())
    doc["segGroups"][1]["label"] = 7
    path.write_text(json.dumps(doc))
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "segGroups[1].label", "not a string")
    doc["segGroups"][1] = {"label": "wall", "objectId": 2, "segments": "all"}
    path.write_text(json.dumps(doc))
    _expect(lambda: scannetpp.read_scene(s_root, s_id), "segGroups[1].segments")
