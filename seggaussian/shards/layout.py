"""Names of a dataset folder's files and splits, and the error every shard problem raises.

Layout (Hugging Face ``datasets`` conventions; details in ``data_specs/SHARDS.md``)::

    DATASET/README.md                                   dataset card (YAML ``configs`` for load_dataset)
    DATASET/manifest.json                               rows, bytes, sha256 per file; scene index; statistics
    DATASET/splits.json                                 scene -> train | val | xval
    DATASET/gaussians/{split}-{i:05d}-of-{n:05d}.parquet one row per Gaussian
    DATASET/views/{split}-{i:05d}-of-{n:05d}.parquet     one row per view
    DATASET/.build/                                     build cache (not part of the published dataset)
"""

from __future__ import annotations

import re

SPLITS = ("train", "val", "xval")
MANIFEST_NAME = "manifest.json"
SPLITS_NAME = "splits.json"
CARD_NAME = "README.md"
#: A shard file's name: ``{split}-{i:05d}-of-{n:05d}.parquet``.
SHARD_NAME = re.compile(r"^(?P<split>[a-z]+)-(?P<i>\d{5})-of-(?P<n>\d{5})\.parquet$")


class ShardError(ValueError):
    """A dataset folder or shard that does not follow the layout; the message names the file."""


def shard_name(split: str, index: int, count: int) -> str:
    """The name of shard ``index`` of ``count`` of ``split`` (matches ``SHARD_NAME``)."""
    return f"{split}-{index:05d}-of-{count:05d}.parquet"
