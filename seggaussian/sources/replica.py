"""Replica reader: labelled mesh vertices of a room and its posed views.

``root`` holds one folder per room::

    <room>/habitat/mesh_semantic.ply      quad faces with an int face property ``object_id``
    <room>/habitat/info_semantic.json     classes [{id, name}], objects [{id, class_id, class_name}],
                                          id_to_label[object_id] = class id (negative = void)
    <room>/traj.txt + <room>/results/frame%06d.jpg, depth%06d.png          NICE-SLAM renders
    <room>/Sequence_1/traj_w_c.txt + rgb/rgb_%d.png + semantic_class/...    Semantic-NeRF renders

Per-vertex labels come from the faces: a vertex takes the object of its faces (the most frequent
one when faces disagree; ties -> smallest object id; counted in ``stats['conflicting_vertices']``).
Class -> top-100 through ``replica_class_to_top100``; unmapped classes are ignore. Instance = the
object id for every non-void object. Views: NICE-SLAM, else Semantic-NeRF, else rendered from the
mesh into ``cache_dir`` (never into the raw tree). Every ``NOVEL_VIEW_EVERY``-th view
(index % 8 == 0) is ``novel``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from seggaussian.core.cameras import Camera, intrinsics
from seggaussian.core.classes import replica_class_to_top100
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.scene import Scene, View
from seggaussian.sources._common import (
    EmptySceneError,
    SourceError,
    atomic_write_image,
    atomic_write_json,
    finite_number,
    image_size,
    json_field,
    read_image,
    read_json,
    read_mesh_ply,
    triangulate_quads,
)
from seggaussian.sources.camera_path import default_intrinsics, generate_camera_path
from seggaussian.sources.raycast import render_labelled_views

MESH_FILE = "habitat/mesh_semantic.ply"
INFO_FILE = "habitat/info_semantic.json"
NICE_SLAM_TRAJ = "traj.txt"
NICE_SLAM_DIR = "results"
NICE_SLAM_FRAME = "frame{:06d}.jpg"
NICE_SLAM_DEPTH = "depth{:06d}.png"
#: NICE-SLAM depth PNGs store metres * this.
NICE_SLAM_DEPTH_SCALE = 6553.5
#: NICE-SLAM render size and intrinsics (fx, fy, cx, cy) at that size.
NICE_SLAM_SIZE = (1200, 680)
NICE_SLAM_INTRINSICS = (600.0, 600.0, 599.5, 339.5)
SEMANTIC_NERF_DIR = "Sequence_1"
SEMANTIC_NERF_TRAJ = "traj_w_c.txt"
SEMANTIC_NERF_SIZE = (640, 480)
SEMANTIC_NERF_INTRINSICS = (320.0, 320.0, 319.5, 239.5)
#: Ground-truth label images next to NICE-SLAM renders (toolkit extension written by the synthetic
#: generator; uint16 PNG, top-100 class ids / object ids, IGNORE_LABEL for void).
GT_DIR = "seggaussian_gt"
GT_SEMANTIC = "semantic{:06d}.png"
GT_INSTANCE = "instance{:06d}.png"
#: Every ``NOVEL_VIEW_EVERY``-th view (index % 8 == 0) is held out as a novel view.
NOVEL_VIEW_EVERY = 8
#: A trajectory pose whose rotation block has |det - 1| above this is not a rigid pose.
ROTATION_DET_TOL = 1e-3
#: Self-rendered views when a room has no pre-rendered sequence.
RENDER_VIEWS = 48
RENDER_SIZE = (320, 240)


def nice_slam_intrinsics(width: int, height: int) -> np.ndarray:
    """NICE-SLAM intrinsics scaled to a ``width`` x ``height`` render (per axis: x by width/1200,
    y by height/680), so reduced-resolution sequences get matching cameras."""
    sx, sy = width / NICE_SLAM_SIZE[0], height / NICE_SLAM_SIZE[1]
    fx, fy, cx, cy = NICE_SLAM_INTRINSICS
    return intrinsics(fx * sx, fy * sy, cx * sx, cy * sy)


def list_scenes(root: Path | str) -> list[str]:
    """Room folders under ``root`` that hold ``habitat/mesh_semantic.ply``, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise SourceError(root, None, "missing (Replica root folder)")
    return sorted(p.name for p in root.iterdir() if not p.name.startswith(".") and (p / MESH_FILE).is_file())


# ---------------------------------------------------------------------------------------------
# semantics


