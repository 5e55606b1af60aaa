"""ScanNet++ reader: labelled mesh vertices and undistorted DSLR views of one scene.

``root`` is the ScanNet++ DATA_ROOT, as the toolkit's ``common/scene_release.py`` names it. Read::

    data/<scene_id>/scans/mesh_aligned_0.05.ply           vertices (x, y, z, red, green, blue) + faces
    data/<scene_id>/scans/segments.json                   {"segIndices": [segment id per vertex]}
    data/<scene_id>/scans/segments_anno.json              {"segGroups": [{objectId, label, segments}]}
    data/<scene_id>/scans/mesh_aligned_0.05_mask.txt      vertex ids to ignore (anonymized areas)
    data/<scene_id>/dslr/colmap/images.txt                COLMAP world-to-camera poses (mesh frame)
    data/<scene_id>/dslr/nerfstudio/transforms_undistorted.json   pinhole intrinsics + frame list
    data/<scene_id>/dslr/undistorted_images/<name>        (else resized_undistorted_images/)
    data/<scene_id>/dslr/undistorted_anon_masks/<mask>    (else resized_undistorted_masks/), optional
    data/<scene_id>/dslr/train_test_lists.json            {"train": [...], "test": [...]}
    metadata/semantic_benchmark/{map_benchmark.csv, top100.txt}
    splits/nvs_sem_{train,val}.txt

Present in every downloaded scene and ignored: the distorted fisheye DSLR data (``resized_images/``,
``resized_anon_masks/``, ``original_images/``, ``original_anon_masks/``, ``nerfstudio/transforms.json``),
``scans/pc_aligned*``, ``scans/mesh_aligned_0.05_semantic.ply``, ``scans/scanner_poses.json``,
``iphone/`` and ``panocam/``. Only when no undistorted data exists (no ``transforms_undistorted.json``)
does the reader stop, with the toolkit's undistortion command.

Labels: raw ``segGroups[].label`` -> ``map_benchmark.csv`` (``semantic_map_to`` empty keeps, ``None``
drops, anything else renames) -> ``top100.txt`` (else ignore). A vertex in several groups takes
the label and ``objectId`` of the smallest group (fewest vertices) among the groups with a top-100
label; ``multilabel`` keeps up to three distinct labels in that order. Masked vertices are ignore.

Poses come from COLMAP, not from ``transform_matrix`` (see ``undo_toolkit_transform``). Field by
field description: ``data_specs/SOURCES.md``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from seggaussian.core.cameras import Camera, intrinsics, invert_rigid
from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.core.rotations import quats_to_rotmats, rotmats_to_quats
from seggaussian.core.scene import Scene, View
from seggaussian.sources._common import (
    EmptySceneError,
    SourceError,
    finite_number,
    image_size,
    json_field,
    read_json,
    read_mesh_ply,
    require_file,
    triangulate_quads,
)

MESH_FILE = "scans/mesh_aligned_0.05.ply"
SEGMENTS_FILE = "scans/segments.json"
ANNOTATION_FILE = "scans/segments_anno.json"
MASK_FILE = "scans/mesh_aligned_0.05_mask.txt"
COLMAP_IMAGES_FILE = "dslr/colmap/images.txt"
COLMAP_CAMERAS_FILE = "dslr/colmap/cameras.txt"
TRANSFORMS_FILE = "dslr/nerfstudio/transforms_undistorted.json"
DISTORTED_TRANSFORMS_FILE = "dslr/nerfstudio/transforms.json"
TRAIN_TEST_FILE = "dslr/train_test_lists.json"
#: Undistorted DSLR image folders, in order of preference, each with its anonymization-mask folder
#: (toolkit ``dslr/configs/undistort.yml`` out_image_dir / out_mask_dir and the release's resized copies).
IMAGE_DIRS = ("dslr/undistorted_images", "dslr/resized_undistorted_images")
MASK_DIRS = ("dslr/undistorted_anon_masks", "dslr/resized_undistorted_masks")
#: Distorted (OPENCV_FISHEYE) DSLR data of the download: never read, only named in the undistortion hint.
DISTORTED_IMAGE_DIRS = ("dslr/resized_images", "dslr/original_images")
#: The toolkit command that writes the undistorted data (run from the toolkit checkout).
UNDISTORT_COMMAND = "python -m dslr.undistort dslr/configs/undistort.yml"
#: Ground-truth label images (uint16 PNG, ``<image stem>.png``): written by the synthetic
#: generator (a toolkit extension; real ScanNet++ has none), read when present.
SEMANTIC_RENDER_DIR = "dslr/render_semantic"
INSTANCE_RENDER_DIR = "dslr/render_instance"
LABEL_MAP_FILE = "metadata/semantic_benchmark/map_benchmark.csv"
TOP100_FILE = "metadata/semantic_benchmark/top100.txt"
SPLITS_DIR = "splits"
#: Up to this many labels per vertex are kept in ``Scene.multilabel``.
MAX_LABELS_PER_VERTEX = 3
#: COLMAP pose and the undone ``transform_matrix`` pose count as disagreeing beyond this
#: (max abs difference of the 4x4 world-to-camera matrices; text files hold ~1e-6 precision).
POSE_AGREEMENT_TOL = 1e-4
#: Resized image folders must scale width and height alike, up to this relative difference
#: (rounding of odd sizes).
RESIZE_ASPECT_TOL = 0.01


# ---------------------------------------------------------------------------------------------
# conventions


def toolkit_transform_matrix(viewmat: np.ndarray) -> np.ndarray:
    """The nerfstudio ``transform_matrix`` the ScanNet++ toolkit writes for a COLMAP pose.

    Toolkit ``convert_frames``: c2w = inverse(w2c); flip camera columns 1-2 (OpenCV -> OpenGL
    axes); swap world rows x <-> y; negate world row 2. The result is a camera-to-world pose in a
    permuted, mirrored world frame, not in the mesh frame.
    """
    c2w = invert_rigid(np.asarray(viewmat, dtype=np.float64))
    c2w[0:3, 1:3] *= -1.0
    c2w = c2w[[1, 0, 2, 3], :]
    c2w[2, :] *= -1.0
    return c2w


def undo_toolkit_transform(transform_matrix: np.ndarray) -> np.ndarray:
    """World-to-camera ``viewmat`` (OpenCV, mesh frame) from a toolkit ``transform_matrix``."""
    c2w = np.array(transform_matrix, dtype=np.float64)
    c2w[2, :] *= -1.0
    c2w = c2w[[1, 0, 2, 3], :]
    c2w[0:3, 1:3] *= -1.0
    return invert_rigid(c2w)


def quaternion_to_rotation(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """``[3, 3]`` rotation of a Hamilton quaternion in COLMAP order w, x, y, z (not necessarily unit on disk:
    normalized here); the formula is ``seggaussian.core.rotations``'."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    return quats_to_rotmats((q / np.linalg.norm(q))[None])[0]


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """``[4]`` unit (w, x, y, z) with w >= 0 (COLMAP's sign) of a ``[3, 3]`` rotation (``seggaussian.core.rotations``)."""
    q = rotmats_to_quats(np.asarray(rotation, dtype=np.float64)[None])[0]
    return q if q[0] >= 0 else -q


