"""Write a synthetic room in the complete ScanNet++ v2 on-disk layout (see ``scannetpp.py`` and SOURCES.md).

Every folder and file a downloaded scene has (toolkit ``common/scene_release.py``) plus the output of the
toolkit's undistortion (``dslr/configs/undistort.yml``) is written, so every reader test meets a
real-shaped tree: the distorted fisheye DSLR data beside the undistorted data, anonymization masks,
the 1 mm point cloud, the scanner poses, ``iphone/`` and ``panocam/``. Content the reader never uses
(iPhone video, panocam images, original-resolution images) is a small placeholder of the right kind.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seggaussian.core.cameras import Camera
from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.sources import scannetpp as layout
from seggaussian.sources._common import (
    atomic_write_bytes,
    encode_image,
    encode_mesh_ply,
    atomic_write_image,
    atomic_write_json,
    atomic_write_text,
    triangulate_quads,
)
from seggaussian.sources.raycast import render_labelled_views
from seggaussian.sources.synthetic.mesh import CLASS_TABLE, RAW_LABEL_MAP, RoomMesh

#: Radius (metres) of the anonymization-like masked disc the generator cuts out of one wall.
MASK_RADIUS = 0.25
#: Every ``NOVEL_VIEW_EVERY``-th view (index % 8 == 0) goes to the test list.
NOVEL_VIEW_EVERY = 8
#: Views with index % ANON_VIEW_EVERY == 1 carry an anonymized rectangle (a "face") in their mask.
ANON_VIEW_EVERY = 4
#: The anonymized rectangle: (top, bottom, left, right) as shares of the image height / width.
ANON_BOX = (0.40, 0.55, 0.45, 0.60)
#: Distorted (OPENCV_FISHEYE) camera of the download: focal length = this x the undistorted one, and
#: the fisheye coefficients k1..k4. Only written (the reader must not use them).
FISHEYE_FOCAL_RATIO = 0.9
FISHEYE_COEFFS = (0.05, 0.01, 0.0, 0.0)
#: Bytes of a placeholder file whose content no reader uses (iPhone video, depth stream).
PLACEHOLDER = b"seggaussian synthetic placeholder\n"


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


def _ply_bytes(room: RoomMesh, triangles: np.ndarray, colors: np.ndarray | None = None) -> bytes:
    colors = room.colors if colors is None else colors
    vertex = np.empty(len(room.vertices), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = room.vertices[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = colors[:, k]
    return encode_mesh_ply(vertex, triangles)


def anon_box(index: int, width: int, height: int) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right) pixel rows/columns of view ``index``'s anonymized rectangle, or None."""
    if index % ANON_VIEW_EVERY != 1:
        return None
    top, bottom, left, right = ANON_BOX
    return int(top * height), int(bottom * height), int(left * width), int(right * width)


def anon_mask(index: int, width: int, height: int) -> np.ndarray:
    """``[H, W]`` uint8 anonymization mask of view ``index`` (toolkit convention: 255 valid, 0 anonymized)."""
    mask = np.full((height, width), 255, np.uint8)
    box = anon_box(index, width, height)
    if box is not None:
        mask[box[0]:box[1], box[2]:box[3]] = 0
    return mask


def fisheye_camera(K: np.ndarray) -> np.ndarray:
    """``[3, 3]`` K of the distorted camera the undistorted pinhole ``K`` is made from (same centre)."""
    Kd = np.array(K, np.float64)
    Kd[0, 0] *= FISHEYE_FOCAL_RATIO
    Kd[1, 1] *= FISHEYE_FOCAL_RATIO
    return Kd


