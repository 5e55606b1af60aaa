"""The record of a training run in its folder: what config.json holds, whether ``--resume`` may continue it,
and the per-step and per-epoch lines of metrics.jsonl (checkpoints themselves: ``ovgaussian.run.checkpoint``).
"""

from __future__ import annotations

import json
from pathlib import Path

from ovgaussian.run.checkpoint import METRICS_NAME, CheckpointError
from ovgaussian.run.config import TrainConfig, config_from_dict, config_to_dict
from seggaussian.util.atomic import write_text_atomic

#: Config fields that may change between an interrupted run and its ``--resume``.
RESUMABLE_FIELDS = ("epochs", "resume", "stop_after_epochs", "progress", "device", "out", "keep_checkpoints",
                    "threads", "loader_workers", "loader_timeout_s")
#: Per-step metric names (means over the scenes of the global batch).
METRIC_NAMES = ("loss", "text_3d", "text_2d", "cosine")


def run_config_payload(config: TrainConfig, model_config, teacher_width, vocabulary, scan, group, text_width,
                       scored_classes, threads: int) -> dict:
    """What config.json holds (``scored_classes``: the text cross-entropies' columns, seen then unseen names;
    ``threads``: each process's torch and numba threads)."""
    return {
        "train": config_to_dict(config),
        "model": config_to_dict(model_config),
        "text_width": int(text_width),
        "teacher_width": teacher_width,
        "vocabulary": {"num_classes": vocabulary.num_classes, "class_ids": vocabulary.class_ids.tolist(),
                       "names": list(vocabulary.names)},
        "scored_classes": list(scored_classes),
        "data": {"fingerprint": scan.fingerprint, "usable_scenes": len(scan.usable),
                 "scenes": len(scan.summaries), "skipped": scan.skipped},
        "world_size": group.world_size,
        "threads": int(threads),
    }


def changed_settings(saved: dict, config: TrainConfig, free: tuple[str, ...] = RESUMABLE_FIELDS) -> list[str]:
    """The TrainConfig fields (sorted, nested ones by dotted name: ``data.renditions``) on which ``config`` differs
    from a run folder's config.json ``saved``, less ``free``. Through the config type: a field added since the run
    was saved compares at its default."""
    old = _dotted(config_to_dict(config_from_dict(TrainConfig, saved["train"])), free)
    new = _dotted(config_to_dict(config), free)
    return sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))


def _dotted(tree: dict, free: tuple[str, ...], prefix: str = "") -> dict:
    """``{"data.dataset": ..., "epochs": ...}``: the leaves of a nested config dict by dotted name, top-level
    ``free`` fields left out."""
    out = {}
    for key, value in tree.items():
        if not prefix and key in free:
            continue
        if isinstance(value, dict):
            out.update(_dotted(value, free, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def check_resumable(saved: dict, config: TrainConfig, scan, path: Path) -> None:
    """CheckpointError when the run folder was trained with other settings or other data."""
    diff = changed_settings(saved, config)
    if diff:
        raise CheckpointError(f"{path}: --resume with different settings ({', '.join(diff)}); use a new --out")
    if saved["data"]["fingerprint"] != scan.fingerprint:
        raise CheckpointError(f"{path}: --resume on different data (fingerprint changed); use a new --out")


def truncate_metrics(path: Path, keep_epochs_below: int) -> None:
    """Keep only the metric lines of epochs < ``keep_epochs_below`` (atomic rewrite)."""
    if not path.is_file():
        return
    lines = [line for line in path.read_text().splitlines()
             if line.strip() and json.loads(line)["epoch"] < keep_epochs_below]
    write_text_atomic(path, "".join(line + "\n" for line in lines))


def read_metrics(run_dir: Path, kind: str = "step") -> list[dict]:
    """The ``kind`` lines (``step`` or ``epoch``) of a run's metrics.jsonl."""
    path = Path(run_dir) / METRICS_NAME
    return [r for r in (json.loads(line) for line in path.read_text().splitlines() if line.strip())
            if r["kind"] == kind]


def append_metrics(path: Path, record: dict) -> None:
    """Append one line to metrics.jsonl (a run's log: each line complete, earlier lines never rewritten here)."""
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")
