"""Parquet shards of a SegGaussian dataset: per-scene tables, split-named shard files, manifest, read API.

Layout of a dataset folder: ``seggaussian.shards.layout`` (details in ``data_specs/SHARDS.md``). One concept
per module:

- ``schema``: Arrow schemas of the two tables and the footer keys, versioned;
- ``layout``: file and split names, ``ShardError``;
- ``records``: a scene and a view as stored (``ViewRow``) and as read (``SceneRecord``, ``ViewRecord``);
- ``images``: PNG/JPEG codecs of RGB and label maps;
- ``tables``: Gaussians and views <-> Arrow tables of one scene;
- ``files``: atomic Parquet and JSON writers, sha256, footer metadata;
- ``rows``: one scene's rows inside a written shard (``SceneRows``): located, checked, read back;
- ``writer``: shards, manifest and card of a dataset (``write_dataset``);
- ``card``: the dataset card;
- ``read``: manifest, scene index and one scene's rows, verified against the manifest (``read_scene``);
- ``inspection``: ``inspect_dataset``.

This package re-exports the public read and write API, so ``from seggaussian import shards`` then
``shards.read_scene(...)`` works.
"""

from seggaussian.shards.card import dataset_card
from seggaussian.shards.files import read_footer, read_fragment, sha256_file, write_parquet_atomic
from seggaussian.shards.images import decode_label_map, decode_rgb, encode_label_map, encode_rgb, image_format
from seggaussian.shards.inspection import inspect_dataset
from seggaussian.shards.layout import CARD_NAME, MANIFEST_NAME, SPLITS, SPLITS_NAME, ShardError
from seggaussian.shards.read import (find_split, iter_scenes, list_scenes, read_manifest, read_scene, read_scene_cameras,
                                     verify_file)
from seggaussian.shards.records import SceneRecord, ViewCamera, ViewRecord, ViewRow
from seggaussian.shards.schema import GAUSSIANS_TABLE, SCHEMA_VERSION, VIEWS_TABLE
from seggaussian.shards.tables import gaussians_table, table_to_cameras, table_to_gaussians, table_to_views, views_table
from seggaussian.shards.writer import FileInfo, write_dataset

__all__ = [
    "CARD_NAME", "GAUSSIANS_TABLE", "MANIFEST_NAME", "SCHEMA_VERSION", "SPLITS", "SPLITS_NAME", "VIEWS_TABLE",
    "FileInfo", "SceneRecord", "ShardError", "ViewCamera", "ViewRecord", "ViewRow",
    "dataset_card", "decode_label_map", "decode_rgb", "encode_label_map", "encode_rgb", "find_split",
    "gaussians_table", "image_format", "inspect_dataset", "iter_scenes", "list_scenes", "read_footer",
    "read_fragment", "read_manifest", "read_scene", "read_scene_cameras", "sha256_file", "table_to_cameras",
    "table_to_gaussians", "table_to_views",
    "verify_file", "views_table", "write_dataset", "write_parquet_atomic",
]
