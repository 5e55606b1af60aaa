"""Parquet shards of a SegGaussian dataset: per-scene tables, split-named shard files, manifest, read API.

Layout of a dataset folder (Hugging Face ``datasets`` conventions; details in ``data_specs/SHARDS.md``)::

    DATASET/README.md                                   dataset card (YAML ``configs`` for load_dataset)
    DATASET/manifest.json                               rows, bytes, sha256 per file; scene index; statistics
    DATASET/splits.json                                 scene -> train | val | xval
    DATASET/gaussians/{split}-{i:05d}-of-{n:05d}.parquet one row per Gaussian
    DATASET/views/{split}-{i:05d}-of-{n:05d}.parquet     one row per view
    DATASET/.build/                                     build cache (not part of the published dataset)

Every file is written to a temporary name in its folder and renamed; files whose bytes would not change are
not rewritten (their mtime stays). A scene's rows are contiguous, never span two shards, and fill whole
row groups of their own, so ``read_scene`` reads only that scene's row groups.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from seggaussian import atomic
from seggaussian.build_config import ShardConfig
from seggaussian.cameras import Camera
from seggaussian.constants import IGNORE_LABEL
from seggaussian.gaussians import Gaussians
from seggaussian.jsonsafe import NAN_AS_NULL
from seggaussian.shard_schema import (
    GAUSSIANS_SCHEMA,
    GAUSSIANS_TABLE,
    META_CLASS_NAMES,
    META_CONFIG_HASH,
    META_SCHEMA_VERSION,
    META_SPLIT,
    META_TABLE,
    SCHEMA_VERSION,
    SCHEMAS,
    VIEWS_SCHEMA,
    VIEWS_TABLE,
)

SPLITS = ("train", "val", "xval")
MANIFEST_NAME = "manifest.json"
SPLITS_NAME = "splits.json"
CARD_NAME = "README.md"
#: Columns whose values repeat a lot (dictionary-encoded); image bytes are never dictionary-encoded.
DICTIONARY_COLUMNS = ["scene_id", "role", "rgb_format", "sh_degree"]
SHARD_NAME = re.compile(r"^(?P<split>[a-z]+)-(?P<i>\d{5})-of-(?P<n>\d{5})\.parquet$")


class ShardError(ValueError):
    """A dataset folder or shard that does not follow the layout; the message names the file."""


class ViewRecord(NamedTuple):
    """One view of a scene as stored.

    Fields:
        name: view (image) name.
        role: ``train`` or ``novel``.
        camera: intrinsics, world-to-camera pose (OpenCV) and size.
        rgb: ``[H, W, 3]`` uint8.
        semantic: ``[H, W]`` int32 class ids rendered from the labelled Gaussians, IGNORE_LABEL where empty.
        instance: ``[H, W]`` int32 instance ids, IGNORE_LABEL where empty.
    """

    name: str
    role: str
    camera: Camera
    rgb: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray


class SceneRecord(NamedTuple):
    """One scene as stored: Gaussians with ``extras`` semantic, instance, multilabel, transfer_distance."""

    scene_id: str
    source: str
    gaussians: Gaussians
    views: list


class FileInfo(NamedTuple):
    """One written file: path relative to the dataset, rows, bytes, sha256 and the scenes it holds."""

    path: str
    rows: int
    bytes: int
    sha256: str
    scenes: tuple


# --- encoding -----------------------------------------------------------------------------------
def encode_label_map(labels: np.ndarray) -> bytes:
    """``[H, W]`` ids (0..65535, IGNORE_LABEL included) -> 16-bit PNG bytes (lossless)."""
    import cv2

    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"label map has shape {labels.shape}, expected (H, W)")
    if labels.size and (labels.min() < 0 or labels.max() > IGNORE_LABEL):
        raise ValueError(f"label map holds ids outside 0..{IGNORE_LABEL} (min {labels.min()}, max {labels.max()})")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(labels.astype(np.uint16)))
    if not ok:
        raise ValueError("cv2.imencode failed on a label map")
    return buf.tobytes()


def decode_label_map(data: bytes, what: str = "label map") -> np.ndarray:
    """16-bit PNG bytes -> ``[H, W]`` int32."""
    import cv2

    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.ndim != 2 or arr.dtype != np.uint16:
        raise ShardError(f"{what}: not a single-channel 16-bit PNG")
    return arr.astype(np.int32)


def encode_rgb(rgb: np.ndarray) -> bytes:
    """``[H, W, 3]`` uint8 RGB -> PNG bytes."""
    import cv2

    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb has shape {rgb.shape} dtype {rgb.dtype}, expected (H, W, 3) uint8")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise ValueError("cv2.imencode failed on an RGB image")
    return buf.tobytes()


def decode_rgb(data: bytes, what: str = "rgb") -> np.ndarray:
    """PNG/JPEG bytes -> ``[H, W, 3]`` uint8 RGB."""
    import cv2

    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if arr is None:
        raise ShardError(f"{what}: image bytes do not decode")
    return np.ascontiguousarray(arr[:, :, ::-1])


def image_format(data: bytes) -> str:
    """``png`` or ``jpeg`` from the magic bytes; ShardError otherwise."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    raise ShardError("rgb bytes are neither PNG nor JPEG")


