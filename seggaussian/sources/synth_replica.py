"""Write a synthetic room in the Replica layout (habitat mesh + info + a NICE-SLAM style sequence).

The sequence is rendered at a reduced resolution (default 320 x 181, the NICE-SLAM 1200 x 680
aspect); the reader scales the NICE-SLAM intrinsics to the image size (``nice_slam_intrinsics``),
and the generator renders with exactly those intrinsics. Ground-truth label images go to
``<room>/seggaussian_gt/`` (a toolkit extension; see SOURCES.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.cameras import Camera
from seggaussian.constants import IGNORE_LABEL
from seggaussian.sources import replica as layout
from seggaussian.sources._common import atomic_write_bytes, encode_mesh_ply, atomic_write_image, atomic_write_json, atomic_write_text, triangulate_quads
from seggaussian.sources.raycast import render_labelled_views
from seggaussian.classes import replica_class_names, replica_class_to_top100
from seggaussian.sources.synth_room import CLASS_TABLE, RoomMesh

#: Depth PNG values saturate here (uint16 max / NICE_SLAM_DEPTH_SCALE ~ 10 m).
MAX_DEPTH_VALUE = 65535


def replica_size(width: int) -> tuple[int, int]:
    """(width, height) of a NICE-SLAM aspect render ``width`` pixels wide."""
    return width, int(round(width * layout.NICE_SLAM_SIZE[1] / layout.NICE_SLAM_SIZE[0]))


def object_ids(room: RoomMesh) -> np.ndarray:
    """Replica object id of each synthetic object (index + 1; id 0 is void)."""
    return np.arange(len(room.objects)) + 1


def intended_labels(room: RoomMesh) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex (semantic, instance) the reader must recover."""
    sem_obj, ins_obj = _object_labels(room)
    return sem_obj[room.vertex_object].astype(np.int32), ins_obj[room.vertex_object].astype(np.int32)


def _object_labels(room: RoomMesh) -> tuple[np.ndarray, np.ndarray]:
    sem, ins = [], []
    for i, obj in enumerate(room.objects):
        cls = CLASS_TABLE[obj.key][2]
        top = replica_class_to_top100(cls) if cls is not None else None
        sem.append(IGNORE_LABEL if top is None else top)
        ins.append(IGNORE_LABEL if cls is None else i + 1)
    return np.asarray(sem, dtype=np.int64), np.asarray(ins, dtype=np.int64)


def _info(room: RoomMesh) -> dict:
    names = replica_class_names()
    class_id = {n: i + 1 for i, n in enumerate(names)}
    objects, id_to_label = [], [-1]  # object id 0: void
    for i, obj in enumerate(room.objects):
        cls = CLASS_TABLE[obj.key][2]
        id_to_label.append(-1 if cls is None else class_id[cls])
        if cls is not None:
            objects.append({"id": i + 1, "class_id": class_id[cls], "class_name": cls})
    return {"classes": [{"id": class_id[n], "name": n, "children": [], "parents": []} for n in names],
            "objects": objects, "id_to_label": id_to_label, "gravity_dir": [0.0, 0.0, -1.0]}


def _ply_bytes(room: RoomMesh) -> bytes:
    vertex = np.empty(len(room.vertices), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                                                 ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = room.vertices[:, k]
        vertex["n" + axis] = room.normals[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = room.colors[:, k]
    return encode_mesh_ply(vertex, room.quads, {"object_id": object_ids(room)[room.vertex_object[room.quads[:, 0]]]})


def write_scene(root: Path, room_name: str, room: RoomMesh, cameras: list[Camera]) -> None:
    """All files of one room under ``root/<room_name>``."""
    room_dir = Path(root) / room_name
    atomic_write_bytes(room_dir / layout.MESH_FILE, _ply_bytes(room))
    atomic_write_json(room_dir / layout.INFO_FILE, _info(room), indent=None)
    atomic_write_text(room_dir / layout.NICE_SLAM_TRAJ, "".join(" ".join(f"{x:.12e}" for x in c.c2w.reshape(-1)) + "\n" for c in cameras))
    triangles, tri_face = triangulate_quads(room.quads)
    sem_obj, ins_obj = _object_labels(room)
    face_object = room.vertex_object[room.quads[tri_face, 0]]
    renders = render_labelled_views(room.vertices, triangles, room.colors, sem_obj[face_object], ins_obj[face_object], cameras)
    for i, render in enumerate(renders):
        atomic_write_image(room_dir / layout.NICE_SLAM_DIR / layout.NICE_SLAM_FRAME.format(i), render.rgb)
        depth = np.clip(np.round(render.depth * layout.NICE_SLAM_DEPTH_SCALE), 0, MAX_DEPTH_VALUE).astype(np.uint16)
        atomic_write_image(room_dir / layout.NICE_SLAM_DIR / layout.NICE_SLAM_DEPTH.format(i), depth)
        atomic_write_image(room_dir / layout.GT_DIR / layout.GT_SEMANTIC.format(i), render.semantic.astype(np.uint16))
        atomic_write_image(room_dir / layout.GT_DIR / layout.GT_INSTANCE.format(i), render.instance.astype(np.uint16))
