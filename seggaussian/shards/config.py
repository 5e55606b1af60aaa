"""Frozen configuration of the Parquet shard layout (Hugging Face datasets conventions)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ShardConfig:
    """Parquet layout (Hugging Face datasets conventions)."""

    #: Target uncompressed size of one row group (bytes); a row group never spans two scenes.
    row_group_bytes: int = 64 * 2**20
    #: Target compressed size of one shard file (bytes); a scene never spans two shards.
    shard_bytes: int = 512 * 2**20
    #: Parquet compression codec.
    compression: str = "zstd"
    #: Codec level (None = codec default).
    compression_level: int | None = 3
