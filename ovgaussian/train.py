"""OVGaussian training: GSR (semantic rasterization M = W S) + CCL losses, SGD, checkpoints, torchrun.

One step (global batch of ``batch_scenes`` scenes, one train view each):

1. every process takes its contiguous slice of the batch (``data.rank_slice``) and draws each scene's
   view, augmentation and pixels from a generator seeded by (seed, epoch, step, scene id), so the
   draws do not depend on the number of processes;
2. the network maps the concatenated scenes to semantic vectors ``s [N, 16]``;
3. per scene: 3D-to-text CE on ``phi(s)``; ``M = render_features(W, s)`` at the sampled pixels;
   2D-to-text CE on ``phi(M)``; cosine loss of ``psi(M)`` against the MaskCLIP teacher on covered pixels;
4. the batch loss is the mean of the scene losses over the *global* batch. With several processes
   (torchrun; gloo on CPU, NCCL on CUDA) each rank back-propagates its share and the gradients are
   summed over ranks with one all-reduce (what DistributedDataParallel's reducer does; done by hand so
   that ablations leaving a decoder unused need no ``find_unused_parameters``), and batch-norm
   statistics are synchronized over ranks (differentiable all-reduce), so P processes compute the same
   step as one process up to float rounding;
5. SGD (momentum) with a learning rate decayed per step (cosine or poly), gradient-norm clipping.

The last incomplete batch of an epoch is dropped (the global batch is fixed); a split with fewer usable
scenes than ``batch_scenes`` trains on all of them per step. Scenes that are empty, have no train view
or are all-ignore are skipped and counted (``TrainResult.skipped``, config.json).

Determinism: the model initialization, scene order, views, augmentations and pixels follow the seed;
``--resume`` restores weights, momentum, batch-norm buffers and the step counter from the last
epoch checkpoint, and the epoch-indexed generators make the continued run identical to an
uninterrupted one.
"""

from __future__ import annotations

import json
import logging
import math
import os
import types
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np

from ovgaussian.checkpoint import (
    CONFIG_NAME, METRICS_NAME, CheckpointError, build_network, latest_checkpoint, load_checkpoint, read_json,
    save_checkpoint, sweep_run_temps, write_json_atomic,
)
from ovgaussian.data import (
    InMemorySource, SceneSample, ShardSource, TrainingData, epoch_batches, rank_slice, training_vocabulary,
    sample_seed, scan_scenes,
)
from ovgaussian.cache_budget import CACHE_BUDGET_FRACTION, DATASET_INTERNAL_FOLDERS, folder_bytes
from ovgaussian.train_config import TrainConfig, config_from_dict, config_to_dict
from seggaussian.atomic import ensure_writable_dir, make_dirs, write_text_atomic
from seggaussian.constants import IGNORE_LABEL

if TYPE_CHECKING:
    import torch

LOG = logging.getLogger("ovgaussian.train")

#: A pixel takes part in the cosine loss when its kept blend weights sum to at least this (the rendered
#: semantic vector is then mostly made of Gaussians, not of the empty background).
COVERAGE_MIN = 0.5
#: Exponent of the polynomial learning-rate decay (``lr * (1 - t)^power``).
POLY_POWER = 0.9
#: Config fields that may change between an interrupted run and its ``--resume``.
RESUMABLE_FIELDS = ("epochs", "resume", "stop_after_epochs", "progress", "device", "out")
#: Per-step metric names (means over the scenes of the global batch).
METRIC_NAMES = ("loss", "text_3d", "text_2d", "cosine")


class TrainResult(NamedTuple):
    """Outcome of :func:`train`.

    Fields:
        run_dir: the run folder.
        epochs: epochs completed (including those of a resumed run).
        steps: optimizer steps completed.
        last_epoch_metrics: mean metrics of the last epoch (``loss``, ``text_3d``, ``text_2d``, ``cosine``).
        skipped: ``{reason: count}`` of scenes not trained on.
        num_scenes: usable scenes.
        checkpoint: the last checkpoint folder.
        notes: things the user should know (loss switched off, batch clamped, ...).
    """

    run_dir: Path
    epochs: int
    steps: int
    last_epoch_metrics: dict
    skipped: dict
    num_scenes: int
    checkpoint: Path | None
    notes: tuple[str, ...]