# --- per-scene tables ---------------------------------------------------------------------------
def _fixed_list(values: np.ndarray, width: int, dtype) -> pa.FixedSizeListArray:
    flat = pa.array(np.ascontiguousarray(values, dtype=dtype).reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, width)


def gaussians_table(scene_id: str, gaussians: Gaussians) -> pa.Table:
    """The ``gaussians`` rows of one scene. ``gaussians.extras`` must hold semantic, instance,
    transfer_distance and (optionally) multilabel."""
    n = len(gaussians)
    ex = gaussians.extras
    for key in ("semantic", "instance", "transfer_distance"):
        if key not in ex:
            raise ValueError(f"scene {scene_id}: Gaussians.extras lacks {key!r}")
    multilabel = ex.get("multilabel")
    if multilabel is None:
        multilabel = np.full((n, 3), IGNORE_LABEL, np.int32)
        multilabel[:, 0] = ex["semantic"]
    k = gaussians.num_sh_coeffs
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * (k * 3))
    sh = pa.ListArray.from_arrays(offsets, pa.array(np.ascontiguousarray(gaussians.sh).reshape(-1)))
    distance = np.asarray(ex["transfer_distance"], np.float32)
    if not np.isfinite(distance).all():
        raise ValueError(f"scene {scene_id}: transfer_distance holds NaN/Inf")
    columns = [
        pa.repeat(pa.scalar(scene_id, pa.string()), n),
        _fixed_list(gaussians.means, 3, np.float32),
        _fixed_list(gaussians.quats, 4, np.float32),
        _fixed_list(gaussians.log_scales, 3, np.float32),
        pa.array(gaussians.opacity_logits.astype(np.float32)),
        pa.array(np.full(n, gaussians.sh_degree, np.uint8)),
        sh,
        pa.array(np.asarray(ex["semantic"], np.int32)),
        pa.array(np.asarray(ex["instance"], np.int32)),
        _fixed_list(multilabel, 3, np.int32),
        pa.array(distance),
    ]
    return pa.Table.from_arrays(columns, schema=GAUSSIANS_SCHEMA)


class ViewRow(NamedTuple):
    """A view ready to store: camera, encoded RGB and label maps."""

    name: str
    role: str
    camera: Camera
    rgb: bytes
    semantic: bytes
    instance: bytes
    label_coverage: float


