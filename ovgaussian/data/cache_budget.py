"""Disk budget of a run folder's caches: at most ``CACHE_BUDGET_FRACTION`` of the dataset's size.

The run folder caches what is expensive and small: the text embeddings of the vocabulary and the MaskCLIP
patch features of each view used (patch resolution, ``ovgaussian.text.teacher``). Blend weights are never
cached: they are computed per step at the sampled pixels (``seggaussian.render.pixel_blend``).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

#: Run-folder caches may take at most this share of the dataset's bytes (issue 17).
CACHE_BUDGET_FRACTION = 0.10
#: Folders of a dataset that are build internals, not part of the published dataset.
DATASET_INTERNAL_FOLDERS = (".build",)


class CacheUsage(NamedTuple):
    """Bytes of a run folder's caches against its dataset.

    Fields:
        cache_bytes: bytes of the files under ``RUN/caches``.
        dataset_bytes: bytes of the dataset's files (shards, manifests), build internals left out.
        by_kind: ``{kind: bytes}`` of the caches, kind = the part of the name before the first ``_``
            (``text``, ``teacher``, ...) of each top-level entry.
    """

    cache_bytes: int
    dataset_bytes: int
    by_kind: dict

    @property
    def fraction(self) -> float:
        return self.cache_bytes / self.dataset_bytes if self.dataset_bytes else float("inf")

    @property
    def within_budget(self) -> bool:
        return self.cache_bytes <= CACHE_BUDGET_FRACTION * self.dataset_bytes


def folder_bytes(path: Path, skip: tuple[str, ...] = ()) -> int:
    """Sum of the sizes of the regular files under ``path`` (0 when it does not exist)."""
    path = Path(path)
    if not path.exists():
        return 0
    return sum(p.stat().st_size for p in path.rglob("*")
               if p.is_file() and not p.is_symlink() and not set(p.relative_to(path).parts) & set(skip))


def run_cache_usage(run_dir: Path, dataset: Path) -> CacheUsage:
    """:class:`CacheUsage` of ``run_dir/caches`` against ``dataset``."""
    caches = Path(run_dir) / "caches"
    by_kind: dict[str, int] = {}
    if caches.is_dir():
        for entry in sorted(caches.iterdir()):
            kind = entry.name.split("_", 1)[0]
            size = entry.stat().st_size if entry.is_file() else folder_bytes(entry)
            by_kind[kind] = by_kind.get(kind, 0) + size
    return CacheUsage(sum(by_kind.values()), folder_bytes(dataset, DATASET_INTERNAL_FOLDERS), by_kind)