class ProcessGroup(NamedTuple):
    """This process's place among the torchrun processes (rank 0 of 1 without torchrun)."""

    rank: int
    world_size: int


# --- schedule ----------------------------------------------------------------------------------


def learning_rate(step: int, total_steps: int, base_lr: float, schedule: str) -> float:
    """Learning rate of optimizer step ``step`` (0-based) out of ``total_steps``."""
    if schedule == "constant" or total_steps <= 0:
        return base_lr
    t = min(max(step / total_steps, 0.0), 1.0)
    if schedule == "cosine":
        return base_lr * 0.5 * (1.0 + math.cos(math.pi * t))
    if schedule == "poly":
        return base_lr * (1.0 - t) ** POLY_POWER
    raise ValueError(f"unknown learning-rate schedule {schedule!r} (cosine, poly or constant)")


# --- model -------------------------------------------------------------------------------------


def make_model_config(config: TrainConfig, text_width: int):
    """The network config of the preset, with ``embedding_width`` = text width and the adapter switch."""
    from ovgaussian.model_config import OVGaussianNetConfig

    fields = dict(embedding_width=int(text_width), use_adapter=config.use_adapter, seed=config.seed)
    if config.model_preset == "slim":
        return OVGaussianNetConfig.slim(**fields)
    if config.model_preset == "default":
        return OVGaussianNetConfig(**fields)
    raise ValueError(f"unknown model preset {config.model_preset!r} (default or slim)")


def check_text_space(config: TrainConfig) -> None:
    """ValueError (one line) when the teacher and the text encoder would live in two embedding spaces.

    The cosine loss trains psi towards the teacher's CLIP image space while phi, the head that scores,
    is trained against the text embeddings: open-vocabulary transfer from the teacher needs both to be
    the same CLIP's. A teacher (``teacher.clip_model`` with the loss on) therefore requires
    ``text.encoder == "clip"`` with the same ``clip_model``.
    """
    teacher_model = config.teacher.clip_model
    if teacher_model is None or config.loss.no_vs_align:
        return
    if config.text.encoder != "clip":
        raise ValueError(f"the MaskCLIP teacher ({teacher_model}) is in CLIP space but the class names would be "
                         f"encoded by {config.text.encoder!r}: pass --text-encoder clip (same --clip-model) "
                         "or --no-vs-align")
    if config.text.clip_model is None or Path(config.text.clip_model) != Path(teacher_model):
        raise ValueError(f"the MaskCLIP teacher ({teacher_model}) and the CLIP text encoder "
                         f"({config.text.clip_model}) must be the same model")


# --- losses of one step ----------------------------------------------------------------------------


def network_inputs(samples: Sequence[SceneSample], device) -> tuple["torch.Tensor", "torch.Tensor", "torch.Tensor"]:
    """Concatenated ``means [N, 3]``, ``attributes [N, 11]`` and ``batch_index [N]`` of the scenes."""
    import torch

    from ovgaussian.model import gaussian_attributes

    means = torch.cat([s.means for s in samples])
    attributes = gaussian_attributes({
        "quats": torch.cat([s.quats for s in samples]),
        "log_scales": torch.cat([s.log_scales for s in samples]),
        "opacity_logits": torch.cat([s.opacity_logits for s in samples]),
        "sh": torch.cat([s.sh_dc for s in samples])[:, None, :],
    })
    batch_index = torch.cat([torch.full((len(s.means),), i, dtype=torch.int64) for i, s in enumerate(samples)])
    return means.to(device), attributes.to(device), batch_index.to(device)


def render_pixels(
    pixel_ids: "torch.Tensor",  # [P, K]
    pixel_weights: "torch.Tensor",  # [P, K]
    semantic: "torch.Tensor",  # [N, S]
) -> "torch.Tensor":  # [P, S]
    """``M = W S`` at the sampled pixels, through ``seggaussian.render.render_features`` (a P x 1 image)."""
    import torch

    from seggaussian.render import BlendWeights, render_features

    blend = BlendWeights(pixel_ids[:, None, :], pixel_weights[:, None, :],
                         torch.zeros(pixel_ids.shape[0], 1, device=pixel_ids.device))
    return render_features(blend, semantic)[:, 0]


