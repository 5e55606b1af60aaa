"""Write a synthetic room in the Replica layout (habitat mesh + info + a NICE-SLAM style sequence).

The sequence is rendered at a reduced resolution (default 320 x 181, the NICE-SLAM 1200 x 680
aspect); the reader scales the NICE-SLAM intrinsics to the image size (``nice_slam_intrinsics``),
and the generator renders with exactly those intrinsics. Ground-truth label images go to
``<room>/seggaussian_gt/`` (a toolkit extension; see SOURCES.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.sources import replica as layout
from seggaussian.sources._common import atomic_write_bytes, encode_mesh_ply, atomic_write_image, atomic_write_json, atomic_write_text, triangulate_quads
from seggaussian.sources.raycast import render_labelled_views
from seggaussian.core.classes import replica_class_names, replica_class_to_top100
from seggaussian.sources.synthetic.mesh import CLASS_TABLE, RoomMesh

#: Depth PNG values saturate here (uint16 max / NICE_SLAM_DEPTH_SCALE ~ 10 m).
MAX_DEPTH_VALUE = 65535
#: Bytes of a placeholder file whose content no reader uses (textures, navmeshes, segmentations).
PLACEHOLDER = b"seggaussian synthetic placeholder\n"
#: NICE-SLAM's root ``cam_params.json`` (its Replica download: 1200x680 renders, depth scale 6553.5).
NICE_SLAM_CAM_PARAMS = "cam_params.json"


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


def _ply_bytes(room: RoomMesh, with_object_id: bool = True) -> bytes:
    vertex = np.empty(len(room.vertices), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                                                 ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = room.vertices[:, k]
        vertex["n" + axis] = room.normals[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = room.colors[:, k]
    faces = {"object_id": object_ids(room)[room.vertex_object[room.quads[:, 0]]]} if with_object_id else None
    return encode_mesh_ply(vertex, room.quads, faces)


def write_scene(root: Path, room_name: str, room: RoomMesh, cameras: list[Camera]) -> None:
    """All files of one room under ``root/<room_name>``."""
    room_dir = Path(root) / room_name
    semantic_mesh = _ply_bytes(room)
    atomic_write_bytes(room_dir / layout.MESH_FILE, semantic_mesh)
    atomic_write_json(room_dir / layout.INFO_FILE, _info(room), indent=None)
    _write_unused_assets(room_dir, room, semantic_mesh)
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


def _write_unused_assets(room_dir: Path, room: RoomMesh, semantic_mesh: bytes) -> None:
    """The rest of an official Replica scene folder (Replica-Dataset README "Dataset Layout"), never read:
    the plain quad mesh, glass surfaces, pre-segmentation and segmentation, textures, habitat extras."""
    atomic_write_bytes(room_dir / "mesh.ply", _ply_bytes(room, with_object_id=False))
    for name in ("glass.sur", "preseg.bin", "semantic.bin", "textures/0-color-ptex.hdr", "textures/0-color-ptex.w",
                 "habitat/mesh_semantic.navmesh", "habitat/mesh_preseg_semantic.navmesh"):
        atomic_write_bytes(room_dir / name, PLACEHOLDER)
    for name in ("preseg.json", "semantic.json", "textures/parameters.json", "habitat/info_preseg_semantic.json",
                 "habitat/replica_stage.stage_config.json"):
        atomic_write_json(room_dir / name, {})
    atomic_write_bytes(room_dir / "habitat/mesh_preseg_semantic.ply", semantic_mesh)


def write_root_files(root: Path, room_names: list[str]) -> None:
    """NICE-SLAM's files beside the room folders: ``cam_params.json`` and ``<room>_mesh.ply`` (its culled
    mesh; here a copy of the room's plain mesh). Never read; the reader lists room folders only."""
    root = Path(root)
    w, h = layout.NICE_SLAM_SIZE
    fx, fy, cx, cy = layout.NICE_SLAM_INTRINSICS
    atomic_write_json(root / NICE_SLAM_CAM_PARAMS, {"camera": {"w": w, "h": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
                                                                "scale": layout.NICE_SLAM_DEPTH_SCALE}})
    for name in room_names:
        atomic_write_bytes(root / f"{name}_mesh.ply", (root / name / "mesh.ply").read_bytes())
