"""Write a synthetic room in the ScanNet++ on-disk layout (see ``scannetpp.py`` and SOURCES.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.cameras import Camera
from seggaussian.constants import IGNORE_LABEL, read_class_names
from seggaussian.sources import scannetpp as layout
from seggaussian.sources._common import (
    atomic_write_bytes,
    encode_mesh_ply,
    atomic_write_image,
    atomic_write_json,
    atomic_write_text,
    triangulate_quads,
)
from seggaussian.sources.raycast import render_labelled_views
from seggaussian.sources.synth_room import CLASS_TABLE, RAW_LABEL_MAP, RoomMesh

#: Radius (metres) of the anonymization-like masked disc the generator cuts out of one wall.
MASK_RADIUS = 0.25
#: Every ``NOVEL_VIEW_EVERY``-th view (index % 8 == 0) goes to the test list.
NOVEL_VIEW_EVERY = 8


def image_name(index: int) -> str:
    return f"DSC{index + 1:05d}.JPG"


def choose_mask(room: RoomMesh) -> np.ndarray:
    """Vertex ids in a disc of ``MASK_RADIUS`` around the middle of the first wall (deterministic)."""
    first_wall = next(i for i, o in enumerate(room.objects) if o.key == "wall")
    ids = np.flatnonzero(room.vertex_object == first_wall)
    centre = room.vertices[ids].mean(axis=0)
    near = np.linalg.norm(room.vertices[ids] - centre, axis=1) < MASK_RADIUS
    return ids[near]


def intended_labels(room: RoomMesh) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex (semantic, instance) the reader must recover: class of the object's top-100 name,
    instance = objectId (object index + 1); ignore for unmapped classes and masked vertices."""
    semantic = _object_classes(room)[room.vertex_object].astype(np.int32)
    instance = np.where(semantic != IGNORE_LABEL, room.vertex_object + 1, IGNORE_LABEL).astype(np.int32)
    masked = choose_mask(room)
    semantic[masked] = IGNORE_LABEL
    instance[masked] = IGNORE_LABEL
    return semantic, instance


