"""Read a dataset: the manifest, its scene index, and one scene's rows (only its row groups), each shard file
checked against the manifest first (size always, sha256 on request) and float columns checked finite.
Every problem is a ``ShardError`` naming the file and the scene.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from seggaussian.shards.files import sha256_file
from seggaussian.shards.layout import MANIFEST_NAME, SPLITS, ShardError
from seggaussian.shards.records import SceneRecord, ViewCamera
from seggaussian.shards.schema import GAUSSIANS_TABLE, SCHEMAS, VIEWS_TABLE
from seggaussian.shards.tables import table_to_cameras, table_to_gaussians, table_to_views


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
                      manifest: dict | None = None, columns: list[str] | None = None) -> pa.Table:
    path = Path(dataset) / rel
    verify_file(dataset, rel, sha256=verify, scene_id=scene_id, manifest=manifest)
    try:
        pf = pq.ParquetFile(path)
        groups = _scene_row_groups(pf, scene_id, path)
        if not groups:
            empty = SCHEMAS[table_name].empty_table()
            return empty if columns is None else empty.select(columns)
        return pf.read_row_groups(groups, columns=columns)
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


def _scene_entry(dataset: Path, split: str, scene_id: str) -> tuple[dict, dict]:
    """(the manifest, its entry of ``scene_id``); ShardError when the scene is not in ``split``."""
    manifest = read_manifest(dataset)
    info = manifest.get("scenes", {}).get(scene_id)
    if info is None or info.get("split") != split:
        raise ShardError(f"{dataset / MANIFEST_NAME}: no scene {scene_id!r} in split {split!r}")
    return manifest, info


def read_scene(dataset: Path, split: str, scene_id: str, *, views: bool = True, verify: bool = False) -> SceneRecord:
    """One scene of ``split``: its Gaussians (with labels) and views, reading only its row groups.

    Its shard files are checked against the manifest first: size always, sha256 with ``verify``.
    Every problem is a ``ShardError`` naming the file and the scene.
    """
    dataset = Path(dataset)
    manifest, info = _scene_entry(dataset, split, scene_id)
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


#: Columns of the views table that make a camera (no image is read or decoded).
_CAMERA_COLUMNS = ["view_name", "role", "K", "viewmat", "width", "height"]


def read_scene_cameras(dataset: Path, split: str, scene_id: str) -> list[ViewCamera]:
    """The cameras of one scene's views (stored order), without reading their images; the shard file is checked
    against the manifest (size) first."""
    dataset = Path(dataset)
    manifest, info = _scene_entry(dataset, split, scene_id)
    rel = info["files"][VIEWS_TABLE]
    table = _read_scene_table(dataset, VIEWS_TABLE, rel, scene_id, manifest=manifest, columns=_CAMERA_COLUMNS)
    try:
        return table_to_cameras(table)  # Camera refuses a NaN or Inf K / viewmat
    except (ValueError, pa.ArrowException) as exc:
        if isinstance(exc, ShardError):
            raise
        raise ShardError(f"{dataset / rel}: scene {scene_id}: {exc}") from None


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
