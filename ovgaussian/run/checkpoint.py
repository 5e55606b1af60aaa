"""Run-folder checkpoints of OVGaussian training, and loading a trained network.

Layout of a run folder::

    RUN/config.json                      training config, model config, vocabulary, data fingerprint
    RUN/metrics.jsonl                    one JSON line per step and per epoch
    RUN/checkpoints/epoch-0003/          model.safetensors (weights + BN buffers),
                                         optimizer.safetensors (SGD momentum buffers),
                                         state.json (epoch, global step, optimizer hyper-parameters)
    RUN/checkpoints/latest.json          {"epoch": 3, "path": "checkpoints/epoch-0003"}
    RUN/checkpoints/best.json            the same for the epoch of lowest mean training loss so far
    RUN/caches/                          text embeddings, blend weights, teacher features

Every file is written under a temporary name in its folder and renamed; a checkpoint folder is
complete before ``latest.json`` points at it. No pickle: tensors in safetensors, the rest in JSON, written by
``seggaussian.util.atomic.write_json_atomic`` with NaN/Inf refused (``nan=NAN_IS_ERROR``: they must read back).

Retention (``TrainConfig.keep_checkpoints = N``, 0 = off): after each save, the epoch folders other than
the last ``N``, the best and the latest are removed, each by one rename to a temporary name (``seggaussian.util.atomic.
remove_dir_atomic``), after ``latest.json`` and ``best.json`` point at kept folders; a kill at any point
leaves complete checkpoints, pointers to kept folders, and at most a temporary the next run sweeps.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from ovgaussian.model.network import OVGaussianNet
from ovgaussian.model.config import LEGACY_FIELD_VALUES, OVGaussianNetConfig
from ovgaussian.run.config import config_from_dict
from seggaussian.shards.files import sha256_file
from seggaussian.util.atomic import atomic_dir, atomic_path, remove_dir_atomic, sweep_temps, write_json_atomic
from seggaussian.util.jsonsafe import NAN_IS_ERROR

if TYPE_CHECKING:
    import torch

CONFIG_NAME = "config.json"
METRICS_NAME = "metrics.jsonl"
CHECKPOINTS_DIR = "checkpoints"
LATEST_NAME = "latest.json"
BEST_NAME = "best.json"
#: Checkpoint folder names: ``epoch-`` and the zero-padded epoch number (the only folders retention removes).
EPOCH_FOLDER = re.compile(r"^epoch-(\d{4,})$")


class CheckpointError(ValueError):
    """A run folder or checkpoint that cannot be used; the message names the file."""


def read_json(path: Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: missing")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path}: not valid JSON ({error})") from None


def build_network(model_config, teacher_width: int | None = None):
    """``OVGaussianNet(model_config)``; ``psi`` rebuilt with output width ``teacher_width`` when it differs
    from ``model_config.embedding_width`` (text and teacher embeddings of different widths)."""
    import torch
    from torch import nn

    net = OVGaussianNet(model_config)
    if teacher_width is not None and teacher_width != model_config.embedding_width:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(model_config.seed + 1)
            net.psi = nn.Sequential(
                nn.Linear(model_config.semantic_width, model_config.decoder_hidden), nn.ReLU(),
                nn.Linear(model_config.decoder_hidden, teacher_width),
            )
    return net


def save_checkpoint(run_dir: Path, epoch: int, net, optimizer, state: dict) -> Path:
    """Write ``checkpoints/epoch-XXXX`` (weights, momentum, state) then point ``latest.json`` at it."""
    from safetensors.torch import save_file

    run_dir = Path(run_dir)
    folder = run_dir / CHECKPOINTS_DIR / f"epoch-{epoch:04d}"
    with atomic_dir(folder) as tmp:
        weights = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
        with atomic_path(tmp / "model.safetensors") as path:
            save_file(weights, str(path))
        opt_state = optimizer.state_dict()
        buffers = {}
        for index, entry in opt_state["state"].items():
            for name, value in entry.items():
                if hasattr(value, "detach"):
                    buffers[f"{index}.{name}"] = value.detach().cpu().contiguous()
        with atomic_path(tmp / "optimizer.safetensors") as path:
            save_file(buffers, str(path))
        groups = [{k: v for k, v in g.items()} for g in opt_state["param_groups"]]
        write_json_atomic(tmp / "state.json", dict(state, epoch=epoch, param_groups=groups), nan=NAN_IS_ERROR)
    write_json_atomic(run_dir / CHECKPOINTS_DIR / LATEST_NAME,
                      {"epoch": epoch, "path": str(folder.relative_to(run_dir))}, nan=NAN_IS_ERROR)
    return folder


def weights_sha256(checkpoint: Path | None) -> str | None:
    """sha256 of a checkpoint folder's ``model.safetensors`` (what bench reports record of the weights they scored);
    None without a folder or weights."""
    weights = None if checkpoint is None else Path(checkpoint) / "model.safetensors"
    return sha256_file(weights) if weights is not None and weights.is_file() else None


def checkpoint_folders(run_dir: Path) -> dict[int, Path]:
    """``{epoch: folder}`` of the run's complete checkpoint folders (those holding ``state.json``)."""
    root = Path(run_dir) / CHECKPOINTS_DIR
    folders = {}
    if root.is_dir():
        for entry in root.iterdir():
            match = EPOCH_FOLDER.match(entry.name)
            if match and entry.is_dir() and (entry / "state.json").is_file():
                folders[int(match.group(1))] = entry
    return folders


