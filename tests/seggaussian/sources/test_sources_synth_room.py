"""Synthetic room geometry: edge lengths, classes, determinism, degenerate configs."""

from __future__ import annotations

import numpy as np
import pytest

from seggaussian.core.constants import read_class_names
from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources.synthetic.mesh import CLASS_TABLE, RAW_LABEL_MAP, RoomConfig
from seggaussian.sources.synthetic.room import build_room


@pytest.mark.parametrize("style", ["scannetpp", "replica"])
def test_edges_classes_and_shapes(style):
    room = build_room(np.random.default_rng(4), RoomConfig(style=style, max_edge=0.05))
    v, q = room.vertices, room.quads
    edges = np.stack([np.linalg.norm(v[q[:, i]] - v[q[:, (i + 1) % 4]], axis=1) for i in range(4)], axis=1)
    assert edges.max() <= 0.05 * 1.02  # 2%: curved surfaces are sampled, not measured exactly
    assert len(v) == len(room.normals) == len(room.colors) == len(room.vertex_object) == len(room.vertex_segment)
    assert np.isfinite(v).all() and np.isfinite(room.normals).all()
    assert q.min() >= 0 and q.max() < len(v)
    # every quad belongs to one object (objects are not welded together)
    assert (room.vertex_object[q] == room.vertex_object[q[:, :1]]).all()
    names = set(read_class_names())
    top = {CLASS_TABLE[o.key][0] for o in room.objects} - {None}
    assert top <= names and len(top) >= 15
    # textured: many distinct colours on every large surface
    for key in ("wall", "floor"):
        ids = [i for i, o in enumerate(room.objects) if o.key == key]
        colours = room.colors[np.isin(room.vertex_object, ids)]
        assert len(np.unique(colours, axis=0)) > 50, key
    # the vertices stay inside the room shell (+ its overlap)
    assert (v >= room.room_min - 0.05).all() and (v <= room.room_max + 0.05).all()


def test_raw_labels_cover_the_map():
    raws = {CLASS_TABLE[k][1] for k in CLASS_TABLE}
    assert raws == set(RAW_LABEL_MAP)
    names = set(read_class_names())
    for raw, target in RAW_LABEL_MAP.items():
        mapped = None if target == "None" else (target or raw)
        assert mapped is None or mapped in names or raw == "rug", raw


def test_rooms_vary_with_the_seed_and_repeat_with_it():
    a = build_room(np.random.default_rng(1))
    b = build_room(np.random.default_rng(1))
    c = build_room(np.random.default_rng(2))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.colors, b.colors)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


def test_bad_configs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="layout"):
        synthetic.synthesize(tmp_path, 1, 0, "scannet")
    with pytest.raises(ValueError, match="num_scenes"):
        synthetic.synthesize(tmp_path, -1, 0, "replica")
    with pytest.raises(ValueError, match="SynthConfig"):
        synthetic.synthesize(tmp_path, 1, 0, "replica", synthetic.SynthConfig(max_edge=0.0))
    assert synthetic.synthesize(tmp_path / "none", 0, 0, "scannetpp") == []
