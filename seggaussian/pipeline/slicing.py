"""Slices of a build for job arrays: ``seggaussian build --num-shards N --shard-index K``.

A slice is the scenes whose position in the sorted scene ids is ``K`` modulo ``N`` (round robin), so it depends
only on the raw tree's scene ids, ``N`` and ``K``: not on the machine, the order the source lists its scenes, or
what other slices do. The ``N`` slices are disjoint, cover every scene, and differ in size by at most one scene.

Slices of one build run at the same time into one output folder on shared storage. Each writes only the cache
folders of its own scenes (``.build/scenes/<scene>``, ``.build/replica_views/<scene>``; every file in them
written atomically) and sweeps the temporaries of killed runs only there, since a temporary's process id says
nothing about a writer on another machine. A slice never writes the dataset-level files (``.build/build.json``,
the shards, manifest, card, ``splits.json``): a later build without slicing finds every scene cached, builds
nothing, and assembles them, byte-identical to a build in one process.
"""

from __future__ import annotations

from typing import Iterable


def check_slice(num_shards: int, shard_index: int) -> None:
    """Refuse a slice that does not exist (one-line error naming the options)."""
    if int(num_shards) < 1:
        raise ValueError(f"build: --num-shards must be at least 1, got {num_shards}")
    if not 0 <= int(shard_index) < int(num_shards):
        raise ValueError(f"build: --shard-index must be in 0..{int(num_shards) - 1} for --num-shards {num_shards}, "
                         f"got {shard_index}")


def slice_ids(scene_ids: Iterable[str], num_shards: int, shard_index: int) -> list[str]:
    """The sorted scene ids of slice ``shard_index`` of ``num_shards``: every ``num_shards``-th id of the sorted
    (deduplicated) list, starting at position ``shard_index``."""
    check_slice(num_shards, shard_index)
    return sorted(set(scene_ids))[int(shard_index)::int(num_shards)]

