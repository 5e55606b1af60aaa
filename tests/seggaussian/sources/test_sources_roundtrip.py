"""synth -> read round trip: labels per vertex, cameras, and projections onto the ground-truth images."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.sources import replica, scannetpp
from seggaussian.sources.synthetic import replica as synth_replica
from seggaussian.sources.synthetic import scannetpp as synth_scannetpp
from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources._common import read_image
from seggaussian.sources.raycast import MeshRaycaster

SEED = 7
CONFIG = synthetic.SynthConfig(width=240, num_views=10)
#: A vertex counts as visible when its camera depth is within this of the depth raycast through the
#: centre of the pixel it falls in (metres): contact edges are embedded >= 1 cm (synth_room.EMBED);
#: vertices on oblique surfaces away from the pixel centre fail the test and are simply not counted.
DEPTH_TOL = 0.002


@pytest.fixture(scope="module")
def scannetpp_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("scannetpp")
    ids = synthetic.synthesize(root, 1, SEED, "scannetpp", CONFIG)
    return root, ids


@pytest.fixture(scope="module")
def replica_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("replica")
    ids = synthetic.synthesize(root, 1, SEED, "replica", CONFIG)
    return root, ids


def test_scannetpp_vertex_labels_are_the_generators(scannetpp_root):
    root, ids = scannetpp_root
    scene = scannetpp.read_scene(root, ids[0])
    room, cameras = synthetic.build_scene(SEED, 0, "scannetpp", CONFIG)
    semantic, instance = synth_scannetpp.intended_labels(room)
    np.testing.assert_allclose(scene.points, room.vertices, atol=1e-5)  # float32 on disk
    np.testing.assert_array_equal(scene.semantic, semantic)
    np.testing.assert_array_equal(scene.instance, instance)
    np.testing.assert_array_equal(scene.multilabel[:, 0], scene.semantic)
    names = read_class_names()
    # books sit inside the bookshelf's annotation group: smallest instance wins, both kept as multilabel
    books = scene.semantic == names.index("book")
    assert books.any()
    assert (scene.multilabel[books, 1] == names.index("bookshelf")).all()
    # rug (kept by the map, not top-100), "object" (dropped by the map) and the mask are ignore
    keys = np.array([o.key for o in room.objects])[room.vertex_object]
    assert (scene.semantic[(keys == "rug") | (keys == "clutter")] == IGNORE_LABEL).all()
    assert scene.stats["masked_vertices"] == len(synth_scannetpp.choose_mask(room)) > 0
    assert len({names[c] for c in np.unique(scene.semantic) if c != IGNORE_LABEL}) >= 15
    for unseen in ("curtain", "bookshelf", "sofa", "bed"):
        assert (scene.semantic == names.index(unseen)).any(), unseen


def test_scannetpp_cameras_and_roles(scannetpp_root):
    root, ids = scannetpp_root
    scene = scannetpp.read_scene(root, ids[0])
    _, cameras = synthetic.build_scene(SEED, 0, "scannetpp", CONFIG)
    by_name = {v.name: v for v in scene.views}
    assert len(by_name) == len(cameras)
    for i, cam in enumerate(cameras):
        view = by_name[synth_scannetpp.image_name(i)]
        np.testing.assert_allclose(view.camera.viewmat, cam.viewmat, atol=1e-9)
        np.testing.assert_allclose(view.camera.K, cam.K, atol=1e-9)
        assert view.role == ("novel" if i % 8 == 0 else "train")
        assert view.semantic_path is not None and view.instance_path is not None
    assert scene.stats["pose_disagreements"] == 0


def test_replica_vertex_labels_are_the_generators(replica_root):
    root, ids = replica_root
    scene = replica.read_scene(root, ids[0])
    room, cameras = synthetic.build_scene(SEED, 0, "replica", CONFIG)
    semantic, instance = synth_replica.intended_labels(room)
    # degenerate cap/pole vertices belong to their object too: every vertex has faces
    np.testing.assert_array_equal(scene.semantic, semantic)
    np.testing.assert_array_equal(scene.instance, instance)
    assert scene.stats["conflicting_vertices"] == 0
    assert len(scene.views) == len(cameras)
    for view, cam in zip(scene.views, cameras):
        np.testing.assert_allclose(view.camera.viewmat, cam.viewmat, atol=1e-9)
        np.testing.assert_allclose(view.camera.K, cam.K, atol=1e-12)
    names = read_class_names()
    present = {names[c] for c in np.unique(scene.semantic) if c != IGNORE_LABEL}
    assert {"curtain", "sofa", "bed", "shelf", "wall", "floor"} <= present


def _projection_agreement(scene) -> tuple[int, int]:
    """(agreeing, visible) labelled vertices over all views."""
    caster = MeshRaycaster(scene.points, scene.faces)
    labelled = np.flatnonzero(scene.semantic != IGNORE_LABEL)
    agree = visible = 0
    for view in scene.views:
        cam = view.camera
        gt = read_image(view.semantic_path, "gt", unchanged=True).astype(np.int64)
        assert gt.shape == (cam.height, cam.width)
        depth = caster.cast(cam).depth
        uv, z = cam.project(scene.points[labelled])
        px = np.floor(uv).astype(np.int64)
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        idx, px, z = labelled[inside], px[inside], z[inside]
        seen = np.abs(depth[px[:, 1], px[:, 0]] - z) < DEPTH_TOL
        visible += int(seen.sum())
        agree += int((gt[px[seen, 1], px[seen, 0]] == scene.semantic[idx[seen]]).sum())
    return agree, visible


@pytest.mark.parametrize("which", ["scannetpp", "replica"])
def test_projected_vertices_land_on_their_label(which, scannetpp_root, replica_root):
    root, ids = scannetpp_root if which == "scannetpp" else replica_root
    reader = scannetpp if which == "scannetpp" else replica
    scene = reader.read_scene(root, ids[0])
    agree, visible = _projection_agreement(scene)
    assert visible > 10000
    assert agree / visible >= 0.99, (agree, visible)


def test_images_exist_and_have_the_camera_size(scannetpp_root, replica_root):
    for reader, (root, ids) in ((scannetpp, scannetpp_root), (replica, replica_root)):
        scene = reader.read_scene(root, ids[0])
        for view in scene.views[:3]:
            rgb = read_image(view.image_path, "rgb")
            assert rgb.shape == (view.camera.height, view.camera.width, 3)
            assert rgb.std() > 10  # textured, not a flat image


def _tree_digest(root) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("layout", ["scannetpp", "replica"])
def test_synthesis_is_deterministic(tmp_path, layout):
    small = synthetic.SynthConfig(width=48, num_views=2, max_edge=0.15)
    a = synthetic.synthesize(tmp_path / "a", 1, 3, layout, small)
    b = synthetic.synthesize(tmp_path / "b", 1, 3, layout, small)
    c = synthetic.synthesize(tmp_path / "c", 1, 4, layout, small)
    assert a == b
    assert _tree_digest(tmp_path / "a") == _tree_digest(tmp_path / "b")
    assert _tree_digest(tmp_path / "a") != _tree_digest(tmp_path / "c")
    assert not any(p.name.startswith(".") for p in (tmp_path / "a").rglob("*"))  # no staging left


@pytest.mark.parametrize("layout", ["scannetpp", "replica"])
def test_synthesis_in_processes_writes_the_same_tree(tmp_path, layout, monkeypatch):
    """jobs=2 (a spawned pool, scenes finishing in any order) writes the bytes of jobs=1, ids in index order."""
    from concurrent.futures import ProcessPoolExecutor

    pools = []

    class RecordedPool(ProcessPoolExecutor):
        def __init__(self, *args, **kwargs):
            pools.append(kwargs.get("max_workers"))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(synthetic, "ProcessPoolExecutor", RecordedPool)
    small = synthetic.SynthConfig(width=48, num_views=2, max_edge=0.15)
    seen = []
    serial = synthetic.synthesize(tmp_path / "a", 3, 3, layout, small)
    assert pools == []
    pooled = synthetic.synthesize(tmp_path / "b", 3, 3, layout, small, jobs=2,
                                  progress=lambda index, name: seen.append((index, name)))
    assert pools == [2]  # the scenes were written by a pool of two processes
    assert pooled == serial and sorted(seen) == list(enumerate(serial))
    assert _tree_digest(tmp_path / "a") == _tree_digest(tmp_path / "b")
    assert not any(p.name.startswith(".") for p in (tmp_path / "b").rglob("*"))


def test_reading_never_writes_into_the_raw_tree(scannetpp_root, replica_root):
    for reader, (root, ids) in ((scannetpp, scannetpp_root), (replica, replica_root)):
        before = {p: p.stat().st_mtime_ns for p in root.rglob("*")}
        reader.read_scene(root, ids[0])
        reader.list_scenes(root)
        assert {p: p.stat().st_mtime_ns for p in root.rglob("*")} == before