def render_pixels_reference(pixel_ids, pixel_weights, semantic):
    """Slow reference of :func:`render_pixels`: one pixel and one contributor at a time."""
    import torch

    out = torch.zeros(pixel_ids.shape[0], semantic.shape[1], dtype=semantic.dtype)
    for p in range(pixel_ids.shape[0]):
        for k in range(pixel_ids.shape[1]):
            gid = int(pixel_ids[p, k])
            if gid >= 0:
                out[p] = out[p] + pixel_weights[p, k] * semantic[gid]
    return out


def decoded_text_logits(
    phi,
    semantic: "torch.Tensor",  # [N, S]
    text_embeddings: "torch.Tensor",  # [C, D]
    temperature: float,
) -> "torch.Tensor":  # [N, C]
    """``compute_text_logits(phi(semantic), text_embeddings, temperature)`` without phi's ``[N, D]`` output.

    For ``phi = Linear(W2, b2) o ReLU o Linear``, with ``h`` the ``[N, H]`` hidden rows and ``t`` the unit text
    rows: ``phi(s) . t = h (W2^T t^T) + b2 . t`` and ``|phi(s)|^2 = h G h^T + 2 h (W2^T b2) + |b2|^2`` with
    ``G = W2^T W2 [H, H]``: ``H (H + C)`` multiply-adds per row instead of ``H D`` (128 x 144 vs 128 x 384),
    and no ``[N, D]`` activation. Any other ``phi`` takes the direct expression (the reference).
    """
    import torch

    from ovgaussian.losses import COSINE_NORM_EPS, compute_text_logits, normalize_rows

    layers = list(phi) if isinstance(phi, torch.nn.Sequential) else []
    if not (len(layers) == 3 and isinstance(layers[0], torch.nn.Linear) and isinstance(layers[1], torch.nn.ReLU)
            and isinstance(layers[2], torch.nn.Linear) and layers[2].bias is not None):
        return compute_text_logits(phi(semantic), text_embeddings, temperature)
    if temperature <= 0:
        raise ValueError(f"temperature must be positive, got {temperature}")
    hidden = layers[1](layers[0](semantic))  # [N, H]
    w2, b2 = layers[2].weight, layers[2].bias  # [D, H], [D]
    text = normalize_rows(text_embeddings)  # [C, D]
    dots = hidden @ (w2.T @ text.T) + (text @ b2)[None, :]  # [N, C]
    squared = ((hidden @ (w2.T @ w2)) * hidden).sum(1) + 2.0 * (hidden @ (w2.T @ b2)) + b2.square().sum()
    norms = squared.clamp_min(0.0).sqrt().clamp_min(COSINE_NORM_EPS)
    return dots / norms[:, None] / temperature


def text_cross_entropy_3d(
    phi,
    semantic: "torch.Tensor",  # [N, S] semantic vectors of the labelled Gaussians
    labels: "torch.Tensor",  # [N] seen-class index
    text_embeddings: "torch.Tensor",  # [C, D]
    temperature: float,
) -> tuple["torch.Tensor", int]:
    """3D-to-text cross-entropy (mean over the rows, count): ``masked_cross_entropy`` of
    ``compute_text_logits(phi(semantic))``, over row chunks under activation checkpointing
    (``ovgaussian.model.checkpointed_rows``): phi's ``[N, D]`` output is never held whole."""
    from ovgaussian.losses import masked_cross_entropy
    from ovgaussian.model import checkpointed_rows

    def chunk_sum(rows, rows_labels):
        mean, count = masked_cross_entropy(decoded_text_logits(phi, rows, text_embeddings, temperature), rows_labels)
        return mean * count

    count = int((labels != IGNORE_LABEL).sum())
    sums = checkpointed_rows(chunk_sum, semantic, labels)
    total = sum(sums)
    return (total * 0.0, 0) if count == 0 else (total / count, count)


