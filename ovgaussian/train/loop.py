"""OVGaussian training: GSR (semantic rasterization M = W S) + CCL losses, SGD, checkpoints, torchrun.

One step (global batch of ``batch_scenes`` scenes, one train view each):

1. every process takes its contiguous slice of the batch (``schedule.rank_slice``) and draws each scene's
   view, augmentation and pixels from a generator seeded by (seed, epoch, step, scene id), so the
   draws do not depend on the number of processes (``data.TrainingData.sample``), nor on the number of loader
   workers that draw them ahead (``loader``, ``TrainConfig.loader_workers``); they are then copied to the device
   (pinned, without blocking, on CUDA);
2. the network maps the concatenated scenes to semantic vectors ``s [N, 16]``;
3. per scene: 3D-to-text CE on ``phi(s)``; ``M = render_features(W, s)`` at the sampled pixels;
   2D-to-text CE on ``phi(M)``; cosine loss of ``psi(M)`` against the MaskCLIP teacher on covered pixels
   (``train_losses``);
4. the batch loss is the mean of the scene losses over the *global* batch. With several processes
   (torchrun) each rank back-propagates its share, the gradients are summed over ranks and batch-norm
   statistics are synchronized (``process_group``), so P processes compute the same step as one process
   up to float rounding;
5. SGD (momentum) with a learning rate decayed per step (cosine or poly, ``schedule.learning_rate``),
   gradient-norm clipping.

The last incomplete batch of an epoch is dropped (the global batch is fixed); a split with fewer usable
scenes than ``batch_scenes`` trains on all of them per step. Scenes that are empty, have no train view
or are all-ignore are skipped and counted (``TrainResult.skipped``, config.json).

Phases: each step's wait for its samples, their copy to the device and the compute (forward, backward, SGD, the
metric reduction that waits for the device) are timed (``loader.PhaseTimes``); the share of the step spent in the
compute is the share the device was busy, shown on the progress bar, logged per epoch and returned in
``TrainResult.phases``. The timings stay out of metrics.jsonl, which holds only what the seed determines.

Determinism: the model initialization, scene order, views, augmentations and pixels follow the seed;
``--resume`` restores weights, momentum, batch-norm buffers and the step counter from the last
epoch checkpoint (``run_folder.check_resumable`` refuses other settings or data), and the epoch-indexed
generators make the continued run identical to an uninterrupted one.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from ovgaussian.data.cache_budget import CACHE_BUDGET_FRACTION, DATASET_INTERNAL_FOLDERS, folder_bytes
from ovgaussian.run.checkpoint import (
    CONFIG_NAME, METRICS_NAME, CheckpointError, build_network, latest_checkpoint, load_checkpoint, read_json,
    retain_checkpoints, save_checkpoint, saved_model_config, sweep_run_temps,
)
from ovgaussian.data.training_data import TrainingData
from ovgaussian.run.devices import resolve_device
from ovgaussian.model.config import OVGaussianNetConfig
from ovgaussian.train.process_group import (
    ProcessGroup, barrier, broadcast_module, init_process_group, reduce_sums, sum_gradients,
    synchronize_batch_norms, torchrun_world_size,
)
from ovgaussian.run.folder import (
    METRIC_NAMES, append_metrics, check_resumable, run_config_payload, truncate_metrics,
)
from ovgaussian.data.scene_source import ScanResult, ShardSource, class_weights, scan_scenes, with_renditions
from ovgaussian.train.loader import LoadedStep, PhaseTimes, phase_line, samples_to_device, step_loader, step_tasks
from ovgaussian.train.schedule import epoch_batches, learning_rate
from ovgaussian.text.teacher import DenseTeacher
from ovgaussian.text.encoders import load_or_encode_texts
from ovgaussian.run.config import TrainConfig, config_from_dict
from ovgaussian.train.step_losses import batch_losses
from ovgaussian.text.vocabulary import Vocabulary, benchmark_vocabulary, training_vocabulary
from seggaussian.util.atomic import ensure_writable_dir, make_dirs, write_json_atomic
from seggaussian.util.jsonsafe import NAN_IS_ERROR
from seggaussian.util.threads import thread_cap, threads_for_gaussians

LOG = logging.getLogger("ovgaussian.train.loop")


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
        phases: this call's step timings (``PhaseTimes.summary``): seconds waiting for samples, drawing them,
            copying them to the device, computing, whole steps, and ``device_busy`` (compute / step); and the
            ``loader_workers`` this process used.
        rank: this process's torchrun rank (0 alone); only rank 0 saves, the others' ``checkpoint`` is None.
    """

    run_dir: Path
    epochs: int
    steps: int
    last_epoch_metrics: dict
    skipped: dict
    num_scenes: int
    checkpoint: Path | None
    notes: tuple[str, ...]
    phases: dict = {}
    rank: int = 0


