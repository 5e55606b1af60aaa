"""Vectorized label rules against slow per-vertex references, on random and degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.sources._common import SourceError, triangulate_quads
from seggaussian.sources.replica import compute_vertex_objects, compute_vertex_objects_reference
from seggaussian.sources.scannetpp import compute_vertex_labels, compute_vertex_labels_reference


@pytest.mark.parametrize("seed", range(6))
def test_smallest_instance_rule_matches_reference(seed):
    rng = np.random.default_rng(seed)
    p = int(rng.integers(1, 80))
    seg = rng.integers(0, 12, size=p) * 7  # sparse segment ids, like ScanNet++'s
    groups = []
    for g in range(int(rng.integers(0, 9))):
        segs = rng.choice(np.arange(0, 100, 7), size=int(rng.integers(0, 5)), replace=False)
        label = int(rng.integers(-1, 5))  # -1: dropped by the map
        groups.append((label, g + 1, segs))
    fast = compute_vertex_labels(seg, groups)
    slow = compute_vertex_labels_reference(seg, groups)
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a, b)


def test_smallest_instance_rule_by_hand():
    seg = np.array([0, 0, 1, 1, 2, 5])
    groups = [(3, 10, np.array([0, 1, 2])),  # 5 vertices: big "bookshelf"
              (7, 11, np.array([1])),  # 2 vertices: a "book" inside it
              (3, 12, np.array([1, 2])),  # same class again: multilabel keeps it once
              (-1, 13, np.array([5])),  # dropped by the map
              (9, 14, np.array([0, 2]))]
    semantic, instance, multilabel = compute_vertex_labels(seg, groups)
    np.testing.assert_array_equal(semantic, [9, 9, 7, 7, 3, 65535])
    np.testing.assert_array_equal(instance, [14, 14, 11, 11, 12, 65535])
    np.testing.assert_array_equal(multilabel[2], [7, 3, 65535])
    np.testing.assert_array_equal(multilabel[0], [9, 3, 65535])
    empty = compute_vertex_labels(np.zeros(0, dtype=np.int64), groups)
    assert all(a.shape[0] == 0 for a in empty)


@pytest.mark.parametrize("seed", range(5))
def test_vertex_objects_match_reference(seed):
    rng = np.random.default_rng(seed)
    v = int(rng.integers(1, 40))
    faces = rng.integers(0, v, size=(int(rng.integers(0, 30)), 4))
    objects = rng.integers(0, 4, size=len(faces))
    fast, conflicts = compute_vertex_objects(v, faces, objects) if len(faces) else (np.full(v, -1), 0)
    np.testing.assert_array_equal(fast, compute_vertex_objects_reference(v, faces, objects))
    assert conflicts >= 0


def test_triangulate_quads_drops_degenerates():
    quads = np.array([[0, 1, 2, 3], [4, 5, 6, 6]])
    tris, src = triangulate_quads(quads)
    np.testing.assert_array_equal(tris, [[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(src, [0, 0, 1])
    assert IGNORE_LABEL == 65535


def test_fast_ply_writer_matches_plyfile_and_reads_back(tmp_path):
    import io

    from plyfile import PlyData, PlyElement

    from seggaussian.sources._common import encode_mesh_ply, read_mesh_ply

    rng = np.random.default_rng(0)
    vertex = np.empty(7, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for name in ("x", "y", "z"):
        vertex[name] = rng.normal(size=7)
    for name in ("red", "green", "blue"):
        vertex[name] = rng.integers(0, 256, size=7)
    quads = rng.integers(0, 7, size=(5, 4))
    object_id = rng.integers(0, 9, size=5)
    fast = encode_mesh_ply(vertex, quads, {"object_id": object_id})
    face = np.empty(5, dtype=[("vertex_indices", "O"), ("object_id", "<i4")])
    face["vertex_indices"] = list(quads.astype(np.int32))
    face["object_id"] = object_id
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex"),
             PlyElement.describe(face, "face", val_types={"vertex_indices": "i4"}, len_types={"vertex_indices": "u1"})],
            text=False, byte_order="<").write(buffer)
    assert fast == buffer.getvalue()
    (tmp_path / "m.ply").write_bytes(fast)
    mesh = read_mesh_ply(tmp_path / "m.ply", face_properties=("object_id",))
    np.testing.assert_array_equal(mesh["faces"], quads)
    np.testing.assert_array_equal(mesh["object_id"], object_id)
    np.testing.assert_allclose(mesh["points"][:, 0], vertex["x"])
    (tmp_path / "t.ply").write_bytes(encode_mesh_ply(vertex, quads[:, :3]))
    assert read_mesh_ply(tmp_path / "t.ply")["faces"].shape == (5, 3)
    # mixed polygon sizes take the slow path and are refused with the field named
    mixed = np.empty(2, dtype=[("vertex_indices", "O")])
    mixed["vertex_indices"] = [np.array([0, 1, 2], np.int32), np.array([0, 1, 2, 3], np.int32)]
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(mixed, "face")]).write(str(tmp_path / "x.ply"))
    with pytest.raises(SourceError, match=r"x\.ply \[face\.vertex_indices\]: expected all triangles or all quads"):
        read_mesh_ply(tmp_path / "x.ply")
