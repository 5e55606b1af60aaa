"""Class lists, benchmark vocabularies and the Replica -> ScanNet++ top-100 mapping (read from data_specs/).

Class id = index into ``data_specs/top100.txt`` (0 = wall). The data files are described in
``data_specs/README.md``; this module only reads and checks them.
"""

from __future__ import annotations

import json
from pathlib import Path

from seggaussian.core.constants import DATA_SPECS_DIR, UNSEEN_CLASSES, read_class_names

__all__ = [
    "class_names",
    "class_id",
    "unseen_class_ids",
    "benchmark_vocabulary",
    "benchmark_vocabulary_names",
    "VOCABULARY_SIZES",
    "replica_class_names",
    "replica_class_to_top100",
    "is_replica_class",
    "replica_class_id_to_top100",
    "replica_common_class_ids",
]

#: Vocabulary sizes of the benchmark (paper, section 4).
VOCABULARY_SIZES = (20, 50, 100)


def _read_json(name: str, data_dir: Path | None) -> dict:
    path = (data_dir or DATA_SPECS_DIR) / name
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the data file ({exc})") from None


def class_names(data_dir: Path | None = None) -> tuple[str, ...]:
    """ScanNet++ benchmark class names; class id = position."""
    return read_class_names((data_dir or DATA_SPECS_DIR) / "top100.txt")


def class_id(name: str, data_dir: Path | None = None) -> int:
    """Class id of a top-100 class name; ``KeyError`` naming the class otherwise."""
    names = class_names(data_dir)
    try:
        return names.index(name)
    except ValueError:
        raise KeyError(f"{name!r} is not a class of top100.txt") from None


def unseen_class_ids(data_dir: Path | None = None) -> list[int]:
    """Ids of the four unseen classes (never supervised in training), ascending."""
    return sorted(class_id(name, data_dir) for name in UNSEEN_CLASSES)


def benchmark_vocabulary_names(num_classes: int, data_dir: Path | None = None) -> list[str]:
    """Class names of the ``num_classes``-class benchmark vocabulary, in top100.txt order (from vocabularies.json)."""
    doc = _read_json("vocabularies.json", data_dir)
    vocabularies = doc.get("vocabularies", {})
    if str(num_classes) not in vocabularies:
        raise ValueError(f"no benchmark vocabulary of {num_classes} classes; available: {sorted(map(int, vocabularies))}")
    if tuple(doc.get("unseen", ())) != UNSEEN_CLASSES:
        raise ValueError(f"vocabularies.json: unseen classes {doc.get('unseen')} differ from {UNSEEN_CLASSES}")
    names = list(vocabularies[str(num_classes)])
    if len(names) != num_classes or len(set(names)) != num_classes:
        raise ValueError(f"vocabularies.json: vocabulary {num_classes} has {len(set(names))} distinct names, "
                         f"expected {num_classes}")
    return names


def benchmark_vocabulary(num_classes: int, data_dir: Path | None = None) -> list[int]:
    """Class ids (ascending) of the ``num_classes``-class vocabulary: the 4 unseen classes + the
    ``num_classes - 4`` first others."""
    names = benchmark_vocabulary_names(num_classes, data_dir)
    ids = sorted(class_id(name, data_dir) for name in names)
    return ids


def _replica_mapping(data_dir: Path | None) -> dict:
    doc = _read_json("replica_to_top100.json", data_dir)
    mapping = doc.get("mapping")
    if not isinstance(mapping, dict):
        raise ValueError("replica_to_top100.json: no 'mapping' object")
    return mapping


def _normalize_replica_name(name: str) -> str:
    return name.strip().lower().replace(" ", "-")


def replica_class_names(data_dir: Path | None = None) -> tuple[str, ...]:
    """The 101 Replica class names; Replica class id = position + 1 (info_semantic.json ``classes``)."""
    return tuple(_replica_mapping(data_dir))


def replica_class_to_top100(name: str, data_dir: Path | None = None) -> int | None:
    """Top-100 class id of a Replica class name (``tv-screen`` or ``tv screen``), or None when it has no
    counterpart or is not one of the 101 Replica classes (``is_replica_class`` tells the two apart)."""
    target = _replica_mapping(data_dir).get(_normalize_replica_name(name))
    return None if target is None else class_id(target["top100"], data_dir)


def is_replica_class(name: str, data_dir: Path | None = None) -> bool:
    """True for one of the 101 Replica class names (``-`` or spaces)."""
    return _normalize_replica_name(name) in _replica_mapping(data_dir)


def replica_class_id_to_top100(replica_class_id: int, data_dir: Path | None = None) -> int | None:
    """Top-100 class id of a Replica class id (1..101), or None; negative ids (void) give None."""
    names = replica_class_names(data_dir)
    if replica_class_id < 1:
        return None
    if replica_class_id > len(names):
        raise KeyError(f"Replica class id {replica_class_id} is outside 1..{len(names)}")
    return replica_class_to_top100(names[replica_class_id - 1], data_dir)


def replica_common_class_ids(data_dir: Path | None = None) -> list[int]:
    """Ascending top-100 ids reached by some Replica class: the classes scored by CDA."""
    ids = {replica_class_to_top100(name, data_dir) for name in replica_class_names(data_dir)}
    return sorted(i for i in ids if i is not None)