class ReplicaInfo:
    """``info_semantic.json`` parsed and checked: object id -> top-100 class id / instance."""

    def __init__(self, path: Path):
        info = read_json(path, "Replica semantic info")
        classes = json_field(info, path, "classes", list)
        id_to_label = json_field(info, path, "id_to_label", list)
        self.class_names: dict[int, str] = {}
        for i, c in enumerate(classes):
            if not isinstance(c, dict) or not isinstance(c.get("id"), int) or not isinstance(c.get("name"), str):
                raise SourceError(path, f"classes[{i}]", "expected {id: int, name: str}")
            self.class_names[c["id"]] = c["name"]
        objects = json_field(info, path, "objects", list) if "objects" in info else []
        for i, o in enumerate(objects):
            if not isinstance(o, dict) or not isinstance(o.get("id"), int) or not isinstance(o.get("class_id"), int):
                raise SourceError(path, f"objects[{i}]", "expected {id: int, class_id: int, ...}")
        labels = []
        for i, v in enumerate(id_to_label):
            if not isinstance(v, int) or isinstance(v, bool):
                raise SourceError(path, f"id_to_label[{i}]", f"expected an integer class id, got {v!r}")
            if v >= 0 and v not in self.class_names:
                raise SourceError(path, f"id_to_label[{i}]", f"class id {v} is not in classes")
            labels.append(v)
        self.id_to_label = np.asarray(labels, dtype=np.int64)  # [num object ids]
        self.path = path
        self.top100_of_class = {cid: replica_class_to_top100(name) for cid, name in self.class_names.items()}

    def mapped_classes(self) -> tuple[list[str], list[str]]:
        """(Replica class names that map onto a top-100 class, names that do not), sorted."""
        mapped = sorted(n for c, n in self.class_names.items() if self.top100_of_class[c] is not None)
        ignored = sorted(n for c, n in self.class_names.items() if self.top100_of_class[c] is None)
        return mapped, ignored

    def class_to_top100(self) -> np.ndarray:
        """``[max class id + 1]`` top-100 id per Replica class id (IGNORE_LABEL when unmapped)."""
        table = np.full(max(self.class_names, default=0) + 1, IGNORE_LABEL, dtype=np.int64)
        for cid, top in self.top100_of_class.items():
            if top is not None:
                table[cid] = top
        return table

    def object_labels(self, object_ids: np.ndarray, mesh_path: Path) -> tuple[np.ndarray, np.ndarray]:
        """(semantic, instance) per object id; void ids give IGNORE_LABEL for both."""
        if object_ids.size and (object_ids.min() < 0 or object_ids.max() >= len(self.id_to_label)):
            raise SourceError(mesh_path, "face.object_id", f"object id out of range [0, {len(self.id_to_label)}) of {self.path} id_to_label")
        cls = self.id_to_label[object_ids]
        table = self.class_to_top100()
        semantic = np.where(cls >= 0, table[np.maximum(cls, 0)], IGNORE_LABEL)
        instance = np.where(cls >= 0, object_ids, IGNORE_LABEL)
        return semantic, instance


def compute_vertex_objects(num_vertices: int, faces: np.ndarray, face_object: np.ndarray) -> tuple[np.ndarray, int]:
    """(object id per vertex (-1 without faces), number of vertices whose faces disagree).

    The most frequent object among a vertex's faces wins; ties go to the smallest object id.
    """
    v = faces.reshape(-1).astype(np.int64)
    o = np.repeat(np.asarray(face_object, dtype=np.int64), faces.shape[1])
    if o.size and o.min() < 0:
        raise ValueError("compute_vertex_objects: negative object id")
    stride = int(o.max()) + 1 if o.size else 1
    keys, counts = np.unique(v * stride + o, return_counts=True)  # one (vertex, object) pair per key
    pv, po = keys // stride, keys % stride
    # order: vertex asc, count desc, object asc -> first row per vertex wins
    order = np.lexsort((po, -counts, pv))
    pv, po = pv[order], po[order]
    first = np.ones(len(pv), dtype=bool)
    first[1:] = pv[1:] != pv[:-1]
    out = np.full(num_vertices, -1, dtype=np.int64)
    out[pv[first]] = po[first]
    conflicts = int(np.unique(pv[~first]).size)  # vertices with a second (losing) object
    return out, conflicts