def epoch_loss(folder: Path) -> float:
    """The mean training loss of the checkpoint's epoch (``state.json`` metrics), +inf when it has none."""
    loss = read_json(Path(folder) / "state.json").get("metrics", {}).get("loss")
    return float(loss) if isinstance(loss, (int, float)) and math.isfinite(loss) else math.inf


def retain_checkpoints(run_dir: Path, keep_last: int) -> list[Path]:
    """Point ``best.json`` at the epoch of lowest training loss (ties: the earliest), then remove every
    epoch folder but the last ``keep_last``, the best and the latest (``0``: remove none). Returns the
    removed folders.

    Only complete ``epoch-NNNN`` folders are considered; ``latest.json`` must already point at the newest.
    """
    if keep_last < 0:
        raise ValueError(f"keep_last must be 0 (keep every folder) or more, got {keep_last}")
    run_dir = Path(run_dir)
    folders = checkpoint_folders(run_dir)
    if not folders:
        return []
    best = min(folders, key=lambda epoch: (epoch_loss(folders[epoch]), epoch))
    pointer = {"epoch": best, "path": str(folders[best].relative_to(run_dir)), "loss": epoch_loss(folders[best])}
    best_path = run_dir / CHECKPOINTS_DIR / BEST_NAME
    if not math.isfinite(pointer["loss"]):
        pointer["loss"] = None
    if not best_path.is_file() or read_json(best_path) != pointer:
        write_json_atomic(best_path, pointer, nan=NAN_IS_ERROR)
    if keep_last == 0:
        return []
    kept = set(sorted(folders)[-keep_last:]) | {best}
    latest = latest_checkpoint(run_dir)
    if latest is not None and EPOCH_FOLDER.match(latest.name):
        kept.add(int(EPOCH_FOLDER.match(latest.name).group(1)))  # never the one resume would load
    removed = []
    for epoch in sorted(set(folders) - kept):
        if remove_dir_atomic(folders[epoch]):
            removed.append(folders[epoch])
    return removed


def sweep_run_temps(run_dir: Path) -> int:
    """Remove temporaries (half-written checkpoint folders, JSON, caches) a killed run left in ``run_dir``."""
    return sweep_temps(run_dir, recursive=True)


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The folder ``latest.json`` points at, or None when the run has no checkpoint."""
    pointer = Path(run_dir) / CHECKPOINTS_DIR / LATEST_NAME
    if not pointer.is_file():
        return None
    folder = Path(run_dir) / read_json(pointer)["path"]
    if not (folder / "model.safetensors").is_file():
        raise CheckpointError(f"{pointer}: points at {folder}, which has no model.safetensors")
    return folder


def load_checkpoint(folder: Path, net, optimizer=None, device: "str | torch.device" = "cpu") -> dict:
    """Load weights (and momentum buffers) into ``net`` (and ``optimizer``); returns state.json."""
    from safetensors.torch import load_file

    folder = Path(folder)
    weights = load_file(str(folder / "model.safetensors"), device=str(device))
    missing, unexpected = net.load_state_dict(weights, strict=False)
    if missing or unexpected:
        raise CheckpointError(f"{folder / 'model.safetensors'}: does not match the network "
                              f"(missing {missing[:5]}, unexpected {unexpected[:5]})")
    state = read_json(folder / "state.json")
    if optimizer is not None:
        buffers = load_file(str(folder / "optimizer.safetensors"), device=str(device))
        per_param: dict[int, dict] = {}
        for key, value in buffers.items():
            index, name = key.split(".", 1)
            per_param.setdefault(int(index), {})[name] = value
        optimizer.load_state_dict({"state": per_param, "param_groups": state["param_groups"]})
    return state


class TrainedModel(NamedTuple):
    """A trained network and what is needed to use it.

    Fields:
        net: ``OVGaussianNet`` in eval mode.
        run_config: the run's config.json.
        checkpoint: the checkpoint folder loaded.
        seen_class_ids: top-100 ids of the training vocabulary (seen classes).
    """

    net: object
    run_config: dict
    checkpoint: Path
    seen_class_ids: list


def saved_model_config(payload: dict) -> OVGaussianNetConfig:
    """The network config a run folder saved: fields added since it was written take the values that run was
    trained with (``LEGACY_FIELD_VALUES``), not today's defaults, so an old run loads and predicts as before."""
    return config_from_dict(OVGaussianNetConfig, {**LEGACY_FIELD_VALUES, **payload})


def load_trained_model(run_dir: Path, checkpoint: Path | None = None, device: str = "cpu") -> TrainedModel:
    """The network of a run (latest checkpoint unless ``checkpoint`` is given), ready for inference.

    Text embeddings of any vocabulary come from ``ovgaussian.text.encoders.encode_texts(names, text_config)``
    with ``text_config = config_from_dict(TextConfig, run_config["train"]["text"])``.
    """
    run_dir = Path(run_dir)
    run_config = read_json(run_dir / CONFIG_NAME)
    folder = Path(checkpoint) if checkpoint is not None else latest_checkpoint(run_dir)
    if folder is None:
        raise CheckpointError(f"{run_dir / CHECKPOINTS_DIR}: no checkpoint (train first)")
    model_config = saved_model_config(run_config["model"])
    net = build_network(model_config, run_config.get("teacher_width"))
    load_checkpoint(folder, net, device=device)
    net.to(device).eval()
    return TrainedModel(net, run_config, folder, list(run_config["vocabulary"]["class_ids"]))
