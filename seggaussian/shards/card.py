"""The dataset card (``README.md``): Hugging Face YAML header with one config per table and each config's
column types (``dataset_info: features``), and a short description.

The ``features`` make ``datasets.load_dataset(DATASET, "views")`` decode the image columns (``rgb``,
``semantic``, ``instance``) into ``PIL.Image`` objects: ``datasets`` casts a plain ``binary`` column to its
``Image`` feature when the card declares one, so the shards keep their ``binary`` columns (the Parquet schema's
own ``huggingface`` metadata would need the ``struct<bytes, path>`` storage instead). The features are derived
from the Arrow schemas, so the card and the shards cannot disagree.
"""

from __future__ import annotations

import pyarrow as pa

from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.shards.layout import SPLITS
from seggaussian.shards.schema import GAUSSIANS_TABLE, IMAGE_COLUMNS, SCHEMA_VERSION, SCHEMAS, VIEWS_TABLE

#: Arrow scalar types -> Hugging Face ``Value`` dtype names.
_DTYPES = {
    pa.string(): "string", pa.binary(): "binary", pa.bool_(): "bool",
    pa.int8(): "int8", pa.int16(): "int16", pa.int32(): "int32", pa.int64(): "int64",
    pa.uint8(): "uint8", pa.uint16(): "uint16", pa.uint32(): "uint32", pa.uint64(): "uint64",
    pa.float32(): "float32", pa.float64(): "float64",
}


def _dtype(t: pa.DataType) -> str:
    if t not in _DTYPES:
        raise ValueError(f"no Hugging Face dtype for Arrow type {t}")
    return _DTYPES[t]


def feature_lines(table_name: str) -> list[str]:
    """YAML lines (``- name: ...`` entries, unindented) of the ``features`` of one table.

    Lists use the ``sequence`` form (``length`` for fixed-size lists), which every ``datasets`` from 2.18 on
    reads (5.x maps it to ``List``); the image columns of a table are ``dtype: image``.
    """
    lines = []
    images = IMAGE_COLUMNS.get(table_name, ())
    for field in SCHEMAS[table_name]:
        lines.append(f"- name: {field.name}")
        t = field.type
        if field.name in images:
            if t != pa.binary():
                raise ValueError(f"image column {table_name}.{field.name} is {t}, expected binary")
            lines.append("  dtype: image")
        elif isinstance(t, pa.FixedSizeListType):
            lines += [f"  sequence: {_dtype(t.value_type)}", f"  length: {t.list_size}"]
        elif isinstance(t, pa.ListType):
            lines.append(f"  sequence: {_dtype(t.value_type)}")
        else:
            lines.append(f"  dtype: {_dtype(t)}")
    return lines


def dataset_card(name: str, splits: dict[str, list[str]], class_names, schema_doc: str = "data_specs/SHARDS.md") -> str:
    """README.md with the Hugging Face YAML header (one config per table, data_files per split, features)."""
    present = [s for s in SPLITS if splits.get(s)]
    lines = ["---", "configs:"]
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
        lines += [f"- config_name: {table_name}", "  data_files:"]
        for split in present:
            lines += [f"  - split: {split}", f"    path: {table_name}/{split}-*.parquet"]
    lines.append("dataset_info:")
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
        lines += [f"- config_name: {table_name}", "  features:"]
        lines += ["  " + line for line in feature_lines(table_name)]
    lines += ["tags:", "- 3d-gaussian-splatting", "- semantic-segmentation", "---", ""]
    lines += [
        f"# {name}",
        "",
        "Labelled 3D Gaussian Splatting scenes built by `seggaussian build` (SegGaussian). Each Gaussian carries",
        "the semantic class (index into the ScanNet++ top-100 list), instance id and label-transfer distance of",
        "its nearest labelled point; each view carries its camera, RGB and rendered semantic/instance maps.",
        f"Schema version {SCHEMA_VERSION}, documented column by column in `{schema_doc}`.",
        "",
        "| split | scenes |",
        "|---|---|",
    ]
    for split in SPLITS:
        lines.append(f"| {split} | {len(splits.get(split, []))} |")
    lines += [
        "",
        f"Ignore label: {IGNORE_LABEL}. Classes ({len(class_names)}): " + ", ".join(class_names) + ".",
        "",
        "Images: in the `views` config, `rgb` (8-bit RGB, PNG or the source's JPEG) and the label maps `semantic`",
        f"and `instance` (16-bit single-channel PNG, mode `I;16`, {IGNORE_LABEL} = ignore) are `Image` features:",
        "`load_dataset` returns `PIL.Image` objects (`numpy.asarray(image)` gives the ids as uint16). The Parquet",
        "columns hold the encoded bytes (`binary`); loading the files without this card",
        '(`load_dataset("parquet", data_files=...)`) returns those bytes.',
        "",
        "```python",
        "from datasets import load_dataset",
        'views = load_dataset(".", "views")          # rgb, semantic, instance: PIL images',
        'gaussians = load_dataset(".", "gaussians")  # one row per Gaussian',
        "from seggaussian import shards",
        'record = shards.read_scene(".", "train", shards.list_scenes(".", "train")[0])',
        "```",
        "",
    ]
    return "\n".join(lines)
