"""train / val / xval assignment of a dataset's scenes.

Rules (DESIGN.md section 4):
- Replica scenes are the cross-domain set ``xval`` (all of them).
- ScanNet++ scenes listed in the official ``splits/nvs_sem_train.txt`` / ``nvs_sem_val.txt`` of the raw
  tree follow those lists.
- Other ScanNet++ scenes are assigned in a stable order (sha256 of seed + scene id) so that the val share of
  all ScanNet++ scenes approaches ``val / (train + val)`` of the ratios (230/50 -> 17.9 %); for small sets this
  scales down (at least one val scene once there are two ScanNet++ scenes).
- Assignments already recorded in ``splits.json`` never move (unless ``reassign``): adding scenes only assigns
  the new ones, filling whichever of train/val is below its target share.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import NamedTuple

from seggaussian.pipeline.config import SplitConfig

SPLITS_VERSION = 1
REPLICA_DOMAIN = "replica"


class SceneSplitInfo(NamedTuple):
    """What the split needs to know of a scene: its domain and its official split (None if unlisted)."""

    domain: str  # "scannetpp" | "replica" | other (treated like scannetpp)
    official: str | None  # "train" | "val" | None


class SplitResult(NamedTuple):
    """Assignment of every scene: ``assignments[scene] = split``, ``reasons[scene]`` in
    ``kept | official | replica | hash``; ``counts[split]``."""

    assignments: dict
    reasons: dict
    counts: dict


def stable_rank(scene_id: str, seed: int) -> str:
    """Order key of a scene: hex sha256 of ``"{seed}:{scene_id}"`` (stable across runs and machines)."""
    return hashlib.sha256(f"{seed}:{scene_id}".encode()).hexdigest()


def target_val_count(num_scenes: int, ratios) -> int:
    """Val scenes among ``num_scenes`` ScanNet++ scenes: round(n * val / (train + val)), >= 1 once n >= 2,
    and leaving at least one train scene."""
    train, val = ratios[0], ratios[1]
    if num_scenes < 2 or val <= 0:
        return 0
    if train <= 0:
        return num_scenes
    return min(num_scenes - 1, max(1, int(math.floor(num_scenes * val / (train + val) + 0.5))))


def assign_splits(scenes: dict, config: SplitConfig, previous: dict | None = None) -> SplitResult:
    """Assign ``scenes`` (id -> SceneSplitInfo). ``previous`` = id -> split from an earlier splits.json."""
    previous = {} if config.reassign or previous is None else dict(previous)
    assignments: dict[str, str] = {}
    reasons: dict[str, str] = {}
    pending: list[str] = []
    for scene_id in sorted(scenes):
        info = scenes[scene_id]
        if info.domain == REPLICA_DOMAIN:
            assignments[scene_id], reasons[scene_id] = "xval", "replica"
        elif info.official in ("train", "val"):
            assignments[scene_id], reasons[scene_id] = info.official, "official"
        elif previous.get(scene_id) in ("train", "val"):
            assignments[scene_id], reasons[scene_id] = previous[scene_id], "kept"
        else:
            pending.append(scene_id)
    num_scannetpp = sum(1 for s, i in scenes.items() if i.domain != REPLICA_DOMAIN)
    want_val = target_val_count(num_scannetpp, config.ratios)
    have_val = sum(1 for s in assignments if assignments[s] == "val")
    for scene_id in sorted(pending, key=lambda s: stable_rank(s, config.seed)):
        split = "val" if have_val < want_val else "train"
        have_val += split == "val"
        assignments[scene_id], reasons[scene_id] = split, "hash"
    counts = {s: sum(1 for v in assignments.values() if v == s) for s in ("train", "val", "xval")}
    return SplitResult(dict(sorted(assignments.items())), dict(sorted(reasons.items())), counts)


def read_official_lists(root: Path) -> dict[str, str]:
    """scene id -> train|val from ``root/splits/nvs_sem_{train,val}.txt`` (empty when absent)."""
    out: dict[str, str] = {}
    for split in ("train", "val"):
        path = Path(root) / "splits" / f"nvs_sem_{split}.txt"
        if path.is_file():
            for line in path.read_text().splitlines():
                if line.strip():
                    out[line.strip()] = split
    return out


def splits_payload(result: SplitResult, config: SplitConfig) -> dict:
    """The JSON document written to ``splits.json``."""
    return {
        "version": SPLITS_VERSION,
        "ratios": list(config.ratios),
        "seed": config.seed,
        "counts": result.counts,
        "scenes": result.assignments,
        "reasons": result.reasons,
    }


def read_splits(path: Path) -> dict[str, str]:
    """scene -> split of an existing ``splits.json`` (empty when the file does not exist)."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
        return dict(data["scenes"])
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a splits.json written by seggaussian split ({exc})") from None