def scene_losses(net, semantic: "torch.Tensor", sample: SceneSample, text_embeddings: "torch.Tensor",
                 config: TrainConfig, use_teacher: bool):
    """:class:`ovgaussian.losses.LossTerms` of one scene from its semantic vectors ``[N, S]``."""
    import torch

    from ovgaussian.losses import (
        combine_losses, compute_text_logits, masked_cosine_loss, masked_cross_entropy,
    )

    device = semantic.device
    temperature = config.loss.temperature
    labels = sample.labels.to(device)
    valid3 = labels != IGNORE_LABEL
    if config.loss.no_3dt_align:
        text_3d = (semantic.sum() * 0.0, 0)
    else:
        text_3d = text_cross_entropy_3d(net.phi, semantic[valid3], labels[valid3], text_embeddings, temperature)
    pixel_ids, pixel_weights = sample.pixel_ids.to(device), sample.pixel_weights.to(device)
    rendered = render_pixels(pixel_ids, pixel_weights, semantic)  # [P, S]
    pixel_labels = sample.pixel_labels.to(device)
    valid2 = pixel_labels != IGNORE_LABEL
    logits2 = compute_text_logits(net.phi(rendered[valid2]), text_embeddings, temperature)
    text_2d = masked_cross_entropy(logits2, pixel_labels[valid2])
    cosine = None
    if use_teacher and sample.teacher is not None:
        covered = (pixel_weights * (pixel_ids >= 0)).sum(-1) >= COVERAGE_MIN
        predicted = net.psi(rendered[covered])
        cosine = masked_cosine_loss(predicted, sample.teacher.to(device)[covered],
                                    torch.ones(predicted.shape[0], dtype=torch.bool, device=device))
    return combine_losses(text_3d, text_2d, cosine, no_3dt_align=config.loss.no_3dt_align,
                          no_vs_align=config.loss.no_vs_align, cosine_weight=config.loss.cosine_weight)


def batch_losses(net, samples: Sequence[SceneSample], text_embeddings, config: TrainConfig, use_teacher: bool,
                 device) -> list:
    """LossTerms of each scene of this process's slice (one network forward for all of them)."""
    means, attributes, batch_index = network_inputs(samples, device)
    semantic = net(means, attributes, batch_index)
    terms, start = [], 0
    for sample in samples:
        n = len(sample.means)
        terms.append(scene_losses(net, semantic[start:start + n], sample, text_embeddings, config, use_teacher))
        start += n
    return terms


# --- several processes ---------------------------------------------------------------------------