def compute_vertex_objects_reference(num_vertices: int, faces: np.ndarray, face_object: np.ndarray) -> np.ndarray:
    """Vertex-by-vertex version of ``compute_vertex_objects`` (slow; for tests)."""
    from collections import Counter

    votes = [Counter() for _ in range(num_vertices)]
    for f, obj in zip(faces, face_object):
        for v in f:
            votes[v][int(obj)] += 1
    out = np.full(num_vertices, -1, dtype=np.int64)
    for v, c in enumerate(votes):
        if c:
            best = max(c.values())
            out[v] = min(o for o, n in c.items() if n == best)
    return out


# ---------------------------------------------------------------------------------------------
# views


def read_trajectory(path: Path) -> list[np.ndarray]:
    """One 4x4 camera-to-world pose (16 numbers, row-major) per non-empty line."""
    poses = []
    for i, line in enumerate(path.read_text().splitlines()):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 16:
            raise SourceError(path, f"line {i + 1}", f"expected 16 numbers, got {len(parts)}")
        m = np.array([finite_number(x, path, f"line {i + 1}") for x in parts]).reshape(4, 4)
        if np.abs(np.linalg.det(m[:3, :3]) - 1.0) > ROTATION_DET_TOL:
            raise SourceError(path, f"line {i + 1}", "rotation part is not a rotation (det != 1)")
        poses.append(m)
    return poses


def _views_nice_slam(room_dir: Path) -> list[View]:
    poses = read_trajectory(room_dir / NICE_SLAM_TRAJ)
    views = []
    K = None
    for i, c2w in enumerate(poses):
        image = room_dir / NICE_SLAM_DIR / NICE_SLAM_FRAME.format(i)
        if not image.is_file():
            raise SourceError(image, None, f"missing (frame {i} of {room_dir / NICE_SLAM_TRAJ})")
        if K is None:
            width, height = image_size(image, "NICE-SLAM frame")
            K = nice_slam_intrinsics(width, height)
        sem = room_dir / GT_DIR / GT_SEMANTIC.format(i)
        ins = room_dir / GT_DIR / GT_INSTANCE.format(i)
        views.append(View(image.name, Camera.from_c2w(K, c2w, width, height), image,
                          "novel" if i % NOVEL_VIEW_EVERY == 0 else "train",
                          sem if sem.is_file() else None, ins if ins.is_file() else None))
    return views


def _views_semantic_nerf(room_dir: Path, info: ReplicaInfo, cache_dir: Path | None, scene_id: str) -> list[View]:
    seq = room_dir / SEMANTIC_NERF_DIR
    poses = read_trajectory(seq / SEMANTIC_NERF_TRAJ)
    table = info.class_to_top100()
    views = []
    for i, c2w in enumerate(poses):
        image = seq / "rgb" / f"rgb_{i}.png"
        if not image.is_file():
            raise SourceError(image, None, f"missing (frame {i} of {seq / SEMANTIC_NERF_TRAJ})")
        width, height = image_size(image, "Semantic-NeRF frame")
        sx, sy = width / SEMANTIC_NERF_SIZE[0], height / SEMANTIC_NERF_SIZE[1]
        fx, fy, cx, cy = SEMANTIC_NERF_INTRINSICS
        K = intrinsics(fx * sx, fy * sy, cx * sx, cy * sy)
        sem_path = None
        raw = seq / "semantic_class" / f"semantic_class_{i}.png"
        if raw.is_file() and cache_dir is not None:  # Replica class ids -> top-100 ids, cached
            sem_path = Path(cache_dir) / scene_id / "semantic_nerf" / f"semantic_{i}.png"
            if not sem_path.is_file():
                ids = read_image(raw, "Semantic-NeRF class image", unchanged=True).astype(np.int64)
                mapped = np.where(ids < len(table), table[np.minimum(ids, len(table) - 1)], IGNORE_LABEL)
                atomic_write_image(sem_path, mapped.astype(np.uint16))
        views.append(View(image.name, Camera.from_c2w(K, c2w, width, height), image,
                          "novel" if i % NOVEL_VIEW_EVERY == 0 else "train", sem_path, None))
    return views


