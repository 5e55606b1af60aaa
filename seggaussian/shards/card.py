"""The dataset card (``README.md``): Hugging Face YAML header with one config per table, and a short description.
"""

from __future__ import annotations

from seggaussian.constants import IGNORE_LABEL
from seggaussian.shards.layout import SPLITS
from seggaussian.shards.schema import GAUSSIANS_TABLE, SCHEMA_VERSION, VIEWS_TABLE


def dataset_card(name: str, splits: dict[str, list[str]], class_names, schema_doc: str = "data_specs/SHARDS.md") -> str:
    """README.md with the Hugging Face YAML header (one config per table, data_files per split)."""
    present = [s for s in SPLITS if splits.get(s)]
    lines = ["---", "configs:"]
    for table_name in (GAUSSIANS_TABLE, VIEWS_TABLE):
        lines += [f"- config_name: {table_name}", "  data_files:"]
        for split in present:
            lines += [f"  - split: {split}", f"    path: {table_name}/{split}-*.parquet"]
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
        "```python",
        "from datasets import load_dataset",
        'gaussians = load_dataset("parquet", data_files={"train": "gaussians/train-*.parquet"})',
        "from seggaussian import shards",
        'record = shards.read_scene(".", "train", shards.list_scenes(".", "train")[0])',
        "```",
        "",
    ]
    return "\n".join(lines)