def views_table(scene_id: str, rows: list) -> pa.Table:
    """The ``views`` rows of one scene (``rows``: ViewRow list, stored in the given order)."""
    n = len(rows)
    columns = [
        pa.array([scene_id] * n, pa.string()),
        pa.array([r.name for r in rows], pa.string()),
        pa.array([r.role for r in rows], pa.string()),
        pa.array([r.camera.width for r in rows], pa.int32()),
        pa.array([r.camera.height for r in rows], pa.int32()),
        _fixed_list(np.array([r.camera.K for r in rows]).reshape(n, 9), 9, np.float64),
        _fixed_list(np.array([r.camera.viewmat for r in rows]).reshape(n, 16), 16, np.float64),
        pa.array([r.rgb for r in rows], pa.binary()),
        pa.array([image_format(r.rgb) for r in rows], pa.string()),
        pa.array([r.semantic for r in rows], pa.binary()),
        pa.array([r.instance for r in rows], pa.binary()),
        pa.array([float(r.label_coverage) for r in rows], pa.float32()),
    ]
    return pa.Table.from_arrays(columns, schema=VIEWS_SCHEMA)


# --- writing ------------------------------------------------------------------------------------
def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_bytes_atomic(path: Path, data: bytes, *, only_if_changed: bool = True) -> bool:
    """``atomic.write_bytes_atomic`` that by default leaves a file holding exactly ``data`` untouched
    (mtime kept; returns False then)."""
    return atomic.write_bytes_atomic(path, data, only_if_changed=only_if_changed)


def write_json_atomic(path: Path, payload) -> bool:
    """The dataset's JSON files (manifest, splits, cache records): ``atomic.write_json_atomic`` with keys sorted,
    unchanged files left alone and NaN/Inf written as null."""
    return atomic.write_json_atomic(path, payload, nan=NAN_AS_NULL, sort_keys=True, only_if_changed=True)


def footer_metadata(table: str, split: str | None, class_names, config_hash: str) -> dict[bytes, bytes]:
    """Key-value metadata written into every shard's Parquet footer."""
    meta = {
        META_SCHEMA_VERSION: SCHEMA_VERSION.encode(),
        META_TABLE: table.encode(),
        META_CLASS_NAMES: json.dumps(list(class_names)).encode(),
        META_CONFIG_HASH: config_hash.encode(),
    }
    if split is not None:
        meta[META_SPLIT] = split.encode()
    return meta


