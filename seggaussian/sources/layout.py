"""Raw-tree layout dispatch: which reader reads a raw tree, and where each layout's root lies.

Three on-disk shapes reach the readers:
- a ScanNet++ DATA_ROOT (``ROOT/data/<scene>/...``), read by ``sources.scannetpp``;
- a Replica root (``ROOT/<room>/...``), read by ``sources.replica``;
- a synthetic root as ``seggaussian synth`` writes it, holding ``ROOT/scannetpp`` and/or ``ROOT/replica``
  (each one of the two layouts above), or a single layout root.

Every caller that turns a ``--source`` and a root into (domain, layout root, reader) goes through this
module (one dispatch, not a copy per command).
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

from seggaussian.sources import replica, scannetpp

#: The layouts a raw tree can have (each has one reader module).
DOMAINS = ("scannetpp", "replica")
#: ``--source`` values: a layout, a synthetic root (holding layout folders), or a folder of PLYs beside a layout.
SOURCES = ("synthetic", "scannetpp", "replica", "ply")


def detect_layout(root: Path) -> str:
    """``scannetpp`` when ``root/data`` exists (ScanNet++ layout), else ``replica``."""
    if not Path(root).is_dir():
        raise FileNotFoundError(f"{root}: raw tree does not exist")
    return "scannetpp" if (Path(root) / "data").is_dir() else "replica"


def reader(domain: str) -> ModuleType:
    """The source module of a layout (``list_scenes`` / ``read_scene``)."""
    if domain == "scannetpp":
        return scannetpp
    if domain == "replica":
        return replica
    raise ValueError(f"unknown source domain {domain!r} (expected one of {', '.join(DOMAINS)})")


def layout_roots(source: str, root: Path) -> list[tuple[str, Path]]:
    """(domain, layout root) pairs a ``--source`` reads under ``root``: a synthetic root gives one pair per
    layout folder it holds (``scannetpp/``, ``replica/``), or the root's own layout when it holds none."""
    root = Path(root)
    if source in DOMAINS:
        return [(source, root)]
    if source == "ply":
        return [(detect_layout(root), root)]
    if source == "synthetic":
        pairs = [(d, root / d) for d in DOMAINS if (root / d).is_dir()]
        return pairs or [(detect_layout(root), root)]
    raise ValueError(f"--source must be one of {', '.join(SOURCES)}, got {source!r}")


def source_of_tree(root: Path) -> str:
    """The ``--source`` that reads a whole raw tree: ``synthetic`` for a root holding ``scannetpp/`` or
    ``replica/``, else the root's own layout."""
    root = Path(root)
    if any((root / d).is_dir() for d in DOMAINS):
        return "synthetic"
    return detect_layout(root)


def find_scene_layout(root: Path, scene_id: str) -> tuple[str, Path]:
    """(domain, layout root) of one scene of a synthetic root or of a single layout root: the first of
    ``ROOT/scannetpp``, ``ROOT/replica``, ``ROOT`` (ScanNet++), ``ROOT`` (Replica) that holds ``scene_id``."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: raw tree does not exist")
    candidates = [("scannetpp", root / "scannetpp"), ("replica", root / "replica"),
                  ("scannetpp", root), ("replica", root)]
    for domain, layout_root in candidates:
        where = layout_root / "data" / scene_id if domain == "scannetpp" else layout_root / scene_id
        if where.is_dir() and (domain == "replica" or (layout_root / "data").is_dir()):
            return domain, layout_root
    raise FileNotFoundError(f"{root}: no scene {scene_id!r} (looked in scannetpp/data, replica, data and the root "
                            "itself)")