# --- settings checked before any work --------------------------------------------------------------


def make_model_config(config: TrainConfig, text_width: int) -> OVGaussianNetConfig:
    """The network config of the preset, with ``embedding_width`` = text width and the adapter switch."""
    fields = dict(embedding_width=int(text_width), use_adapter=config.use_adapter, seed=config.seed,
                  use_coordinates=config.use_coordinates, input_encoding=config.input_encoding,
                  pool_weighting=config.pool_weighting, devoxelize=config.devoxelize,
                  voxel_geometry=config.voxel_geometry, grid_anchor=config.grid_anchor,
                  surface_radius=config.surface_radius)
    if config.voxel_size is not None:
        fields["voxel_size"] = float(config.voxel_size)
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


# --- set-up of a run -------------------------------------------------------------------------------


def join_processes(config: TrainConfig) -> tuple[ProcessGroup, torch.device]:
    """This process's rank and its device (under torchrun on CUDA: the GPU of ``LOCAL_RANK``); the first step of a
    run, so a device that cannot be used is refused before any data is read."""
    device = resolve_device(config.device)
    group = init_process_group(config.device)
    if config.device == "cuda" and group.world_size > 1:
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        device = torch.device("cuda", torch.cuda.current_device())
    return group, device


def scan_split(config: TrainConfig, source, vocabulary: Vocabulary, notes: list[str]) -> ScanResult:
    """The split's scan; ValueError when no scene can be trained on, a note when some are skipped."""
    scan = scan_scenes(source, vocabulary)
    if not scan.usable:
        raise ValueError(f"{config.data.dataset}: split {config.data.split!r} has no trainable scene "
                         f"(skipped: {scan.skipped or 'none listed'})")
    if scan.skipped:
        notes.append("skipped scenes: " + ", ".join(f"{n} {r}" for r, n in sorted(scan.skipped.items())))
    return scan


def saved_run(config: TrainConfig, run_dir: Path, scan: ScanResult) -> dict | None:
    """The config.json of the run to resume (checked against ``config`` and the data), or None for a new run.

    ``config.resume == "auto"`` resumes when the folder holds a checkpoint and starts a new run otherwise (a run
    killed in its first epoch starts again). Every rank decides from the checkpoints alone: rank 0 writes the first
    one only after a step all ranks took part in, and a restarted run's ranks see the same folder.
    CheckpointError when there is nothing to resume, or when a new run would overwrite a trained one."""
    if config.resume == "auto":
        config = replace(config, resume=latest_checkpoint(run_dir) is not None)
    if config.resume:
        if not (run_dir / CONFIG_NAME).is_file():
            raise CheckpointError(f"{run_dir / CONFIG_NAME}: missing; nothing to resume")
        saved = read_json(run_dir / CONFIG_NAME)
        check_resumable(saved, config, scan, run_dir / CONFIG_NAME)
        return saved
    if latest_checkpoint(run_dir) is not None:  # every rank checks: none may wait for a failed rank 0
        raise CheckpointError(f"{run_dir}: already holds a trained run; pass --resume or use a new --out")
    return None