def _ply_bytes(room: RoomMesh, triangles: np.ndarray) -> bytes:
    vertex = np.empty(len(room.vertices), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = room.vertices[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = room.colors[:, k]
    return encode_mesh_ply(vertex, triangles)


def write_scene(data_root: Path, scene_id: str, room: RoomMesh, cameras: list[Camera]) -> None:
    """All files of one scene under ``data_root/data/<scene_id>``."""
    scene_dir = Path(data_root) / "data" / scene_id
    triangles, _ = triangulate_quads(room.quads)
    atomic_write_bytes(scene_dir / layout.MESH_FILE, _ply_bytes(room, triangles))

    # over-segmentation: a segment's id is its smallest vertex index (the ScanNet convention)
    num_segments = int(room.vertex_segment.max()) + 1
    seg_id = np.full(num_segments, np.iinfo(np.int64).max)
    np.minimum.at(seg_id, room.vertex_segment, np.arange(len(room.vertices)))
    seg_indices = seg_id[room.vertex_segment]
    atomic_write_json(scene_dir / layout.SEGMENTS_FILE, {"sceneId": scene_id, "segIndices": seg_indices.tolist()}, indent=None)

    object_segments = [np.unique(seg_indices[room.vertex_object == i]) for i in range(len(room.objects))]
    groups = []
    for i, obj in enumerate(room.objects):
        segs = np.unique(np.concatenate([object_segments[i]] + [object_segments[j] for j in obj.contains]))
        groups.append({"id": i + 1, "objectId": i + 1, "label": CLASS_TABLE[obj.key][1], "segments": segs.tolist()})
    atomic_write_json(scene_dir / layout.ANNOTATION_FILE, {"sceneId": scene_id, "segGroups": groups}, indent=None)
    atomic_write_text(scene_dir / layout.MASK_FILE, "".join(f"{v}\n" for v in choose_mask(room)))

    # cameras: COLMAP (mesh frame, world-to-camera) + nerfstudio transforms the toolkit's way
    K, width, height = cameras[0].K, cameras[0].width, cameras[0].height
    names = [image_name(i) for i in range(len(cameras))]
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (camera, name) in enumerate(zip(cameras, names)):
        q = layout.rotation_to_quaternion(camera.viewmat[:3, :3])
        t = camera.viewmat[:3, 3]
        lines.append(" ".join([str(i + 1)] + [f"{x:.12f}" for x in (*q, *t)] + ["1", name]))
        lines.append("")
    atomic_write_text(scene_dir / layout.COLMAP_IMAGES_FILE, "\n".join(lines) + "\n")
    atomic_write_text(scene_dir / layout.COLMAP_CAMERAS_FILE, "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                      f"1 PINHOLE {width} {height} {K[0, 0]:.12f} {K[1, 1]:.12f} {K[0, 2]:.12f} {K[1, 2]:.12f}\n")
    test = [i % NOVEL_VIEW_EVERY == 0 for i in range(len(cameras))]
    frame = lambda i: {"file_path": names[i], "transform_matrix": layout.toolkit_transform_matrix(cameras[i].viewmat).round(12).tolist(), "is_bad": False}  # noqa: E731
    atomic_write_json(scene_dir / layout.TRANSFORMS_FILE, {
        "camera_model": "PINHOLE", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "w": int(width), "h": int(height), "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0,
        "frames": [frame(i) for i in range(len(cameras)) if not test[i]],
        "test_frames": [frame(i) for i in range(len(cameras)) if test[i]],
    })
    atomic_write_json(scene_dir / layout.TRAIN_TEST_FILE, {"train": [n for n, t in zip(names, test) if not t], "test": [n for n, t in zip(names, test) if t]})

    # images and ground-truth label images rendered from the mesh; a face is void when its object
    # has no top-100 class or all three of its vertices are masked
    face_object = room.vertex_object[triangles[:, 0]]
    face_masked = np.isin(triangles, choose_mask(room)).all(axis=1)
    face_semantic = np.where(face_masked, IGNORE_LABEL, _object_classes(room)[face_object])
    face_instance = np.where(face_semantic == IGNORE_LABEL, IGNORE_LABEL, face_object + 1)
    renders = render_labelled_views(room.vertices, triangles, room.colors, face_semantic, face_instance, cameras)
    for name, render in zip(names, renders):
        stem = Path(name).stem
        atomic_write_image(scene_dir / layout.IMAGE_DIRS[0] / name, render.rgb)
        atomic_write_image(scene_dir / layout.SEMANTIC_RENDER_DIR / f"{stem}.png", render.semantic.astype(np.uint16))
        atomic_write_image(scene_dir / layout.INSTANCE_RENDER_DIR / f"{stem}.png", render.instance.astype(np.uint16))


def _object_classes(room: RoomMesh) -> np.ndarray:
    """``[num objects]`` top-100 class id of each object (IGNORE_LABEL for rug / clutter)."""
    names = read_class_names()
    return np.array([names.index(CLASS_TABLE[o.key][0]) if CLASS_TABLE[o.key][0] else IGNORE_LABEL for o in room.objects], dtype=np.int64)


def write_metadata(data_root: Path, scene_ids: list[str], val_every: int = 5) -> None:
    """``metadata/semantic_benchmark/{map_benchmark.csv, top100.txt}`` and ``splits/nvs_sem_*.txt``
    (every ``val_every``-th scene is a val scene, at least one when there are two or more)."""
    data_root = Path(data_root)
    rows = [",class,count,vertex_count,voxel_count,semantic_map_to,instance_map_to"]
    for i, (raw, target) in enumerate(sorted(RAW_LABEL_MAP.items())):
        rows.append(f"{i},{raw},1,1,1,{target},{target}")
    atomic_write_text(data_root / layout.LABEL_MAP_FILE, "\n".join(rows) + "\n")
    atomic_write_text(data_root / layout.TOP100_FILE, "\n".join(read_class_names()) + "\n")
    val = [s for i, s in enumerate(scene_ids) if len(scene_ids) > 1 and i % val_every == val_every - 1 or (len(scene_ids) > 1 and len(scene_ids) < val_every and i == len(scene_ids) - 1)]
    train = [s for s in scene_ids if s not in val]
    atomic_write_text(data_root / layout.SPLITS_DIR / "nvs_sem_train.txt", "".join(f"{s}\n" for s in train))
    atomic_write_text(data_root / layout.SPLITS_DIR / "nvs_sem_val.txt", "".join(f"{s}\n" for s in val))
