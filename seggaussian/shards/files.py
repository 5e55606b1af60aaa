"""Files of a dataset, written atomically: Parquet files of whole scenes (row groups sized in bytes, footer
metadata), the JSON files, and their sha256.

Every file is written to a temporary name in its folder and renamed; files whose bytes would not change are
not rewritten (their mtime stays). The dataset's JSON files (manifest, splits, build records) are written by
``seggaussian.util.atomic.write_json_atomic`` with keys sorted, ``only_if_changed`` and NaN/Inf as null.
"""

from __future__ import annotations

import hashlib
import json
from contextlib import ExitStack
from pathlib import Path
from typing import Iterable

import pyarrow as pa
import pyarrow.parquet as pq

from seggaussian.util import atomic
from seggaussian.shards.config import ShardConfig
from seggaussian.shards.layout import ShardError
from seggaussian.shards.schema import (
    META_CLASS_NAMES,
    META_CONFIG_HASH,
    META_SCHEMA_VERSION,
    META_SPLIT,
    META_TABLE,
    SCHEMA_VERSION,
    SCHEMAS,
)


#: Columns whose values repeat a lot (dictionary-encoded); image bytes are never dictionary-encoded.
DICTIONARY_COLUMNS = ["scene_id", "role", "rgb_format", "sh_degree"]


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


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
    *,
    stack: ExitStack | None = None,
) -> bool:
    """Write the tables (one per scene, in order) into one Parquet file; each table fills its own row
    groups. Temp name + rename; byte-deterministic for the same inputs and pyarrow version. Returns False
    when an identical file was already there (left untouched).

    ``stack``: the rename waits until ``stack`` closes (and the temporary goes if it closes on an error), so
    that the files of one assembly replace the earlier ones together, after every row copied from those was read.
    """
    path = Path(path)
    if stack is None:
        with ExitStack() as own:
            return write_parquet_atomic(path, table_name, scene_tables, config, metadata, stack=own)
    schema = SCHEMAS[table_name].with_metadata(metadata or {})
    tmp = stack.enter_context(atomic.atomic_path(path))
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


def read_footer(path: Path) -> dict:
    """Decoded seggaussian footer metadata of one shard file."""
    meta = pq.ParquetFile(path).schema_arrow.metadata or {}
    out = {k.decode(): v.decode() for k, v in meta.items() if k.startswith(b"seggaussian.")}
    if "seggaussian.class_names" in out:
        out["seggaussian.class_names"] = json.loads(out["seggaussian.class_names"])
    return out
