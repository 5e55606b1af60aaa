"""Arrow schemas of the two shard tables, versioned. Prose, column by column: ``data_specs/SHARDS.md``.

Bump ``SCHEMA_VERSION`` on any change of a column's name, type or meaning.
"""

from __future__ import annotations

import pyarrow as pa

#: Version of the shard layout (tables, columns, footer keys); written into every Parquet footer.
SCHEMA_VERSION = "1.0"

#: Footer (Parquet key-value metadata) keys.
META_SCHEMA_VERSION = b"seggaussian.schema_version"
META_TABLE = b"seggaussian.table"
META_CLASS_NAMES = b"seggaussian.class_names"
META_CONFIG_HASH = b"seggaussian.config_hash"
META_SPLIT = b"seggaussian.split"

GAUSSIANS_TABLE = "gaussians"
VIEWS_TABLE = "views"

GAUSSIANS_SCHEMA = pa.schema([
    pa.field("scene_id", pa.string(), nullable=False),
    pa.field("means", pa.list_(pa.float32(), 3), nullable=False),
    pa.field("quats", pa.list_(pa.float32(), 4), nullable=False),
    pa.field("log_scales", pa.list_(pa.float32(), 3), nullable=False),
    pa.field("opacity_logit", pa.float32(), nullable=False),
    pa.field("sh_degree", pa.uint8(), nullable=False),
    pa.field("sh", pa.list_(pa.float32()), nullable=False),
    pa.field("semantic", pa.int32(), nullable=False),
    pa.field("instance", pa.int32(), nullable=False),
    pa.field("multilabel", pa.list_(pa.int32(), 3), nullable=False),
    pa.field("transfer_distance", pa.float32(), nullable=False),
])

VIEWS_SCHEMA = pa.schema([
    pa.field("scene_id", pa.string(), nullable=False),
    pa.field("view_name", pa.string(), nullable=False),
    pa.field("role", pa.string(), nullable=False),
    pa.field("width", pa.int32(), nullable=False),
    pa.field("height", pa.int32(), nullable=False),
    pa.field("K", pa.list_(pa.float64(), 9), nullable=False),
    pa.field("viewmat", pa.list_(pa.float64(), 16), nullable=False),
    pa.field("rgb", pa.binary(), nullable=False),
    pa.field("rgb_format", pa.string(), nullable=False),
    pa.field("semantic", pa.binary(), nullable=False),
    pa.field("instance", pa.binary(), nullable=False),
    pa.field("label_coverage", pa.float32(), nullable=False),
])

SCHEMAS = {GAUSSIANS_TABLE: GAUSSIANS_SCHEMA, VIEWS_TABLE: VIEWS_SCHEMA}

#: Columns holding encoded images (``binary``: PNG/JPEG bytes), declared as Hugging Face ``Image`` features in
#: the dataset card (``seggaussian.shards.card``) so ``load_dataset`` decodes them; the shards store them as is.
IMAGE_COLUMNS = {VIEWS_TABLE: ("rgb", "semantic", "instance")}