def scored_class_names(config: TrainConfig, vocabulary: Vocabulary) -> tuple[str, ...]:
    """The classes the text cross-entropies score, in column order: the training vocabulary's (seen) classes, then
    for a transductive run (``loss.unlabelled_as_unseen``) the unseen classes of the K-class benchmark vocabulary."""
    if not config.loss.unlabelled_as_unseen:
        return tuple(vocabulary.names)
    benchmark = benchmark_vocabulary(config.data.num_classes)
    return tuple(vocabulary.names) + tuple(benchmark.names[i] for i in benchmark.unseen)


def class_text_embeddings(config: TrainConfig, names: tuple[str, ...], cache_dir: Path,
                          group: ProcessGroup) -> torch.Tensor:
    """``[C, D]`` text embeddings of ``names`` (rank 0 writes the cache, the others read it)."""
    text_embeddings = None
    if group.rank == 0:
        text_embeddings = load_or_encode_texts(names, config.text, cache_dir)
    barrier(group)
    if group.rank != 0:
        text_embeddings = load_or_encode_texts(names, config.text, cache_dir)
    return text_embeddings


def visual_teacher(config: TrainConfig, teacher, notes: list[str]):
    """The dense teacher of the cosine loss, or None when the loss is off (a note when no CLIP was given)."""
    if config.loss.no_vs_align:
        return None
    if teacher is not None:
        return teacher
    if config.teacher.clip_model is None:
        notes.append("visual-semantic (cosine) loss off: no local CLIP given (--clip-model PATH)")
        return None
    return DenseTeacher.from_config(config.teacher)


def training_network(config: TrainConfig, saved: dict | None, model_config, teacher, text_width: int,
                     group: ProcessGroup, device: torch.device):
    """``(net, model_config, teacher_width)``: the network of a new run (preset or ``model_config``) or of the
    saved run, identical on every process, in training mode."""
    teacher_width = None if teacher is None else int(teacher.feature_dim)
    if saved is not None:
        model_config = saved_model_config(saved["model"])
        teacher_width = saved["teacher_width"]
    elif model_config is None:
        model_config = make_model_config(config, text_width)
    if model_config.embedding_width != text_width:
        raise ValueError(f"model embedding_width {model_config.embedding_width} != text embedding width "
                         f"{text_width}")
    net = build_network(model_config, teacher_width).to(device)
    if group.world_size > 1:
        broadcast_module(net)
        synchronize_batch_norms(net)
    net.train()
    return net, model_config, teacher_width


def global_batch_size(config: TrainConfig, scan: ScanResult, group: ProcessGroup, notes: list[str]) -> int:
    """Scenes per step: ``batch_scenes``, clamped to the usable scenes (with a note); at least one per process."""
    batch_scenes = min(config.batch_scenes, len(scan.usable))
    if batch_scenes < config.batch_scenes:
        notes.append(f"batch of {batch_scenes} scenes: the split has only {len(scan.usable)} usable scenes")
    if batch_scenes < group.world_size:
        raise ValueError(f"a global batch of {batch_scenes} scenes cannot be split over {group.world_size} processes")
    return batch_scenes