def distort(image: np.ndarray, K: np.ndarray, Kd: np.ndarray, nearest: bool = False) -> np.ndarray:
    """The fisheye (OPENCV_FISHEYE, ``Kd``, ``FISHEYE_COEFFS``) image whose undistortion is ``image`` (pinhole K)."""
    import cv2

    h, w = image.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    undistorted = cv2.fisheye.undistortPoints(pixels, Kd, np.asarray(FISHEYE_COEFFS, np.float64), P=K)
    maps = undistorted.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


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
    Kd = fisheye_camera(K)
    atomic_write_text(scene_dir / layout.COLMAP_CAMERAS_FILE, "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                      f"1 OPENCV_FISHEYE {width} {height} {Kd[0, 0]:.12f} {Kd[1, 1]:.12f} {Kd[0, 2]:.12f} {Kd[1, 2]:.12f} "
                      + " ".join(f"{k:.12f}" for k in FISHEYE_COEFFS) + "\n")
    atomic_write_text(scene_dir / "dslr/colmap/points3D.txt", "# 3D point list with one line of data per point:\n"
                      "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
    test = [i % NOVEL_VIEW_EVERY == 0 for i in range(len(cameras))]
    frame = lambda i: {"file_path": names[i], "mask_path": mask_name(names[i]), "transform_matrix": layout.toolkit_transform_matrix(cameras[i].viewmat).round(12).tolist(), "is_bad": False}  # noqa: E731
    frames = {"frames": [frame(i) for i in range(len(cameras)) if not test[i]],
              "test_frames": [frame(i) for i in range(len(cameras)) if test[i]]}
    # the download's distorted transforms (toolkit input) and the undistortion's output
    atomic_write_json(scene_dir / layout.DISTORTED_TRANSFORMS_FILE, {
        "camera_model": "OPENCV_FISHEYE", "fl_x": float(Kd[0, 0]), "fl_y": float(Kd[1, 1]), "cx": float(Kd[0, 2]),
        "cy": float(Kd[1, 2]), "w": int(width), "h": int(height),
        **{f"k{i + 1}": float(k) for i, k in enumerate(FISHEYE_COEFFS)}, "has_mask": True, **frames,
    })
    atomic_write_json(scene_dir / layout.TRANSFORMS_FILE, {
        "camera_model": "PINHOLE", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "w": int(width), "h": int(height), "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "has_mask": True, **frames,
    })
    atomic_write_json(scene_dir / layout.TRAIN_TEST_FILE, {"train": [n for n, t in zip(names, test) if not t], "test": [n for n, t in zip(names, test) if t]})

    # images and ground-truth label images rendered from the mesh; a face is void when its object
    # has no top-100 class or all three of its vertices are masked
    face_object = room.vertex_object[triangles[:, 0]]
    face_masked = np.isin(triangles, choose_mask(room)).all(axis=1)
    face_semantic = np.where(face_masked, IGNORE_LABEL, _object_classes(room)[face_object])
    face_instance = np.where(face_semantic == IGNORE_LABEL, IGNORE_LABEL, face_object + 1)
    renders = render_labelled_views(room.vertices, triangles, room.colors, face_semantic, face_instance, cameras)
    for index, (name, render) in enumerate(zip(names, renders)):
        stem = Path(name).stem
        mask = anon_mask(index, width, height)
        distorted = encode_image(distort(render.rgb, K, Kd), ".JPG")
        distorted_mask = encode_image(distort(mask, K, Kd, nearest=True), ".png")
        undistorted_mask = encode_image(mask, ".png")
        atomic_write_image(scene_dir / layout.IMAGE_DIRS[0] / name, render.rgb)
        atomic_write_image(scene_dir / layout.IMAGE_DIRS[1] / name, render.rgb)
        for folder, data in (("resized_images", distorted), ("original_images", distorted),
                             ("resized_anon_masks", distorted_mask), ("original_anon_masks", distorted_mask)):
            atomic_write_bytes(scene_dir / "dslr" / folder / (name if folder.endswith("images") else mask_name(name)), data)
        for folder in layout.MASK_DIRS:
            atomic_write_bytes(scene_dir / folder / mask_name(name), undistorted_mask)
        atomic_write_image(scene_dir / layout.SEMANTIC_RENDER_DIR / f"{stem}.png", render.semantic.astype(np.uint16))
        atomic_write_image(scene_dir / layout.INSTANCE_RENDER_DIR / f"{stem}.png", render.instance.astype(np.uint16))
    _write_unused_assets(scene_dir, room, triangles, cameras)


def mask_name(image_name: str) -> str:
    """The anonymization mask of a DSLR image (transforms ``mask_path``): ``DSC00001.JPG`` -> ``DSC00001.png``."""
    return f"{Path(image_name).stem}.png"


def _write_unused_assets(scene_dir: Path, room: RoomMesh, triangles: np.ndarray, cameras: list[Camera]) -> None:
    """The files of a downloaded scene the reader never opens, with small placeholder content."""
    # scans/: the semantic mesh (vertex colours by object), the point cloud + its mask, the scanner pose
    palette = np.random.default_rng(0).integers(0, 256, (len(room.objects), 3)).astype(np.uint8)
    atomic_write_bytes(scene_dir / "scans/mesh_aligned_0.05_semantic.ply", _ply_bytes(room, triangles, palette[room.vertex_object]))
    atomic_write_bytes(scene_dir / "scans/pc_aligned.ply", _ply_bytes(room, np.zeros((0, 3), np.int64)))
    atomic_write_text(scene_dir / "scans/pc_aligned_mask.txt", "".join(f"{v}\n" for v in choose_mask(room)))
    centre = room.vertices.mean(axis=0)
    pose = np.eye(4)
    pose[:3, 3] = centre
    atomic_write_json(scene_dir / "scans/scanner_poses.json", [pose.round(9).tolist()])
    # iphone/: video, mask video, depth stream, poses, COLMAP and nerfstudio files (placeholders)
    iphone = scene_dir / "iphone"
    for name in ("rgb.mkv", "rgb_mask.mkv", "depth.bin"):
        atomic_write_bytes(iphone / name, PLACEHOLDER)
    atomic_write_json(iphone / "pose_intrinsic_imu.json", {})
    atomic_write_json(iphone / "exif.json", {})
    atomic_write_json(iphone / "nerfstudio/transforms.json", {"frames": []})
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        atomic_write_text(iphone / "colmap" / name, "# placeholder\n")
    # panocam/: one scan position, every folder of the release (tiny images)
    pano = scene_dir / "panocam"
    rgb = np.zeros((4, 8, 3), np.uint8)
    single = np.zeros((4, 8), np.uint16)
    for folder, ext, image in (("images", ".jpg", rgb), ("resized_images", ".jpg", rgb), ("anon_mask", ".png", single.astype(np.uint8)),
                               ("resized_anon_mask", ".png", single.astype(np.uint8)), ("depth", ".png", single),
                               ("resized_depth", ".png", single), ("azim", ".png", single), ("resized_azim", ".png", single),
                               ("elev", ".png", single), ("resized_elev", ".png", single)):
        atomic_write_image(pano / folder / f"scan0{ext}", image)


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
    # the release's full class lists (toolkit semantic/configs eval_*.yml); not read
    raw_classes = sorted(RAW_LABEL_MAP)
    atomic_write_text(data_root / "metadata/semantic_classes.txt", "\n".join(raw_classes) + "\n")
    atomic_write_text(data_root / "metadata/instance_classes.txt", "\n".join(c for c in raw_classes if RAW_LABEL_MAP[c] != "None") + "\n")
    val = [s for i, s in enumerate(scene_ids) if len(scene_ids) > 1 and i % val_every == val_every - 1 or (len(scene_ids) > 1 and len(scene_ids) < val_every and i == len(scene_ids) - 1)]
    train = [s for s in scene_ids if s not in val]
    atomic_write_text(data_root / layout.SPLITS_DIR / "nvs_sem_train.txt", "".join(f"{s}\n" for s in train))
    atomic_write_text(data_root / layout.SPLITS_DIR / "nvs_sem_val.txt", "".join(f"{s}\n" for s in val))
