"""One scene's rows of one table inside a written shard: where they lie, whether they are still there, reading them.

The build cache keeps no copy of what the shards hold: once a scene's rows are assembled into a shard, its cache
keeps a ``SceneRows`` (the shard's path in the dataset, the first row and the row count) instead of its per-scene
table, and a later assembly copies the rows from that shard (``read_fragment_rows``, one scene at a time).

A ``SceneRows`` also holds the shard's size and a sha256 of the bytes the rows are decoded from: the shard's
footer (schema, row-group and column-chunk metadata) and every column chunk of the scene's row groups. Rows read
through it are the rows it was taken from, or an error: a removed, truncated or rewritten shard, or one whose
scene moved, no longer matches (``rows_intact``). The check reads the scene's bytes, not the whole shard.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import NamedTuple

import pyarrow as pa
import pyarrow.parquet as pq

from seggaussian.shards.files import read_fragment
from seggaussian.shards.layout import ShardError
from seggaussian.shards.schema import SCHEMAS

#: A Parquet file's last bytes: the footer's length (4 bytes, little-endian) and the magic ``PAR1``.
_TAIL = 8
_MAGIC = b"PAR1"
#: Bytes hashed per read.
_BLOCK = 1 << 20


class SceneRows(NamedTuple):
    """One scene's rows of one table in one shard of a dataset.

    Fields:
        table: ``gaussians`` or ``views``.
        scene_id: the scene.
        shard: the shard's path relative to the dataset folder (None when the scene has no rows).
        row_offset: the scene's first row in the shard.
        rows: how many rows (a scene's rows are contiguous and fill whole row groups).
        shard_bytes: the shard's size.
        sha256: of the shard's footer and of the column chunks of the scene's row groups (``rows_fingerprint``).
        plan_bytes: the size the shard packing counts for the scene (``writer.plan_shards``): that of the per-scene
            table first written for it, kept so that shards assembled from these rows pack the scenes as before.
    """

    table: str
    scene_id: str
    shard: str | None
    row_offset: int
    rows: int
    shard_bytes: int
    sha256: str
    plan_bytes: int


def _row_groups(metadata, row_offset: int, rows: int) -> list[int] | None:
    """The row groups holding exactly rows ``[row_offset, row_offset + rows)``; None when no whole groups do."""
    groups, start, covered = [], 0, 0
    for i in range(metadata.num_row_groups):
        end = start + metadata.row_group(i).num_rows
        if row_offset <= start and end <= row_offset + rows:
            groups.append(i)
            covered += end - start
        elif start < row_offset + rows and end > row_offset:
            return None  # a group holds rows on both sides of a bound
        start = end
    return groups if covered == rows else None


def _chunk_ranges(metadata, groups: list[int]) -> list[tuple[int, int]]:
    """(start, length) of every column chunk of ``groups`` (dictionary page included), in file order."""
    ranges = []
    for i in groups:
        group = metadata.row_group(i)
        for j in range(group.num_columns):
            column = group.column(j)
            start = column.data_page_offset
            if column.has_dictionary_page and column.dictionary_page_offset is not None:
                start = min(start, column.dictionary_page_offset)
            ranges.append((start, column.total_compressed_size))
    return sorted(ranges)


def rows_fingerprint(path: Path, metadata, groups: list[int]) -> str:
    """sha256 of the footer of the Parquet file ``path`` and of the column chunks of its row groups ``groups``."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        f.seek(size - _TAIL)
        tail = f.read(_TAIL)
        if len(tail) != _TAIL or tail[4:] != _MAGIC:
            raise ShardError(f"{path}: not a Parquet file (no footer)")
        footer = int.from_bytes(tail[:4], "little")
        f.seek(size - _TAIL - footer)
        h.update(f.read(footer + _TAIL))
        for start, length in _chunk_ranges(metadata, groups):
            f.seek(start)
            h.update(start.to_bytes(8, "little"))
            while length > 0:
                block = f.read(min(length, _BLOCK))
                if not block:
                    raise ShardError(f"{path}: truncated (a column chunk ends past the end of the file)")
                h.update(block)
                length -= len(block)
    return h.hexdigest()


def locate_scenes(dataset: Path, shard: str, table: str, scene_ids, plan_bytes: dict[str, int]) -> dict[str, SceneRows]:
    """``SceneRows`` of every scene of ``scene_ids`` in the shard ``dataset/shard`` (scenes in shard order; a scene
    with no rows is located too, with no shard). ``plan_bytes[scene]`` is kept in each (``SceneRows.plan_bytes``).
    ``ShardError`` when a scene's rows are not the contiguous whole row groups the writer makes."""
    path = Path(dataset) / shard
    try:
        pf = pq.ParquetFile(path)
    except (OSError, pa.ArrowException) as exc:
        raise ShardError(f"{path}: unreadable {table} shard ({exc})") from None
    metadata = pf.metadata
    col = pf.schema_arrow.get_field_index("scene_id")
    spans: dict[str, list[int]] = {}  # scene -> [first row, rows, first group, groups]
    start = 0
    for i in range(metadata.num_row_groups):
        group = metadata.row_group(i)
        stats = group.column(col).statistics
        if stats is None or not stats.has_min_max or stats.min != stats.max:
            raise ShardError(f"{path}: row group {i} is not one scene's")
        scene = stats.min.decode() if isinstance(stats.min, bytes) else stats.min
        span = spans.setdefault(scene, [start, 0, i, 0])
        if span[2] + span[3] != i:
            raise ShardError(f"{path}: the rows of scene {scene} are not contiguous")
        span[1] += group.num_rows
        span[3] += 1
        start += group.num_rows
    size = path.stat().st_size
    located = {}
    for scene in scene_ids:
        if scene not in spans:
            located[scene] = SceneRows(table, scene, None, 0, 0, 0, "", plan_bytes[scene])
            continue
        first, rows, group, count = spans[scene]
        digest = rows_fingerprint(path, metadata, list(range(group, group + count)))
        located[scene] = SceneRows(table, scene, shard, first, rows, size, digest, plan_bytes[scene])
    return located


def _open_rows(dataset: Path, rows: SceneRows) -> tuple[pq.ParquetFile, list[int]] | None:
    """(the open shard, the scene's row groups) when the shard still holds exactly the rows, else None."""
    path = Path(dataset) / rows.shard
    try:
        if path.stat().st_size != rows.shard_bytes:
            return None
        pf = pq.ParquetFile(path)
        groups = _row_groups(pf.metadata, rows.row_offset, rows.rows)
        if groups is None or rows_fingerprint(path, pf.metadata, groups) != rows.sha256:
            return None
    except (OSError, pa.ArrowException, ShardError):
        return None
    return pf, groups


def rows_intact(dataset: Path, rows: SceneRows) -> bool:
    """True when the shard still holds the scene's rows byte for byte (see the module docstring)."""
    return rows.shard is None or _open_rows(dataset, rows) is not None


def read_scene_rows(dataset: Path, rows: SceneRows, columns: list[str] | None = None) -> pa.Table:
    """The scene's rows (``columns`` of them, or all, in the table's schema); ``ShardError`` when the shard no longer
    holds them."""
    schema = SCHEMAS[rows.table]
    if rows.shard is None:
        empty = schema.empty_table()
        return empty if columns is None else empty.select(columns)
    opened = _open_rows(dataset, rows)
    if opened is None:
        raise ShardError(f"{Path(dataset) / rows.shard}: no longer holds the {rows.table} rows of scene "
                         f"{rows.scene_id} it held when it was assembled (rebuild with `seggaussian build`)")
    pf, groups = opened
    table = pf.read_row_groups(groups, columns=columns).replace_schema_metadata(None)
    return table.cast(schema) if columns is None else table


def fragment_bytes(fragment: Path | SceneRows) -> int:
    """The size the shard packing counts for one scene's table: its per-scene file's, or ``SceneRows.plan_bytes``."""
    return fragment.plan_bytes if isinstance(fragment, SceneRows) else Path(fragment).stat().st_size


def read_fragment_rows(dataset: Path, fragment: Path | SceneRows, table_name: str,
                       columns: list[str] | None = None) -> pa.Table:
    """One scene's rows of ``table_name`` (``columns`` of them, or all) from its per-scene file or from the shard
    that holds them."""
    if isinstance(fragment, SceneRows):
        return read_scene_rows(dataset, fragment, columns)
    if columns is not None:
        try:
            return pq.read_table(fragment, columns=columns)
        except (OSError, pa.ArrowInvalid) as exc:
            raise ShardError(f"{fragment}: unreadable {table_name} table ({exc})") from None
    return read_fragment(fragment, table_name)