# ---------------------------------------------------------------------------------------------
# listing


def list_scenes(root: Path | str, split_file: Path | str | None = None) -> list[str]:
    """Scene ids under ``root/data`` that hold a mesh, sorted; or the ids of a split file.

    ``split_file``: a path, or a split name such as ``nvs_sem_train`` looked up in ``root/splits``.
    Every id of a split file must have a scene folder.
    """
    root = Path(root)
    data = root / "data"
    if not data.is_dir():
        raise SourceError(data, None, "missing (ScanNet++ DATA_ROOT must contain data/<scene_id>/)")
    if split_file is None:
        return sorted(p.name for p in data.iterdir() if not p.name.startswith(".") and (p / MESH_FILE).is_file())
    path = Path(split_file)
    if not path.is_file() and not path.is_absolute():
        path = root / SPLITS_DIR / (path.name if path.suffix == ".txt" else f"{path.name}.txt")
    require_file(path, "split file")
    ids = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    for i, scene_id in enumerate(ids):
        if not (data / scene_id / MESH_FILE).is_file():
            raise SourceError(path, f"line {i + 1}", f"scene {scene_id!r} has no {data / scene_id / MESH_FILE}")
    return ids


# ---------------------------------------------------------------------------------------------
# labels


def read_label_map(path: Path) -> dict[str, str | None]:
    """``map_benchmark.csv``: raw class -> benchmark name (kept or renamed) or None (dropped)."""
    require_file(path, "label map")
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        fields = reader.fieldnames or []
        for column in ("class", "semantic_map_to"):
            if column not in fields:
                raise SourceError(path, column, "column missing")
        mapping: dict[str, str | None] = {}
        for row in reader:
            raw = (row["class"] or "").strip()
            target = (row["semantic_map_to"] or "").strip()
            if raw:
                mapping[raw] = None if target == "None" else (target or raw)
    return mapping