def training_threads(config: TrainConfig, scan: ScanResult, batch_scenes: int, group: ProcessGroup) -> int:
    """torch and numba threads of this process: ``config.threads``, else chosen from the Gaussians of its share of a
    step (the usable scenes' mean size times its scenes per step; ``threads_for_gaussians``)."""
    usable = set(scan.usable)
    sizes = [s.num_gaussians for s in scan.summaries if s.scene_id in usable]
    per_step = (sum(sizes) / max(len(sizes), 1)) * max(1, batch_scenes // group.world_size)
    return threads_for_gaussians(int(per_step), config.threads)


def run_cache_budget(source) -> int | None:
    """Bytes the run folder's caches may take: a fraction of the dataset's size for shards on disk, else None."""
    if isinstance(getattr(source, "dataset", None), Path):
        return int(CACHE_BUDGET_FRACTION * folder_bytes(source.dataset, DATASET_INTERNAL_FOLDERS))
    return None


# --- the loop --------------------------------------------------------------------------------------


class _Run(NamedTuple):
    """What every step of a run uses (set up once by ``train_in_process_group``)."""

    config: TrainConfig
    group: ProcessGroup
    device: torch.device
    net: torch.nn.Module
    optimizer: torch.optim.Optimizer
    data: TrainingData
    text_embeddings: torch.Tensor  # [C, D] on device: the seen classes, then (transductive) the unseen ones
    class_weights: torch.Tensor | None  # [C] weights of the text cross-entropies (None: all 1)
    unlabelled_columns: torch.Tensor | None  # [U] the unseen classes' columns (transductive runs), else None
    use_teacher: bool
    batch_scenes: int
    steps_per_epoch: int
    total_steps: int
    run_dir: Path
    metrics_path: Path  # run_dir / METRICS_NAME


def train_step(run: _Run, epoch: int, step: int, batch: list[str], global_step: int, loaded: LoadedStep,
               times: PhaseTimes) -> tuple[dict, np.ndarray]:
    """One optimizer step on a global batch, on this process's ``loaded`` samples: ``(metrics record, [4] metric
    means over the global batch)``; the transfer and compute seconds are added to ``times``."""
    config, group, optimizer = run.config, run.group, run.optimizer
    if loaded.task.key != (epoch, step):
        raise RuntimeError(f"the loader gave the samples of {loaded.task.where()} for epoch {epoch} step {step}")
    lr = learning_rate(global_step, run.total_steps, config.optim.lr, config.optim.schedule)
    for param_group in optimizer.param_groups:
        param_group["lr"] = lr
    start = time.perf_counter()
    samples = samples_to_device(loaded.samples, run.device)
    computing = time.perf_counter()
    optimizer.zero_grad(set_to_none=True)
    terms = batch_losses(run.net, samples, run.text_embeddings, config, run.use_teacher, run.device,
                         run.class_weights, run.unlabelled_columns)
    loss = sum(t.total for t in terms) / len(batch)
    loss.backward()
    if group.world_size > 1:
        sum_gradients(run.net)
    if config.optim.grad_clip is not None:
        torch.nn.utils.clip_grad_norm_(run.net.parameters(), config.optim.grad_clip)
    optimizer.step()
    local_sums = [sum(float(getattr(t, name).detach()) for t in terms)
                  for name in ("total", "text_3d", "text_2d", "cosine")]
    means = np.array(reduce_sums(local_sums, group, run.device)) / len(batch)
    times.add(transfer=computing - start, compute=time.perf_counter() - computing)
    if not np.isfinite(means).all():
        raise FloatingPointError(f"epoch {epoch} step {step}: non-finite loss {means.tolist()}")
    record = {"kind": "step", "epoch": epoch, "step": step, "global_step": global_step + 1, "lr": lr,
              "scenes": list(batch), **dict(zip(METRIC_NAMES, means.tolist()))}
    return record, means


def train_epoch(run: _Run, epoch: int, global_step: int, loaded_steps, times: PhaseTimes
                ) -> tuple[dict, int, Path | None]:
    """One epoch on the next steps of the iterator ``loaded_steps`` (``LoadedStep``): ``(mean metrics, global step
    after it, its checkpoint folder (rank 0; else None))``; its step timings are added to ``times``."""
    config, is_main = run.config, run.group.rank == 0
    torch.manual_seed(config.seed * 100003 + epoch)
    batches = epoch_batches(run.data.scene_ids, run.batch_scenes, config.seed, epoch)[:run.steps_per_epoch]
    bar = None
    if config.progress and is_main:
        bar = tqdm(total=len(batches), desc=f"epoch {epoch + 1}/{config.epochs}", unit="step", leave=False)
    sums = np.zeros(len(METRIC_NAMES))
    epoch_times = PhaseTimes()
    for step, batch in enumerate(batches):
        start = time.perf_counter()
        loaded = next(loaded_steps, None)
        if loaded is None:
            raise RuntimeError(f"the loader ended before epoch {epoch} step {step}")
        epoch_times.add(wait=loaded.wait_s, sample=loaded.sample_s)
        record, means = train_step(run, epoch, step, batch, global_step, loaded, epoch_times)
        del loaded
        global_step += 1
        sums += means
        if is_main:
            append_metrics(run.metrics_path, record)
        epoch_times.add(step=time.perf_counter() - start)
        epoch_times.steps += 1
        if bar is not None:
            busy = epoch_times.summary()["device_busy"]
            bar.set_postfix({**{n: f"{v:.3f}" for n, v in zip(METRIC_NAMES, means)}, "busy": f"{100 * busy:.0f}%"})
            bar.update(1)
    if bar is not None:
        bar.close()
    for name, value in epoch_times.seconds.items():
        times.add(**{name: value})
    times.steps += epoch_times.steps
    if is_main and epoch_times.steps:
        LOG.info("epoch %d: %s", epoch + 1, phase_line(epoch_times.summary()))
    epoch_metrics = dict(zip(METRIC_NAMES, (sums / max(len(batches), 1)).tolist()))
    checkpoint = None
    if is_main:
        append_metrics(run.metrics_path, {"kind": "epoch", "epoch": epoch, "global_step": global_step,
                                          "steps": len(batches), **epoch_metrics})
        checkpoint = save_checkpoint(run.run_dir, epoch + 1, run.net, run.optimizer,
                                     {"global_step": global_step, "metrics": epoch_metrics})
        retain_checkpoints(run.run_dir, config.keep_checkpoints)
    barrier(run.group)
    return epoch_metrics, global_step, checkpoint


def train(config: TrainConfig, **kwargs) -> TrainResult:
    """Train (or resume) a run; see ``train_in_process_group`` for the arguments.

    Under torchrun, the process group this call creates is destroyed when it returns or fails: a gloo group
    left alive at interpreter exit can abort the process ("terminate called without an active exception").
    """
    owns_group = torchrun_world_size() > 1 and not dist.is_initialized()
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
    text_embeddings: torch.Tensor | None = None,
    teacher=None,
    pixel_blend_function: Callable | None = None,
) -> TrainResult:
    """Train (or resume) a run. Library entry point of ``ovgaussian train``.

    Args:
        config: the run's settings.
        source: SceneSource (default: ``ShardSource(config.data.dataset, config.data.split)``).
        model_config: network config overriding the preset (tests: tiny networks).
        text_embeddings: ``[C, D]`` overriding the text encoder (tests): one row per ``scored_class_names``.
        teacher: a ``DenseTeacher`` overriding the one built from ``config.teacher`` (tests).
        pixel_blend_function: ``compute_pixel_blend_weights`` replacement (tests).
    """
    check_text_space(config)
    group, device = join_processes(config)
    run_dir = Path(config.out)
    cache_dir = run_dir / "caches"
    is_main = group.rank == 0
    notes: list[str] = []
    if is_main:
        ensure_writable_dir(run_dir)  # fail before reading data and models, not after
        sweep_run_temps(run_dir)  # half-written checkpoints and files of a killed earlier run

    vocabulary = training_vocabulary(config.data.num_classes, config.data.holdout_classes)
    source = source if source is not None else ShardSource(config.data.dataset, config.data.split, config.data.verify)
    scan = scan_split(config, source, vocabulary, notes)
    renditions = tuple(ShardSource(d, config.data.split, config.data.verify) for d in config.data.renditions)
    scan = with_renditions(scan, renditions, [str(d) for d in config.data.renditions], vocabulary)
    saved = saved_run(config, run_dir, scan)
    names = scored_class_names(config, vocabulary)
    if text_embeddings is None:
        text_embeddings = class_text_embeddings(config, names, cache_dir, group)
    if text_embeddings.shape[0] != len(names):
        raise ValueError(f"text embeddings have {text_embeddings.shape[0]} rows, the run scores {len(names)} classes")
    text_embeddings = text_embeddings.float().to(device)
    teacher = visual_teacher(config, teacher, notes)
    net, model_config, teacher_width = training_network(config, saved, model_config, teacher,
                                                        text_embeddings.shape[1], group, device)
    optimizer = torch.optim.SGD(net.parameters(), lr=config.optim.lr, momentum=config.optim.momentum,
                                weight_decay=config.optim.weight_decay)
    batch_scenes = global_batch_size(config, scan, group, notes)
    steps_per_epoch = len(scan.usable) // batch_scenes
    data = TrainingData(source, config.data, vocabulary, cache_dir=cache_dir, teacher=teacher,
                        pixel_blend_function=pixel_blend_function, scan=scan,
                        cache_budget_bytes=run_cache_budget(source), renditions=renditions)

    start_epoch, global_step, last_checkpoint = 0, 0, None
    if saved is not None:
        folder = latest_checkpoint(run_dir)
        if folder is not None:
            state = load_checkpoint(folder, net, optimizer, device=device)
            start_epoch, global_step, last_checkpoint = int(state["epoch"]), int(state["global_step"]), folder
    metrics_path = run_dir / METRICS_NAME
    threads = training_threads(config, scan, batch_scenes, group)
    if is_main:
        make_dirs(run_dir)
        payload = run_config_payload(config, model_config, teacher_width, vocabulary, scan, group,
                                     text_embeddings.shape[1], names, threads)
        payload["notes"] = notes
        write_json_atomic(run_dir / CONFIG_NAME, payload, nan=NAN_IS_ERROR)
        if saved is not None:
            truncate_metrics(metrics_path, start_epoch)
            retain_checkpoints(run_dir, config.keep_checkpoints)  # a kill may have stopped the last removal
        else:
            metrics_path.unlink(missing_ok=True)
        for note in notes:
            LOG.warning(note)

    weights = None
    if config.loss.class_balance:
        padded = np.ones(len(names), np.float32)  # transductive unseen columns: no labelled row indexes them
        padded[:len(vocabulary.names)] = class_weights(scan, len(vocabulary.names), config.loss.class_balance)
        weights = torch.from_numpy(padded).to(device)
    unlabelled_columns = None
    if config.loss.unlabelled_as_unseen:
        unlabelled_columns = torch.arange(len(vocabulary.names), len(names), dtype=torch.int64, device=device)
    run = _Run(config, group, device, net, optimizer, data, text_embeddings, weights, unlabelled_columns,
               teacher is not None,
               batch_scenes, steps_per_epoch, steps_per_epoch * config.epochs, run_dir, metrics_path)
    last_epoch_metrics: dict = {}
    end_epoch = config.epochs if config.stop_after_epochs is None else min(config.epochs, config.stop_after_epochs)
    times = PhaseTimes()
    workers = config.loader_workers
    tasks = step_tasks(config.seed, data.scene_ids, batch_scenes, steps_per_epoch, group.rank, group.world_size,
                       start_epoch, end_epoch)
    with thread_cap(threads):
        with step_loader(data, tasks, config.seed, workers, threads, config.loader_timeout_s) as loader:
            loaded_steps = iter(loader)
            for epoch in range(start_epoch, end_epoch):
                last_epoch_metrics, global_step, checkpoint = train_epoch(run, epoch, global_step, loaded_steps,
                                                                          times)
                last_checkpoint = checkpoint if is_main else last_checkpoint
            teacher_uncached = data.teacher_uncached + getattr(loader, "teacher_uncached", 0)
    if teacher_uncached:
        notes.append(f"teacher features computed {teacher_uncached} times without caching: the run folder's "
                     f"caches reached {100 * CACHE_BUDGET_FRACTION:.0f} % of the dataset's size")
        if is_main:
            LOG.warning(notes[-1])
    return TrainResult(run_dir, max(end_epoch, start_epoch), global_step, last_epoch_metrics, dict(scan.skipped),
                       len(scan.usable), last_checkpoint, tuple(notes),
                       {**times.summary(), "loader_workers": workers}, group.rank)
