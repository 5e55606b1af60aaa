"""Write a dataset: scenes packed into split-named shard files, the manifest and the card.

A scene's rows are contiguous, never span two shards, and fill whole row groups of their own, so
``read_scene`` reads only that scene's row groups. Shards of a split no longer in the plan are removed.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import pyarrow.parquet as pq

from seggaussian.util import atomic
from seggaussian.util.atomic import write_bytes_atomic, write_json_atomic
from seggaussian.shards.config import ShardConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.util.jsonsafe import NAN_AS_NULL
from seggaussian.shards.card import dataset_card
from seggaussian.shards.files import footer_metadata, read_fragment, sha256_file, write_parquet_atomic
from seggaussian.shards.layout import CARD_NAME, MANIFEST_NAME, SHARD_NAME, SPLITS, ShardError, shard_name
from seggaussian.shards.schema import GAUSSIANS_TABLE, SCHEMA_VERSION, VIEWS_TABLE


class FileInfo(NamedTuple):
    """One written file: path relative to the dataset, rows, bytes, sha256 and the scenes it holds."""

    path: str
    rows: int
    bytes: int
    sha256: str
    scenes: tuple


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
    write_json_atomic(dataset / MANIFEST_NAME, manifest, nan=NAN_AS_NULL, sort_keys=True, only_if_changed=True)
    write_bytes_atomic(dataset / CARD_NAME, dataset_card("SegGaussian dataset", by_split, class_names).encode(),
                       only_if_changed=True)
    return manifest