def read_top100(root: Path) -> dict[str, int]:
    """Benchmark class name -> class id (index into the toolkit's ``top100.txt``)."""
    ours = read_class_names()
    path = root / TOP100_FILE
    listed = ours if not path.is_file() else tuple(n.strip() for n in path.read_text().splitlines() if n.strip())
    unknown = [n for n in listed if n not in ours]
    if unknown:
        raise SourceError(path, None, f"classes not in the toolkit's top100.txt: {unknown[:5]}")
    return {name: ours.index(name) for name in listed}


def _read_mask(path: Path, num_vertices: int, stats: dict) -> np.ndarray:
    """Vertex ids to ignore: one id per line. A file of exactly one 0/1 flag per vertex (more than
    two vertices) is read as a boolean mask instead (``stats['mask_format']``)."""
    try:
        ids = np.loadtxt(path, dtype=np.int64, ndmin=1)
    except ValueError as err:
        raise SourceError(path, None, f"expected one vertex id per line: {err}") from None
    stats["mask_format"] = "vertex ids"
    if num_vertices > 2 and ids.size == num_vertices and np.isin(ids, (0, 1)).all():
        stats["mask_format"] = "per-vertex flags"
        return np.flatnonzero(ids)
    if ids.size and (ids.min() < 0 or ids.max() >= num_vertices):
        raise SourceError(path, None, f"vertex id out of range [0, {num_vertices})")
    return ids


