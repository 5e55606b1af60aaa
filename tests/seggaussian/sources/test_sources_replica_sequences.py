"""Replica Semantic-NeRF sequences: intrinsics scaled to the frame size, class images mapped to top-100."""

from __future__ import annotations

import numpy as np

from seggaussian.core.cameras import Camera, intrinsics
from seggaussian.core.classes import replica_class_names
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.sources import replica
from seggaussian.sources.synthetic import replica as synth_replica
from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources._common import atomic_write_image, read_image, triangulate_quads
from seggaussian.sources.raycast import render_labelled_views
from seggaussian.sources.synthetic.mesh import CLASS_TABLE

SMALL = synthetic.SynthConfig(width=64, num_views=9, max_edge=0.15)


def test_semantic_nerf_sequence(tmp_path):
    root = tmp_path / "raw"
    (room_name,) = synthetic.synthesize(root, 1, 2, "replica", SMALL)
    room_dir = root / room_name
    (room_dir / replica.NICE_SLAM_TRAJ).unlink()  # leave only the Semantic-NeRF sequence
    room, cameras = synthetic.build_scene(2, 0, "replica", SMALL)
    w, h = 64, 48  # 640x480 / 10
    K = intrinsics(32.0, 32.0, 31.95, 23.95)
    cams = [Camera(K, c.viewmat, w, h) for c in cameras]
    names = replica_class_names()
    class_of_object = np.array([names.index(CLASS_TABLE[o.key][2]) + 1 if CLASS_TABLE[o.key][2] else 0 for o in room.objects])
    tris, src = triangulate_quads(room.quads)
    face_class = class_of_object[room.vertex_object[room.quads[src, 0]]]
    seq = room_dir / replica.SEMANTIC_NERF_DIR
    (seq / "rgb").mkdir(parents=True)
    (seq / "semantic_class").mkdir()
    (seq / replica.SEMANTIC_NERF_TRAJ).write_text("".join(" ".join(f"{x:.17g}" for x in c.c2w.ravel()) + "\n" for c in cams))
    raw_classes = []
    for i, render in enumerate(render_labelled_views(room.vertices, tris, room.colors, face_class, face_class, cams)):
        atomic_write_image(seq / "rgb" / f"rgb_{i}.png", render.rgb)
        classes = np.where(render.semantic == IGNORE_LABEL, 0, render.semantic)
        atomic_write_image(seq / "semantic_class" / f"semantic_class_{i}.png", classes.astype(np.uint16))
        raw_classes.append(classes)

    no_cache = replica.read_scene(root, room_name)
    assert no_cache.stats["views_source"] == "semantic-nerf" and no_cache.views[0].semantic_path is None
    scene = replica.read_scene(root, room_name, cache_dir=tmp_path / "cache")
    assert len(scene.views) == len(cams)
    for view, cam in zip(scene.views, cams):
        np.testing.assert_allclose(view.camera.K, K, atol=1e-12)
        np.testing.assert_allclose(view.camera.viewmat, cam.viewmat, atol=1e-9)
    # class images -> top-100, the same labels as the generator's own ground truth
    from seggaussian.core.classes import replica_class_to_top100

    for i in (0, 4):
        mapped = read_image(scene.views[i].semantic_path, "mapped", unchanged=True)
        expected = np.vectorize(lambda c: IGNORE_LABEL if c == 0 else (replica_class_to_top100(names[c - 1]) if replica_class_to_top100(names[c - 1]) is not None else IGNORE_LABEL))(raw_classes[i])
        np.testing.assert_array_equal(mapped, expected)
    sem, _ = synth_replica.intended_labels(room)
    np.testing.assert_array_equal(scene.semantic, sem)
    assert [v.role for v in scene.views].count("novel") == 2