def _views_rendered(scene_id, points, colors, faces, face_semantic, face_instance, cache_dir: Path, raw_root: Path) -> list[View]:
    """Render ``RENDER_VIEWS`` views along a generated path into ``cache_dir/<scene_id>/render``."""
    cache = Path(cache_dir).resolve() / scene_id / "render"
    if cache == raw_root.resolve() or raw_root.resolve() in cache.parents:
        raise SourceError(cache, None, "cache_dir lies inside the raw tree; readers never write there")
    key = hashlib.sha1(np.ascontiguousarray(points).tobytes() + np.ascontiguousarray(faces).tobytes()).hexdigest()[:16]
    width, height = RENDER_SIZE
    K = default_intrinsics(width, height)
    lo = np.percentile(points, 2, axis=0)
    hi = np.percentile(points, 98, axis=0)
    cameras = generate_camera_path(lo, hi, RENDER_VIEWS, K, width, height, np.random.default_rng(0))
    manifest = cache / "manifest.json"
    names = [f"render{i:06d}" for i in range(len(cameras))]
    fresh = manifest.is_file() and json.loads(manifest.read_text()).get("key") == key
    if not fresh:
        for name, render in zip(names, render_labelled_views(points, faces, colors, face_semantic, face_instance, cameras)):
            atomic_write_image(cache / f"{name}.jpg", render.rgb)
            atomic_write_image(cache / f"{name}_semantic.png", render.semantic.astype(np.uint16))
            atomic_write_image(cache / f"{name}_instance.png", render.instance.astype(np.uint16))
        atomic_write_json(manifest, {"key": key, "views": len(cameras)})
    return [View(f"{n}.jpg", c, cache / f"{n}.jpg", "novel" if i % NOVEL_VIEW_EVERY == 0 else "train",
                 cache / f"{n}_semantic.png", cache / f"{n}_instance.png") for i, (n, c) in enumerate(zip(names, cameras))]


# ---------------------------------------------------------------------------------------------
# the scene


def read_scene(root: Path | str, scene_id: str, *, cache_dir: Path | str | None = None) -> Scene:
    """One Replica room. ``cache_dir`` (outside the raw tree) receives self-rendered views when the
    room has no pre-rendered sequence (and mapped Semantic-NeRF label images); without it such a
    room is returned without views (``stats['views_source'] == 'none'``)."""
    room_dir = Path(root) / scene_id
    mesh_path = room_dir / MESH_FILE
    mesh = read_mesh_ply(mesh_path, face_properties=("object_id",))
    if mesh["faces"] is None or len(mesh["faces"]) == 0:
        raise SourceError(mesh_path, "face", "no faces: per-vertex labels come from the faces")
    info = ReplicaInfo(room_dir / INFO_FILE)
    face_object = np.asarray(mesh["object_id"], dtype=np.int64)
    points, colors, polys = mesh["points"], mesh["colors"], mesh["faces"]
    stats: dict = {"vertices": len(points), "faces": len(polys)}

    vertex_object, conflicts = compute_vertex_objects(len(points), polys, face_object)
    stats["conflicting_vertices"] = conflicts
    stats["vertices_without_faces"] = int((vertex_object < 0).sum())
    semantic, instance = info.object_labels(np.maximum(vertex_object, 0), mesh_path)
    semantic = np.where(vertex_object >= 0, semantic, IGNORE_LABEL).astype(np.int32)
    instance = np.where(vertex_object >= 0, instance, IGNORE_LABEL).astype(np.int32)
    stats["labelled_vertices"] = int((semantic != IGNORE_LABEL).sum())
    if stats["labelled_vertices"] == 0:
        raise EmptySceneError(room_dir / INFO_FILE, "id_to_label", "no vertex has a class that maps onto top-100")

    triangles, tri_face = triangulate_quads(polys)
    stats["degenerate_triangles_dropped"] = int(polys.shape[1] // 2 * len(polys) - len(triangles)) if polys.shape[1] == 4 else 0

    if (room_dir / NICE_SLAM_TRAJ).is_file():
        views, stats["views_source"] = _views_nice_slam(room_dir), "nice-slam"
    elif (room_dir / SEMANTIC_NERF_DIR / SEMANTIC_NERF_TRAJ).is_file():
        views, stats["views_source"] = _views_semantic_nerf(room_dir, info, cache_dir, scene_id), "semantic-nerf"
    elif cache_dir is not None:
        face_sem, face_ins = info.object_labels(face_object[tri_face], mesh_path)
        views = _views_rendered(scene_id, points, colors, triangles, face_sem, face_ins, Path(cache_dir), Path(root))
        stats["views_source"] = "rendered"
    else:
        views, stats["views_source"] = [], "none"
    return Scene(
        scene_id=scene_id, source="replica", points=points, colors=colors, semantic=semantic, instance=instance,
        faces=triangles, multilabel=None, views=tuple(views), root=room_dir, stats=stats,
    )