def compute_vertex_labels(
    seg_indices: np.ndarray,  # [P] segment id per vertex
    groups: list[tuple[int, int, np.ndarray]],  # (class id or -1, objectId, segment ids)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(semantic [P], instance [P], multilabel [P, 3]) by the smallest-instance rule.

    Groups without a class (-1) are left out. Ties in size keep the group listed first.
    """
    p = len(seg_indices)
    members = _group_members(np.asarray(seg_indices, dtype=np.int64), [segs for _, _, segs in groups])
    order = sorted((i for i in range(len(groups)) if groups[i][0] >= 0), key=lambda i: (len(members[i]), i))
    semantic = np.full(p, IGNORE_LABEL, dtype=np.int32)
    instance = np.full(p, IGNORE_LABEL, dtype=np.int32)
    multilabel = np.full((p, MAX_LABELS_PER_VERTEX), IGNORE_LABEL, dtype=np.int32)
    for i in order:  # smallest first: a slot once filled is never overwritten
        verts, label = members[i], groups[i][0]
        fresh = verts[semantic[verts] == IGNORE_LABEL]
        semantic[fresh] = label
        instance[fresh] = groups[i][1]
        rows = multilabel[verts]
        already = (rows == label).any(axis=1)
        free = rows == IGNORE_LABEL
        slot = np.argmax(free, axis=1)
        ok = ~already & free.any(axis=1)
        multilabel[verts[ok], slot[ok]] = label
    return semantic, instance, multilabel


def _group_members(seg_indices: np.ndarray, group_segments: list[np.ndarray]) -> list[np.ndarray]:
    """Vertex ids of each group (its segments' vertices), from one sort of ``seg_indices``."""
    by_segment = np.argsort(seg_indices, kind="stable")
    ids, starts, counts = np.unique(seg_indices[by_segment], return_index=True, return_counts=True)
    out = []
    for segs in group_segments:
        segs = np.unique(np.asarray(segs, dtype=np.int64))
        pos = np.minimum(np.searchsorted(ids, segs), max(len(ids) - 1, 0))
        found = pos[(len(ids) > 0) & (ids[pos] == segs)] if len(ids) else pos[:0]
        chunks = [by_segment[starts[k]:starts[k] + counts[k]] for k in found]
        out.append(np.sort(np.concatenate(chunks)) if chunks else np.zeros(0, dtype=np.int64))
    return out


def compute_vertex_labels_reference(seg_indices, groups) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex-by-vertex version of ``compute_vertex_labels`` (slow; for tests)."""
    p = len(seg_indices)
    sizes = [int(np.isin(seg_indices, segs).sum()) for _, _, segs in groups]
    semantic = np.full(p, IGNORE_LABEL, dtype=np.int32)
    instance = np.full(p, IGNORE_LABEL, dtype=np.int32)
    multilabel = np.full((p, MAX_LABELS_PER_VERTEX), IGNORE_LABEL, dtype=np.int32)
    for v in range(p):
        mine = [i for i, (label, _, segs) in enumerate(groups) if label >= 0 and seg_indices[v] in set(np.asarray(segs).tolist())]
        mine.sort(key=lambda i: (sizes[i], i))
        labels: list[int] = []
        for i in mine:
            if groups[i][0] not in labels:
                labels.append(groups[i][0])
        if mine:
            semantic[v], instance[v] = groups[mine[0]][0], groups[mine[0]][1]
        for k, label in enumerate(labels[:MAX_LABELS_PER_VERTEX]):
            multilabel[v, k] = label
    return semantic, instance, multilabel


def _read_groups(path: Path, label_map: dict, top100: dict, on_unknown_label: str, stats: dict):
    anno = read_json(path, "segment annotations")
    seg_groups = json_field(anno, path, "segGroups", list)
    groups = []
    stats.setdefault("unknown_labels", 0)
    for i, group in enumerate(seg_groups):
        where = f"segGroups[{i}]"
        if not isinstance(group, dict):
            raise SourceError(path, where, "expected an object")
        label = group.get("label")
        if not isinstance(label, str):
            raise SourceError(path, f"{where}.label", "missing or not a string")
        if "objectId" not in group or not isinstance(group["objectId"], int) or isinstance(group["objectId"], bool):
            raise SourceError(path, f"{where}.objectId", "missing or not an integer")
        segments = group.get("segments")
        if not isinstance(segments, list) or not all(isinstance(s, int) for s in segments):
            raise SourceError(path, f"{where}.segments", "missing or not a list of integers")
        if label not in label_map:
            if on_unknown_label == "error":
                raise SourceError(path, f"{where}.label", f"label {label!r} is not in map_benchmark.csv (class column)")
            stats["unknown_labels"] += 1
            mapped = None
        else:
            mapped = label_map[label]
        class_id = top100.get(mapped, -1) if mapped is not None else -1
        groups.append((class_id, int(group["objectId"]), np.asarray(segments, dtype=np.int64)))
    return groups


# ---------------------------------------------------------------------------------------------
# cameras


def read_colmap_images(path: Path) -> dict[str, np.ndarray]:
    """COLMAP ``images.txt`` -> {image name: world-to-camera ``[4, 4]``}."""
    require_file(path, "COLMAP images")
    lines = path.read_text().splitlines()
    poses: dict[str, np.ndarray] = {}
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if not line or line.startswith("#"):
            i += 1
            continue
        parts = line.split()
        field = f"line {i + 1}"
        if len(parts) < 10:
            raise SourceError(path, field, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        name = " ".join(parts[9:])
        numbers = [finite_number(x, path, f"{field} ({name}) {key}") for x, key in zip(parts[1:8], ("QW", "QX", "QY", "QZ", "TX", "TY", "TZ"))]
        if np.linalg.norm(numbers[:4]) == 0.0:
            raise SourceError(path, f"{field} ({name}) QW..QZ", "zero quaternion")
        viewmat = np.eye(4)
        viewmat[:3, :3] = quaternion_to_rotation(*numbers[:4])
        viewmat[:3, 3] = numbers[4:7]
        poses[name] = viewmat
        i += 2  # the next line lists the image's 2D points (possibly empty)
    return poses


def _check_undistorted(scene_dir: Path) -> None:
    """Stop with the toolkit's undistortion command when the scene has no undistorted DSLR data.

    ``transforms_undistorted.json`` decides: when it exists, the distorted data beside it (every
    download has ``nerfstudio/transforms.json`` and ``resized_images/``) is simply not used.
    """
    if (scene_dir / TRANSFORMS_FILE).is_file():
        return
    distorted = [p for p in (DISTORTED_TRANSFORMS_FILE, *DISTORTED_IMAGE_DIRS) if (scene_dir / p).exists()]
    if distorted:
        cameras = scene_dir / COLMAP_CAMERAS_FILE
        model = ""
        if cameras.is_file():
            for line in cameras.read_text().splitlines():
                if line.strip() and not line.startswith("#"):
                    model = line.split()[1] if len(line.split()) > 1 else ""
                    break
        raise SourceError(
            scene_dir / TRANSFORMS_FILE, None,
            f"missing: this scene only has distorted {model or 'fisheye'} DSLR data ({', '.join(distorted)}). "
            f"Undistort it first with the ScanNet++ toolkit ({UNDISTORT_COMMAND}), which writes "
            "dslr/undistorted_images/, dslr/undistorted_anon_masks/ and dslr/nerfstudio/transforms_undistorted.json",
        )
    require_file(scene_dir / TRANSFORMS_FILE, "pinhole intrinsics and frame list")


def _read_views(scene_dir: Path, stats: dict) -> list[View]:
    _check_undistorted(scene_dir)
    tpath = scene_dir / TRANSFORMS_FILE
    transforms = read_json(tpath, "pinhole intrinsics and frame list")
    fx, fy, cx, cy = (finite_number(json_field(transforms, tpath, k, (int, float)), tpath, k) for k in ("fl_x", "fl_y", "cx", "cy"))
    width, height = (int(json_field(transforms, tpath, k, (int, float))) for k in ("w", "h"))
    if width <= 0 or height <= 0:
        raise SourceError(tpath, "w/h", f"image size must be positive, got {width}x{height}")
    frames = [("frames", f) for f in json_field(transforms, tpath, "frames", list)]
    if transforms.get("test_frames") is not None:
        frames += [("test_frames", f) for f in json_field(transforms, tpath, "test_frames", list)]

    colmap_path = scene_dir / COLMAP_IMAGES_FILE
    colmap = read_colmap_images(colmap_path) if colmap_path.is_file() else None
    stats["pose_source"] = "colmap" if colmap is not None else "transform_matrix (undone)"

    split_path = scene_dir / TRAIN_TEST_FILE
    if split_path.is_file():
        split = read_json(split_path, "train/test image lists")
        novel = set(json_field(split, split_path, "test", list))
    else:
        novel = {Path(f.get("file_path", "")).name for key, f in frames if key == "test_frames" and isinstance(f, dict)}

    which = next((k for k, d in enumerate(IMAGE_DIRS) if (scene_dir / d).is_dir()), None)
    if which is None:
        raise SourceError(scene_dir / IMAGE_DIRS[0], None, "missing (undistorted DSLR images)")
    image_dir, mask_dir = scene_dir / IMAGE_DIRS[which], scene_dir / MASK_DIRS[which]
    stats["image_dir"] = IMAGE_DIRS[which]
    stats["anon_masks"] = 0
    K = intrinsics(fx, fy, cx, cy)

    views: list[View] = []
    stats["bad_frames"] = 0
    stats["pose_disagreements"] = 0
    for index, (key, frame) in enumerate(frames):
        where = f"{key}[{index if key == 'frames' else index - len(transforms['frames'])}]"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise SourceError(tpath, f"{where}.file_path", "missing or not a string")
        if frame.get("is_bad", False) is True:
            stats["bad_frames"] += 1
            continue
        name = Path(frame["file_path"]).name
        matrix = frame.get("transform_matrix")
        try:
            matrix = np.asarray(matrix, dtype=np.float64)
        except (TypeError, ValueError):
            raise SourceError(tpath, f"{where}.transform_matrix", "not a 4x4 array of numbers") from None
        if matrix.shape != (4, 4):
            raise SourceError(tpath, f"{where}.transform_matrix", f"expected 4x4, got shape {matrix.shape}")
        if not np.isfinite(matrix).all():
            raise SourceError(tpath, f"{where}.transform_matrix", "holds NaN/Inf")
        # transform_matrix lives in the toolkit's permuted world frame (rows x<->y swapped, row 2
        # negated) with OpenGL camera axes; the mesh-frame pose is COLMAP's. Use COLMAP and only
        # cross-check (or, without images.txt, undo the permutation).
        undone = undo_toolkit_transform(matrix)
        if colmap is not None:
            if name not in colmap:
                raise SourceError(colmap_path, name, "image listed in transforms_undistorted.json has no COLMAP pose")
            viewmat = colmap[name]
            stats["pose_disagreements"] += int(np.abs(viewmat - undone).max() > POSE_AGREEMENT_TOL)
        else:
            viewmat = undone
        image_path = image_dir / name
        require_file(image_path, f"DSLR image of {tpath.name} {where}")
        mask_path = _mask_path(mask_dir, frame, name, tpath, where)
        stats["anon_masks"] += mask_path is not None
        views.append(View(
            name=name,
            camera=Camera(K, viewmat, width, height),
            image_path=image_path,
            role="novel" if name in novel else "train",
            semantic_path=_optional(scene_dir / SEMANTIC_RENDER_DIR / f"{Path(name).stem}.png"),
            instance_path=_optional(scene_dir / INSTANCE_RENDER_DIR / f"{Path(name).stem}.png"),
            mask_path=mask_path,
        ))
    if views:  # resized image folders: scale the intrinsics to the images' actual size
        actual_w, actual_h = image_size(views[0].image_path, "DSLR image")
        if (actual_w, actual_h) != (width, height):
            scale = actual_w / width
            if abs(actual_h / height - scale) > RESIZE_ASPECT_TOL:
                raise SourceError(views[0].image_path, None, f"size {actual_w}x{actual_h} does not match w/h {width}x{height} of {tpath} at one scale")
            views = [View(v.name, v.camera.scaled(scale), v.image_path, v.role, v.semantic_path, v.instance_path,
                          v.mask_path) for v in views]
    return views


def _mask_path(mask_dir: Path, frame: dict, name: str, tpath: Path, where: str) -> Path | None:
    """The frame's anonymization mask: ``mask_dir / frame["mask_path"]`` (the toolkit's field), else
    ``<image stem>.png``; None when the scene has no mask folder. A listed mask that is missing is an error."""
    if not mask_dir.is_dir():
        return None
    listed = frame.get("mask_path")
    if listed is not None and not isinstance(listed, str):
        raise SourceError(tpath, f"{where}.mask_path", "not a string")
    path = mask_dir / (listed if listed else f"{Path(name).stem}.png")
    require_file(path, f"anonymization mask of {tpath.name} {where}")
    return path


def _optional(path: Path) -> Path | None:
    return path if path.is_file() else None


# ---------------------------------------------------------------------------------------------
# the scene


def read_scene(root: Path | str, scene_id: str, *, on_unknown_label: str = "error") -> Scene:
    """One ScanNet++ scene. Raises ``SourceError`` on bad input, ``EmptySceneError`` when no vertex
    keeps a label. ``on_unknown_label``: ``error`` (a raw label missing from map_benchmark.csv is
    an error) or ``ignore`` (such groups are dropped and counted in ``stats['unknown_labels']``).
    """
    if on_unknown_label not in ("error", "ignore"):
        raise ValueError(f"on_unknown_label must be 'error' or 'ignore', got {on_unknown_label!r}")
    root = Path(root)
    scene_dir = root / "data" / scene_id
    stats: dict = {}
    label_map = read_label_map(root / LABEL_MAP_FILE)
    top100 = read_top100(root)

    mesh = read_mesh_ply(scene_dir / MESH_FILE)
    points, colors = mesh["points"], mesh["colors"]
    spath = scene_dir / SEGMENTS_FILE
    seg = json_field(read_json(spath, "over-segmentation"), spath, "segIndices", list)
    if len(seg) != len(points):
        raise SourceError(spath, "segIndices", f"has {len(seg)} entries but {scene_dir / MESH_FILE} has {len(points)} vertices")
    try:
        seg_indices = np.asarray(seg, dtype=np.int64)
    except (TypeError, ValueError, OverflowError):
        raise SourceError(spath, "segIndices", "expected a list of integers") from None

    groups = _read_groups(scene_dir / ANNOTATION_FILE, label_map, top100, on_unknown_label, stats)
    semantic, instance, multilabel = compute_vertex_labels(seg_indices, groups)

    mask_path = scene_dir / MASK_FILE
    if mask_path.is_file():
        masked = _read_mask(mask_path, len(points), stats)
        semantic[masked], instance[masked], multilabel[masked] = IGNORE_LABEL, IGNORE_LABEL, IGNORE_LABEL
        stats["masked_vertices"] = int(np.unique(masked).size)
    else:
        stats["masked_vertices"] = 0
        stats["mask_file"] = "absent"
    labelled = int((semantic != IGNORE_LABEL).sum())
    stats["labelled_vertices"] = labelled
    stats["vertices"] = len(points)
    if labelled == 0:
        raise EmptySceneError(scene_dir / ANNOTATION_FILE, "segGroups", "no vertex keeps a top-100 label after mapping and masking")

    faces = mesh["faces"]
    if faces is not None and faces.shape[1] == 4:
        faces, _ = triangulate_quads(faces)
    views = _read_views(scene_dir, stats)
    return Scene(
        scene_id=scene_id, source="scannetpp", points=points, colors=colors, semantic=semantic,
        instance=instance, faces=faces, multilabel=multilabel, views=tuple(views), root=scene_dir, stats=stats,
    )