def rows_per_row_group(table: pa.Table, row_group_bytes: int) -> int:
    """Rows per row group so that a group holds about ``row_group_bytes`` uncompressed bytes."""
    if table.num_rows == 0:
        return 1
    per_row = max(1, table.nbytes // table.num_rows)
    return int(max(1, row_group_bytes // per_row))


def write_parquet_atomic(
    path: Path,
    table_name: str,
    scene_tables: Iterable[pa.Table],
    config: ShardConfig,
    metadata: dict[bytes, bytes] | None = None,
) -> bool:
    """Write the tables (one per scene, in order) into one Parquet file; each table fills its own row
    groups. Temp name + rename; byte-deterministic for the same inputs and pyarrow version. Returns False
    when an identical file was already there (left untouched)."""
    path = Path(path)
    schema = SCHEMAS[table_name].with_metadata(metadata or {})
    with atomic.atomic_path(path) as tmp:
        with pq.ParquetWriter(
            tmp, schema, compression=config.compression, compression_level=config.compression_level,
            use_dictionary=[c for c in DICTIONARY_COLUMNS if c in schema.names], write_statistics=True,
        ) as writer:
            for table in scene_tables:
                if table.num_rows:
                    writer.write_table(table.cast(schema), row_group_size=rows_per_row_group(table, config.row_group_bytes))
        if path.is_file() and path.stat().st_size == tmp.stat().st_size and sha256_file(path) == sha256_file(tmp):
            tmp.unlink()
            return False  # same bytes: keep the existing file (and its mtime)
    return True


def read_fragment(path: Path, table_name: str) -> pa.Table:
    """One scene's cached table (written by ``write_parquet_atomic`` without footer metadata)."""
    try:
        return pq.read_table(path).cast(SCHEMAS[table_name])
    except (OSError, pa.ArrowInvalid) as exc:
        raise ShardError(f"{path}: unreadable {table_name} table ({exc})") from None


def shard_name(split: str, index: int, count: int) -> str:
    return f"{split}-{index:05d}-of-{count:05d}.parquet"


def plan_shards(scene_bytes: list[tuple[str, int]], shard_bytes: int) -> list[list[str]]:
    """Greedy, order-preserving packing of scenes into shards of about ``shard_bytes`` (a scene never splits)."""
    groups: list[list[str]] = []
    current: list[str] = []
    size = 0
    for scene_id, nbytes in scene_bytes:
        if current and size + nbytes > shard_bytes:
            groups.append(current)
            current, size = [], 0
        current.append(scene_id)
        size += nbytes
    if current:
        groups.append(current)
    return groups


def write_split_shards(
    dataset: Path,
    split: str,
    fragments: dict[str, dict[str, Path]],
    config: ShardConfig,
    class_names,
    config_hash: str,
) -> list[FileInfo]:
    """Write ``{table}/{split}-*.parquet`` from per-scene fragment files.

    ``fragments[scene_id][table]`` is the cached per-scene Parquet file of that table. Scenes are written in
    sorted order; shards of the split that are no longer part of the plan are removed. Returns the files.
    """
    dataset = Path(dataset)
    infos: list[FileInfo] = []
    scene_ids = sorted(fragments)
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
        folder = dataset / table_name
        sizes = [(s, fragments[s][table_name].stat().st_size) for s in scene_ids]
        plan = plan_shards(sizes, config.shard_bytes)
        names = [shard_name(split, i, len(plan)) for i in range(len(plan))]
        meta = footer_metadata(table_name, split, class_names, config_hash)
        for name, group in zip(names, plan):
            path = folder / name
            write_parquet_atomic(path, table_name, (read_fragment(fragments[s][table_name], table_name) for s in group),
                                 config, meta)
            infos.append(_file_info(dataset, path, tuple(group)))
        remove_stale_shards(folder, split, keep=set(names))
    return infos


def remove_stale_shards(folder: Path, split: str, keep: set[str]) -> list[str]:
    """Delete ``{split}-*-of-*.parquet`` files in ``folder`` not in ``keep``; returns their names."""
    removed = []
    if folder.is_dir():
        for f in sorted(folder.iterdir()):
            m = SHARD_NAME.match(f.name)
            if m and m["split"] == split and f.name not in keep:
                f.unlink()
                removed.append(f.name)
    return removed


def _file_info(dataset: Path, path: Path, scenes: tuple) -> FileInfo:
    meta = pq.ParquetFile(path).metadata
    return FileInfo(str(path.relative_to(dataset)), int(meta.num_rows), path.stat().st_size, sha256_file(path), scenes)


def dataset_card(name: str, splits: dict[str, list[str]], class_names, schema_doc: str = "data_specs/SHARDS.md") -> str:
    """README.md with the Hugging Face YAML header (one config per table, data_files per split)."""
    present = [s for s in SPLITS if splits.get(s)]
    lines = ["---", "configs:"]
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
        lines += [f"- config_name: {table_name}", "  data_files:"]
        for split in present:
            lines += [f"  - split: {split}", f"    path: {table_name}/{split}-*.parquet"]
    lines += ["tags:", "- 3d-gaussian-splatting", "- semantic-segmentation", "---", ""]
    lines += [
        f"# {name}",
        "",
        "Labelled 3D Gaussian Splatting scenes built by `seggaussian build` (SegGaussian). Each Gaussian carries",
        "the semantic class (index into the ScanNet++ top-100 list), instance id and label-transfer distance of",
        "its nearest labelled point; each view carries its camera, RGB and rendered semantic/instance maps.",
        f"Schema version {SCHEMA_VERSION}, documented column by column in `{schema_doc}`.",
        "",
        "| split | scenes |",
        "|---|---|",
    ]
    for split in SPLITS:
        lines.append(f"| {split} | {len(splits.get(split, []))} |")
    lines += [
        "",
        f"Ignore label: {IGNORE_LABEL}. Classes ({len(class_names)}): " + ", ".join(class_names) + ".",
        "",
        "```python",
        "from datasets import load_dataset",
        'gaussians = load_dataset("parquet", data_files={"train": "gaussians/train-*.parquet"})',
        "from seggaussian import shards",
        'record = shards.read_scene(".", "train", shards.list_scenes(".", "train")[0])',
        "```",
        "",
    ]
    return "\n".join(lines)


def write_dataset(
    dataset: Path,
    assignments: dict[str, str],
    scenes: dict[str, dict],
    config: ShardConfig,
    class_names,
    config_hash: str,
) -> dict:
    """Write every split's shards, the manifest and the dataset card of ``dataset``.

    ``assignments``: scene id -> split. ``scenes[scene_id]`` holds ``fragments`` ({table: cached per-scene
    Parquet path}) and any JSON-ready per-scene information (source, counts, transfer statistics) copied
    into the manifest. Scenes without an assignment are left out. Returns the manifest.
    """
    dataset = Path(dataset)
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):  # leftovers of a killed writer
        atomic.sweep_temps(dataset / table_name)
    files: dict[str, dict] = {}
    scene_entries: dict[str, dict] = {}
    by_split = {split: sorted(s for s, sp in assignments.items() if sp == split and s in scenes) for split in SPLITS}
    unknown = sorted({sp for sp in assignments.values()} - set(SPLITS))
    if unknown:
        raise ShardError(f"unknown split names {unknown}; expected {', '.join(SPLITS)}")
    for split in SPLITS:
        ids = by_split[split]
        if not ids:
            for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
                remove_stale_shards(dataset / table_name, split, keep=set())
            continue
        infos = write_split_shards(dataset, split, {s: scenes[s]["fragments"] for s in ids}, config, class_names,
                                   config_hash)
        for info in infos:
            files[info.path] = {"rows": info.rows, "bytes": info.bytes, "sha256": info.sha256,
                                "scenes": list(info.scenes)}
            table_name = info.path.split("/", 1)[0]
            for s in info.scenes:
                scene_entries.setdefault(s, {"split": split, "files": {}})["files"][table_name] = info.path
    for s, entry in scene_entries.items():
        entry.update({k: v for k, v in scenes[s].items() if k != "fragments"})
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "config_hash": config_hash,
        "class_names": list(class_names),
        "ignore_label": IGNORE_LABEL,
        "files": files,
        "scenes": dict(sorted(scene_entries.items())),
    }
    write_json_atomic(dataset / MANIFEST_NAME, manifest)
    write_bytes_atomic(dataset / CARD_NAME, dataset_card("SegGaussian dataset", by_split, class_names).encode())
    return manifest


# --- reading ------------------------------------------------------------------------------------
def read_manifest(dataset: Path) -> dict:
    path = Path(dataset) / MANIFEST_NAME
    if not path.is_file():
        raise ShardError(f"{path}: missing (not a dataset folder built by seggaussian build)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ShardError(f"{path}: not valid JSON ({exc})") from None


def list_scenes(dataset: Path, split: str) -> list[str]:
    """Sorted scene ids of ``split`` (train, val, xval)."""
    if split not in SPLITS:
        raise ShardError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")
    manifest = read_manifest(dataset)
    return sorted(s for s, info in manifest.get("scenes", {}).items() if info.get("split") == split)


def _scene_row_groups(pf: pq.ParquetFile, scene_id: str, path: Path) -> list[int]:
    """Row groups whose scene_id statistics are exactly ``scene_id``."""
    col = pf.schema_arrow.get_field_index("scene_id")
    groups = []
    for i in range(pf.metadata.num_row_groups):
        stats = pf.metadata.row_group(i).column(col).statistics
        if stats is None or not stats.has_min_max:
            raise ShardError(f"{path}: row group {i} has no scene_id statistics")
        lo, hi = stats.min, stats.max
        lo = lo.decode() if isinstance(lo, bytes) else lo
        hi = hi.decode() if isinstance(hi, bytes) else hi
        if lo == scene_id and hi == scene_id:
            groups.append(i)
        elif lo <= scene_id <= hi:
            raise ShardError(f"{path}: row group {i} mixes scenes {lo}..{hi}")
    return groups


#: Files already checked against the manifest in this process: (path, size, mtime_ns, with sha256).
_VERIFIED: set[tuple[str, int, int, bool]] = set()


def verify_file(dataset: Path, rel: str, *, sha256: bool = False, scene_id: str | None = None,
                manifest: dict | None = None) -> None:
    """Check one dataset file against the manifest: its size always, its sha256 with ``sha256``.

    ``ShardError`` names the file (and the scene read from it). A file is hashed once per process while
    its size and mtime stay the same.
    """
    manifest = manifest if manifest is not None else read_manifest(dataset)
    path = Path(dataset) / rel
    whose = f" (scene {scene_id})" if scene_id else ""
    entry = manifest.get("files", {}).get(rel)
    if entry is None:
        raise ShardError(f"{path}: not listed in {Path(dataset) / MANIFEST_NAME}{whose}")
    try:
        stat = path.stat()
    except FileNotFoundError:
        raise ShardError(f"{path}: shard listed in the manifest is missing{whose}") from None
    key = (str(path), stat.st_size, stat.st_mtime_ns, sha256)
    if key in _VERIFIED or (str(path), stat.st_size, stat.st_mtime_ns, True) in _VERIFIED:
        return
    if stat.st_size != entry["bytes"]:
        raise ShardError(f"{path}: {stat.st_size} bytes, the manifest says {entry['bytes']}{whose}: "
                         f"truncated or replaced; rebuild the dataset")
    if sha256:
        digest = sha256_file(path)
        if digest != entry["sha256"]:
            raise ShardError(f"{path}: sha256 {digest[:12]}... differs from the manifest's "
                             f"{entry['sha256'][:12]}...{whose}: corrupted; rebuild the dataset")
    _VERIFIED.add(key)


def _read_scene_table(dataset: Path, table_name: str, rel: str, scene_id: str, *, verify: bool = False,
                      manifest: dict | None = None) -> pa.Table:
    path = Path(dataset) / rel
    verify_file(dataset, rel, sha256=verify, scene_id=scene_id, manifest=manifest)
    try:
        pf = pq.ParquetFile(path)
        groups = _scene_row_groups(pf, scene_id, path)
        if not groups:
            return SCHEMAS[table_name].empty_table()
        return pf.read_row_groups(groups)
    except (OSError, pa.ArrowException, ValueError) as exc:
        if isinstance(exc, ShardError):
            raise
        raise ShardError(f"{path}: unreadable {table_name} shard (scene {scene_id}): {exc}") from None


#: Float columns of the gaussians table that must hold finite values.
_FINITE_COLUMNS = ("means", "quats", "log_scales", "opacity_logit", "sh")


def _check_finite(table: pa.Table, path: Path, scene_id: str) -> None:
    """``ShardError`` naming the file, the scene and the column when a float column holds NaN or Inf
    (our writer never stores one: a corrupted shard)."""
    for column in _FINITE_COLUMNS:
        arr = table.column(column).combine_chunks()
        if isinstance(arr.type, (pa.ListType, pa.FixedSizeListType)):
            arr = arr.flatten()
        values = arr.to_numpy(zero_copy_only=False)
        if not np.isfinite(values).all():
            raise ShardError(f"{path}: column '{column}' of scene {scene_id} holds NaN or Inf: corrupted shard "
                             f"(check with `seggaussian inspect DATASET --verify`)")


def _flat(table: pa.Table, column: str, width: int, dtype) -> np.ndarray:
    arr = table.column(column).combine_chunks()
    return np.asarray(arr.flatten().to_numpy(zero_copy_only=False), dtype=dtype).reshape(-1, width)


def table_to_gaussians(table: pa.Table) -> Gaussians:
    """``gaussians`` rows of one scene -> Gaussians with extras semantic, instance, multilabel, transfer_distance."""
    n = table.num_rows
    if n == 0:
        g = Gaussians.empty()
        z = np.zeros(0, np.int32)
        return g.with_extras(semantic=z, instance=z.copy(), multilabel=np.zeros((0, 3), np.int32),
                             transfer_distance=np.zeros(0, np.float32))
    degrees = np.unique(table.column("sh_degree").to_numpy())
    if len(degrees) != 1:
        raise ShardError(f"scene {table.column('scene_id')[0]}: mixed SH degrees {degrees.tolist()}")
    k = (int(degrees[0]) + 1) ** 2
    sh = np.asarray(table.column("sh").combine_chunks().flatten().to_numpy(), np.float32).reshape(n, k, 3)
    return Gaussians(
        _flat(table, "means", 3, np.float32),
        _flat(table, "quats", 4, np.float32),
        _flat(table, "log_scales", 3, np.float32),
        np.asarray(table.column("opacity_logit").to_numpy(), np.float32),
        sh,
        {
            "semantic": np.asarray(table.column("semantic").to_numpy(), np.int32),
            "instance": np.asarray(table.column("instance").to_numpy(), np.int32),
            "multilabel": _flat(table, "multilabel", 3, np.int32),
            "transfer_distance": np.asarray(table.column("transfer_distance").to_numpy(), np.float32),
        },
    )


def table_to_views(table: pa.Table) -> list[ViewRecord]:
    """``views`` rows of one scene -> decoded ViewRecords (stored order)."""
    out = []
    cols = table.to_pydict()
    for i in range(table.num_rows):
        what = f"view {cols['scene_id'][i]}/{cols['view_name'][i]}"
        camera = Camera(np.array(cols["K"][i]).reshape(3, 3), np.array(cols["viewmat"][i]).reshape(4, 4),
                        cols["width"][i], cols["height"][i])
        out.append(ViewRecord(
            cols["view_name"][i], cols["role"][i], camera,
            decode_rgb(cols["rgb"][i], what + " rgb"),
            decode_label_map(cols["semantic"][i], what + " semantic"),
            decode_label_map(cols["instance"][i], what + " instance"),
        ))
    return out


def read_scene(dataset: Path, split: str, scene_id: str, *, views: bool = True, verify: bool = False) -> SceneRecord:
    """One scene of ``split``: its Gaussians (with labels) and views, reading only its row groups.

    Its shard files are checked against the manifest first: size always, sha256 with ``verify``.
    Every problem is a ``ShardError`` naming the file and the scene.
    """
    dataset = Path(dataset)
    manifest = read_manifest(dataset)
    info = manifest.get("scenes", {}).get(scene_id)
    if info is None or info.get("split") != split:
        raise ShardError(f"{dataset / MANIFEST_NAME}: no scene {scene_id!r} in split {split!r}")
    rel = info["files"][GAUSSIANS_TABLE]
    table = _read_scene_table(dataset, GAUSSIANS_TABLE, rel, scene_id, verify=verify, manifest=manifest)
    _check_finite(table, dataset / rel, scene_id)
    try:
        g = table_to_gaussians(table)
        v = []
        if views:
            rel = info["files"][VIEWS_TABLE]
            v = table_to_views(_read_scene_table(dataset, VIEWS_TABLE, rel, scene_id, verify=verify,
                                                 manifest=manifest))
    except (ValueError, pa.ArrowException) as exc:
        if isinstance(exc, ShardError) and str(exc).startswith(str(dataset)):
            raise
        raise ShardError(f"{dataset / rel}: scene {scene_id}: {exc}") from None
    return SceneRecord(scene_id, info.get("source", "unknown"), g, v)


def iter_scenes(dataset: Path, split: str, *, views: bool = True, verify: bool = False) -> Iterator[SceneRecord]:
    """Scenes of ``split`` one at a time (memory bounded by the largest scene)."""
    for scene_id in list_scenes(dataset, split):
        yield read_scene(dataset, split, scene_id, views=views, verify=verify)


def find_split(dataset: Path, scene_id: str) -> str:
    """The split holding ``scene_id``."""
    info = read_manifest(dataset).get("scenes", {}).get(scene_id)
    if info is None:
        raise ShardError(f"{Path(dataset) / MANIFEST_NAME}: no scene {scene_id!r}")
    return info["split"]


def read_footer(path: Path) -> dict:
    """Decoded seggaussian footer metadata of one shard file."""
    meta = pq.ParquetFile(path).schema_arrow.metadata or {}
    out = {k.decode(): v.decode() for k, v in meta.items() if k.startswith(b"seggaussian.")}
    if "seggaussian.class_names" in out:
        out["seggaussian.class_names"] = json.loads(out["seggaussian.class_names"])
    return out


def inspect_dataset(path: Path, *, verify: bool = False) -> dict:
    """Summary of a dataset folder: per-split scene counts, class histogram, transfer statistics, files.

    Reads only the manifest and the files' sizes (no row data); flags files missing or changed in size,
    and with ``verify`` files whose sha256 differs from the manifest's (each problem names the file and
    its scenes).
    """
    dataset = Path(path)
    manifest = read_manifest(dataset)
    scenes = manifest.get("scenes", {})
    class_names = manifest.get("class_names", [])
    per_split: dict[str, dict] = {}
    for split in SPLITS:
        ids = sorted(s for s, i in scenes.items() if i.get("split") == split)
        hist: dict[int, int] = {}
        ignored = gaussians = views = 0
        shares, q50, q99, accuracies = [], [], [], []
        for s in ids:
            info = scenes[s]
            t = info.get("transfer", {})
            for k, c in t.get("class_histogram", {}).items():
                hist[int(k)] = hist.get(int(k), 0) + int(c)
            ignored += int(t.get("ignored", 0))
            gaussians += int(info.get("num_gaussians", 0))
            views += int(info.get("num_views", 0))
            shares.append(float(t.get("ignored_share", 0.0)))
            q50.append(float(t.get("distance_quantiles", {}).get("q50", 0.0)))
            q99.append(float(t.get("distance_quantiles", {}).get("q99", 0.0)))
            acc = info.get("label_accuracy", {}).get("accuracy")
            if acc is not None:
                accuracies.append(acc)
        per_split[split] = {
            "scenes": len(ids),
            "gaussians": gaussians,
            "views": views,
            "ignored_share": (ignored / gaussians) if gaussians else 0.0,
            "ignored_share_max": max(shares) if shares else 0.0,
            "distance_q50_median": float(np.median(q50)) if q50 else 0.0,
            "distance_q99_max": max(q99) if q99 else 0.0,
            "label_accuracy_min": min(accuracies) if accuracies else None,
            "class_histogram": {
                (class_names[k] if k < len(class_names) else str(k)): c for k, c in sorted(hist.items())
            },
        }
    problems = []
    for rel, f in sorted(manifest.get("files", {}).items()):
        p = dataset / rel
        whose = f" (scenes {', '.join(f.get('scenes', []))})" if f.get("scenes") else ""
        if not p.is_file():
            problems.append(f"{rel}: missing{whose}")
        elif p.stat().st_size != f["bytes"]:
            problems.append(f"{rel}: {p.stat().st_size} bytes, manifest says {f['bytes']}{whose}")
        elif verify and sha256_file(p) != f["sha256"]:
            problems.append(f"{rel}: sha256 differs from the manifest{whose}")
    counts = " / ".join(f"{per_split[s]['scenes']} {s}" for s in SPLITS)
    total_g = sum(v["gaussians"] for v in per_split.values())
    total_ignored = sum(v["ignored_share"] * v["gaussians"] for v in per_split.values())
    summary = (f"dataset {dataset}: {counts} scenes, {total_g} Gaussians, "
               f"{100 * total_ignored / total_g if total_g else 0.0:.1f}% ignored"
               + (f", {len(problems)} problem(s)" if problems else ""))
    return {
        "summary": summary,
        "path": str(dataset),
        "schema_version": manifest.get("schema_version"),
        "config_hash": manifest.get("config_hash"),
        "num_classes": len(class_names),
        "splits": per_split,
        "scenes": {s: {k: scenes[s].get(k) for k in ("split", "source", "num_gaussians", "num_views")}
                   for s in sorted(scenes)},
        "files": len(manifest.get("files", {})),
        "bytes": sum(f["bytes"] for f in manifest.get("files", {}).values()),
        "problems": problems,
        "verified": verify,
    }
