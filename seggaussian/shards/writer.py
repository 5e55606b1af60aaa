"""Write a dataset: scenes packed into split-named shard files, the manifest and the card.

A scene's rows are contiguous, never span two shards, and fill whole row groups of their own, so
``read_scene`` reads only that scene's row groups. A scene's rows come from its per-scene table in the build
cache or from the shard an earlier assembly wrote them to (``rows.SceneRows``). Shards of a split no longer in
the plan are removed.
"""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path
from typing import NamedTuple

import pyarrow.parquet as pq

from seggaussian.util import atomic
from seggaussian.util.atomic import write_bytes_atomic, write_json_atomic
from seggaussian.shards.config import ShardConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.util.jsonsafe import NAN_AS_NULL
from seggaussian.shards.card import dataset_card
from seggaussian.shards.files import footer_metadata, sha256_file, write_parquet_atomic
from seggaussian.shards.rows import SceneRows, fragment_bytes, read_fragment_rows
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
    fragments: dict[str, dict[str, Path | SceneRows]],
    config: ShardConfig,
    class_names,
    config_hash: str,
    stack: ExitStack,
) -> tuple[list[tuple[Path, tuple]], dict[Path, set[str]]]:
    """Write ``{table}/{split}-*.parquet`` from per-scene fragments, renamed into place when ``stack`` closes
    (``files.write_parquet_atomic``).

    ``fragments[scene_id][table]`` is the cached per-scene Parquet file of that table, or the scene's rows in a
    shard written before (``rows.SceneRows``). Scenes are written in sorted order. Returns the files with their
    scenes, and per table folder the names the split keeps (the caller removes the others once ``stack`` closed).
    """
    dataset = Path(dataset)
    written: list[tuple[Path, tuple]] = []
    keep: dict[Path, set[str]] = {}
    scene_ids = sorted(fragments)
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
        folder = dataset / table_name
        sizes = [(s, fragment_bytes(fragments[s][table_name])) for s in scene_ids]
        plan = plan_shards(sizes, config.shard_bytes)
        names = [shard_name(split, i, len(plan)) for i in range(len(plan))]
        meta = footer_metadata(table_name, split, class_names, config_hash)
        for name, group in zip(names, plan):
            path = folder / name
            write_parquet_atomic(path, table_name,
                                 (read_fragment_rows(dataset, fragments[s][table_name], table_name) for s in group),
                                 config, meta, stack=stack)
            written.append((path, tuple(group)))
        keep[folder] = set(names)
    return written, keep


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
    Parquet path, or the scene's ``rows.SceneRows`` in a shard written before}) and any JSON-ready per-scene
    information (source, counts, transfer statistics) copied into the manifest. Scenes without an assignment are
    left out. Every shard is renamed into place once all are written, so rows copied from an earlier shard are read
    before the file holding them is replaced; the shards no longer in the plan go last. Returns the manifest.
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
    written: dict[str, list[tuple[Path, tuple]]] = {}
    keep: dict[tuple[Path, str], set[str]] = {}
    # every shard is renamed into place once all are written: the rows copied from earlier shards stay readable
    with ExitStack() as stack:
        for split in SPLITS:
            ids = by_split[split]
            if not ids:
                keep.update({(dataset / table_name, split): set() for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE)})
                continue
            written[split], kept = write_split_shards(dataset, split, {s: scenes[s]["fragments"] for s in ids}, config,
                                                      class_names, config_hash, stack)
            keep.update({(folder, split): names for folder, names in kept.items()})
    for (folder, split), names in keep.items():
        remove_stale_shards(folder, split, keep=names)
    for split, shards in written.items():
        for path, group in shards:
            info = _file_info(dataset, path, group)
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