def init_process_group(device: str) -> ProcessGroup:
    """Join the torchrun processes (env ``WORLD_SIZE`` > 1): gloo on CPU, NCCL on CUDA."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return ProcessGroup(0, 1)
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device == "cuda" else "gloo")
    return ProcessGroup(dist.get_rank(), dist.get_world_size())


def _synchronized_batch_norm_forward(module, x):
    """SparseBatchNorm forward with statistics over the rows of every process (two-pass, differentiable)."""
    import torch
    import torch.distributed.nn.functional as dist_fn

    from ovgaussian.sparse.voxelize import SparseVoxels

    if not module.training:
        return module._local_forward(x)
    features = x.features
    channels = features.shape[1]
    head = torch.cat([features.sum(0), features.new_tensor([float(features.shape[0])])])
    head = dist_fn.all_reduce(head)
    count = head[channels]
    mean = head[:channels] / count
    centred = features - mean
    sum_sq = dist_fn.all_reduce(centred.square().sum(0))
    var = sum_sq / count
    out = centred * torch.rsqrt(var + module.eps) * module.weight + module.bias
    with torch.no_grad():
        module.running_mean.mul_(1 - module.momentum).add_(module.momentum * mean)
        if float(count) > 1:
            module.running_var.mul_(1 - module.momentum).add_(module.momentum * var * count / (count - 1))
    return SparseVoxels(out, x.sites)


def synchronize_batch_norms(net) -> int:
    """Make every ``SparseBatchNorm`` of ``net`` use statistics over all processes; returns how many."""
    from ovgaussian.sparse import SparseBatchNorm

    count = 0
    for module in net.modules():
        if isinstance(module, SparseBatchNorm):
            module._local_forward = module.forward
            module.forward = types.MethodType(_synchronized_batch_norm_forward, module)
            count += 1
    return count


def sum_gradients(net) -> None:
    """All-reduce (sum) the gradients of every parameter over the processes, in one flat buffer."""
    import torch
    import torch.distributed as dist

    params = [p for p in net.parameters() if p.requires_grad]
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    flat = torch.cat([p.grad.reshape(-1) for p in params])
    dist.all_reduce(flat)
    offset = 0
    for p in params:
        n = p.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p))
        offset += n


def reduce_sums(values: Sequence[float], group: ProcessGroup, device="cpu") -> list[float]:
    """Element-wise sum of float64 values over the processes (on ``device``: NCCL needs CUDA tensors)."""
    if group.world_size == 1:
        return list(values)
    import torch
    import torch.distributed as dist

    t = torch.tensor(list(values), dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.tolist()


# --- run folder ------------------------------------------------------------------------------------


def run_config_payload(config: TrainConfig, model_config, teacher_width, vocabulary, scan, group, text_width) -> dict:
    """What config.json holds."""
    return {
        "train": config_to_dict(config),
        "model": config_to_dict(model_config),
        "text_width": int(text_width),
        "teacher_width": teacher_width,
        "vocabulary": {"num_classes": vocabulary.num_classes, "class_ids": vocabulary.class_ids.tolist(),
                       "names": list(vocabulary.names)},
        "data": {"fingerprint": scan.fingerprint, "usable_scenes": len(scan.usable),
                 "scenes": len(scan.summaries), "skipped": scan.skipped},
        "world_size": group.world_size,
    }


def check_resumable(saved: dict, config: TrainConfig, scan, path: Path) -> None:
    """CheckpointError when the run folder was trained with other settings or other data."""
    old = {k: v for k, v in saved["train"].items() if k not in RESUMABLE_FIELDS}
    new = {k: v for k, v in config_to_dict(config).items() if k not in RESUMABLE_FIELDS}
    if old != new:
        diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
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


# --- the loop ------------------------------------------------------------------------------------


def train(config: "TrainConfig", **kwargs) -> "TrainResult":
    """Train (or resume) a run; see ``train_in_process_group`` for the arguments.

    Under torchrun, the process group this call creates is destroyed when it returns or fails: a gloo group
    left alive at interpreter exit can abort the process ("terminate called without an active exception").
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    owns_group = False
    if world_size > 1:
        import torch.distributed as dist

        owns_group = not dist.is_initialized()
    try:
        return train_in_process_group(config, **kwargs)
    finally:
        if owns_group and dist.is_initialized():
            dist.destroy_process_group()


def train_in_process_group(
    config: TrainConfig,
    *,
    source=None,
    model_config=None,
    text_embeddings: "torch.Tensor | None" = None,
    teacher=None,
    pixel_blend_function: Callable | None = None,
) -> TrainResult:
    """Train (or resume) a run. Library entry point of ``ovgaussian train``.

    Args:
        config: the run's settings.
        source: SceneSource (default: ``ShardSource(config.data.dataset, config.data.split)``).
        model_config: network config overriding the preset (tests: tiny networks).
        text_embeddings: ``[C_seen, D]`` overriding the text encoder (tests).
        teacher: a ``DenseTeacher`` overriding the one built from ``config.teacher`` (tests).
        pixel_blend_function: ``compute_pixel_blend_weights`` replacement (tests).
    """
    import torch

    from ovgaussian.text import load_or_encode_texts

    check_text_space(config)
    group = init_process_group(config.device)
    device = torch.device(config.device)
    if config.device == "cuda" and group.world_size > 1:
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        device = torch.device("cuda", torch.cuda.current_device())
    run_dir = Path(config.out)
    cache_dir = run_dir / "caches"
    is_main = group.rank == 0
    notes: list[str] = []
    if is_main:
        ensure_writable_dir(run_dir)  # fail before reading data and models, not after
        sweep_run_temps(run_dir)  # half-written checkpoints and files of a killed earlier run

    vocabulary = training_vocabulary(config.data.num_classes)
    source = source if source is not None else ShardSource(config.data.dataset, config.data.split, config.data.verify)
    scan = scan_scenes(source, vocabulary)
    if not scan.usable:
        raise ValueError(f"{config.data.dataset}: split {config.data.split!r} has no trainable scene "
                         f"(skipped: {scan.skipped or 'none listed'})")
    if scan.skipped:
        notes.append("skipped scenes: " + ", ".join(f"{n} {r}" for r, n in sorted(scan.skipped.items())))

    saved = None
    if config.resume:
        if not (run_dir / CONFIG_NAME).is_file():
            raise CheckpointError(f"{run_dir / CONFIG_NAME}: missing; nothing to resume")
        saved = read_json(run_dir / CONFIG_NAME)
        check_resumable(saved, config, scan, run_dir / CONFIG_NAME)
    elif latest_checkpoint(run_dir) is not None:  # every rank checks: none may wait for a failed rank 0
        raise CheckpointError(f"{run_dir}: already holds a trained run; pass --resume or use a new --out")

    # text embeddings (rank 0 writes the cache, the others read it)
    if text_embeddings is None:
        if is_main:
            text_embeddings = load_or_encode_texts(vocabulary.names, config.text, cache_dir)
        if group.world_size > 1:
            import torch.distributed as dist

            dist.barrier()
        if not is_main:
            text_embeddings = load_or_encode_texts(vocabulary.names, config.text, cache_dir)
    text_embeddings = text_embeddings.float().to(device)

    # teacher
    use_teacher = not config.loss.no_vs_align
    if use_teacher and teacher is None:
        if config.teacher.clip_model is None:
            use_teacher = False
            notes.append("visual-semantic (cosine) loss off: no local CLIP given (--clip-model PATH)")
        else:
            from ovgaussian.teacher import DenseTeacher

            teacher = DenseTeacher.from_config(config.teacher)
    if not use_teacher:
        teacher = None
    teacher_width = None if teacher is None else int(teacher.feature_dim)

    # network
    if saved is not None:
        from ovgaussian.model_config import OVGaussianNetConfig

        model_config = config_from_dict(OVGaussianNetConfig, saved["model"])
        teacher_width = saved["teacher_width"]
    elif model_config is None:
        model_config = make_model_config(config, text_embeddings.shape[1])
    if model_config.embedding_width != text_embeddings.shape[1]:
        raise ValueError(f"model embedding_width {model_config.embedding_width} != text embedding width "
                         f"{text_embeddings.shape[1]}")
    net = build_network(model_config, teacher_width).to(device)
    if group.world_size > 1:
        import torch.distributed as dist

        for tensor in list(net.parameters()) + list(net.buffers()):
            dist.broadcast(tensor.data, src=0)
        synchronize_batch_norms(net)
    net.train()
    optimizer = torch.optim.SGD(net.parameters(), lr=config.optim.lr, momentum=config.optim.momentum,
                                weight_decay=config.optim.weight_decay)

    # data and schedule
    batch_scenes = min(config.batch_scenes, len(scan.usable))
    if batch_scenes < config.batch_scenes:
        notes.append(f"batch of {batch_scenes} scenes: the split has only {len(scan.usable)} usable scenes")
    if batch_scenes < group.world_size:
        raise ValueError(f"a global batch of {batch_scenes} scenes cannot be split over {group.world_size} processes")
    steps_per_epoch = len(scan.usable) // batch_scenes
    total_steps = steps_per_epoch * config.epochs
    cache_budget = None
    if isinstance(getattr(source, "dataset", None), Path):  # shards on disk: caches within the budget
        cache_budget = int(CACHE_BUDGET_FRACTION * folder_bytes(source.dataset, DATASET_INTERNAL_FOLDERS))
    data = TrainingData(source, config.data, vocabulary, cache_dir=cache_dir, teacher=teacher,
                        pixel_blend_function=pixel_blend_function, scan=scan, cache_budget_bytes=cache_budget)

    start_epoch, global_step, last_checkpoint = 0, 0, None
    if saved is not None:
        folder = latest_checkpoint(run_dir)
        if folder is not None:
            state = load_checkpoint(folder, net, optimizer, device=device)
            start_epoch, global_step, last_checkpoint = int(state["epoch"]), int(state["global_step"]), folder
    metrics_path = run_dir / METRICS_NAME
    if is_main:
        make_dirs(run_dir)
        payload = run_config_payload(config, model_config, teacher_width, vocabulary, scan, group,
                                     text_embeddings.shape[1])
        payload["notes"] = notes
        write_json_atomic(run_dir / CONFIG_NAME, payload)
        if saved is not None:
            truncate_metrics(metrics_path, start_epoch)
        else:
            metrics_path.unlink(missing_ok=True)
    for note in notes:
        if is_main:
            LOG.warning(note)

    last_epoch_metrics: dict = {}
    end_epoch = config.epochs if config.stop_after_epochs is None else min(config.epochs, config.stop_after_epochs)
    for epoch in range(start_epoch, end_epoch):
        torch.manual_seed(config.seed * 100003 + epoch)
        batches = epoch_batches(scan.usable, batch_scenes, config.seed, epoch)[:steps_per_epoch]
        bar = None
        if config.progress and is_main:
            from tqdm import tqdm

            bar = tqdm(total=len(batches), desc=f"epoch {epoch + 1}/{config.epochs}", unit="step", leave=False)
        sums = np.zeros(len(METRIC_NAMES))
        for step, batch in enumerate(batches):
            lr = learning_rate(global_step, total_steps, config.optim.lr, config.optim.schedule)
            for param_group in optimizer.param_groups:
                param_group["lr"] = lr
            local = rank_slice(batch, group.rank, group.world_size)
            samples = [data.sample(sid, np.random.default_rng(sample_seed(config.seed, epoch, step, sid)))
                       for sid in local]
            optimizer.zero_grad(set_to_none=True)
            terms = batch_losses(net, samples, text_embeddings, config, use_teacher, device)
            loss = sum(t.total for t in terms) / len(batch)
            loss.backward()
            if group.world_size > 1:
                sum_gradients(net)
            if config.optim.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(net.parameters(), config.optim.grad_clip)
            optimizer.step()
            global_step += 1
            local_sums = [sum(float(getattr(t, name).detach()) for t in terms)
                          for name in ("total", "text_3d", "text_2d", "cosine")]
            means = np.array(reduce_sums(local_sums, group, device)) / len(batch)
            if not np.isfinite(means).all():
                raise FloatingPointError(f"epoch {epoch} step {step}: non-finite loss {means.tolist()}")
            sums += means
            record = {"kind": "step", "epoch": epoch, "step": step, "global_step": global_step, "lr": lr,
                      "scenes": list(batch), **dict(zip(METRIC_NAMES, means.tolist()))}
            if is_main:
                with open(metrics_path, "a") as f:
                    f.write(json.dumps(record) + "\n")
            if bar is not None:
                bar.set_postfix({n: f"{v:.3f}" for n, v in zip(METRIC_NAMES, means)})
                bar.update(1)
        if bar is not None:
            bar.close()
        last_epoch_metrics = dict(zip(METRIC_NAMES, (sums / max(len(batches), 1)).tolist()))
        if is_main:
            with open(metrics_path, "a") as f:
                f.write(json.dumps({"kind": "epoch", "epoch": epoch, "global_step": global_step,
                                    "steps": len(batches), **last_epoch_metrics}) + "\n")
            last_checkpoint = save_checkpoint(run_dir, epoch + 1, net, optimizer,
                                              {"global_step": global_step, "metrics": last_epoch_metrics})
        if group.world_size > 1:
            import torch.distributed as dist

            dist.barrier()
    if data.teacher_uncached:
        notes.append(f"teacher features computed {data.teacher_uncached} times without caching: the run folder's "
                     f"caches reached {100 * CACHE_BUDGET_FRACTION:.0f} % of the dataset's size")
        if is_main:
            LOG.warning(notes[-1])
    return TrainResult(run_dir, max(end_epoch, start_epoch), global_step, last_epoch_metrics, dict(scan.skipped),
                       len(scan.usable), last_checkpoint, tuple(notes))


def read_metrics(run_dir: Path, kind: str = "step") -> list[dict]:
    """The ``kind`` lines (``step`` or ``epoch``) of a run's metrics.jsonl."""
    path = Path(run_dir) / METRICS_NAME
    return [r for r in (json.loads(line) for line in path.read_text().splitlines() if line.strip())
            if r["kind"] == kind]


__all__ = ["TrainResult", "train", "learning_rate", "read_metrics", "InMemorySource"]
