"""The samples of the coming training steps: prepared in this process, or ahead in worker processes.

A step's samples depend only on what its :class:`StepTask` names: each scene's view, augmentation and pixels come
from a generator seeded by the task (``schedule.sample_seed``: seed, epoch, step, scene id), never from which
process draws them or when. :func:`prepare_step` is the one function that turns a task into samples, on every path:

* ``workers == 0`` (:class:`InlineLoader`, the reference): the training process calls it before each step;
* ``workers >= 1`` (:class:`WorkerLoader`): that many spawned processes, each with its own copy of the
  ``TrainingData``, call it for the next ``workers`` steps while the current step runs; the training process takes
  the results in step order. Spawned, not forked: numba's threading layer and torch's threads do not survive a
  fork (as ``ovgaussian.suite.profile``), and a forked child of a CUDA process cannot be trusted either.

So a run gives the same samples, and with them the same weights, for every worker count, and a resumed run's
tasks (from its checkpoint's epoch on) are the uninterrupted run's.

Failures end the run with one line naming the scene (:class:`LoaderError`): an exception while sampling a scene
(in any process), a worker that exits without answering, or no answer within ``timeout_s`` seconds of the
training process starting to wait (a hung worker is reported, never waited on forever). Workers check every
second whether their parent is still alive and leave when it is not; :meth:`WorkerLoader.close` (also on errors)
asks them to stop and terminates any that have not within a few seconds.

Tensors travel between processes through shared memory (torch's reductions of ``multiprocessing``). On CUDA,
:func:`samples_to_device` pins the host tensors and copies them without blocking; on the CPU it returns the
samples as they are.
"""

from __future__ import annotations

import os
import pickle
import queue
import resource
import time
from collections import deque
from typing import Iterable, Iterator, NamedTuple, Sequence

import numpy as np
import torch
import torch.multiprocessing as torch_mp

from ovgaussian.data.training_data import SceneSample
from ovgaussian.train.schedule import epoch_batches, rank_slice, sample_seed
from seggaussian.util.threads import cap_threads

#: Seconds between a worker's checks that its parent still lives, and between the training process's checks that
#: its workers do while it waits.
POLL_S = 1.0
#: Seconds a worker gets to leave after being asked to stop, before it is terminated (then killed).
STOP_GRACE_S = 5.0


class LoaderError(RuntimeError):
    """A step's samples could not be prepared: one line naming the scene (and the step)."""


class StepTask(NamedTuple):
    """What one step's samples are drawn from.

    Fields:
        epoch, step: the step (0-based step within its epoch).
        scenes: ``(scene id, generator entropy)`` per scene this process trains on in the step.
    """

    epoch: int
    step: int
    scenes: tuple[tuple[str, tuple[int, ...]], ...]

    @property
    def key(self) -> tuple[int, int]:
        return (self.epoch, self.step)

    def where(self) -> str:
        return f"epoch {self.epoch} step {self.step}"


class LoadedStep(NamedTuple):
    """One step's samples and how long they took.

    Fields:
        task: the step.
        samples: one ``SceneSample`` per scene of ``task.scenes`` (CPU tensors).
        sample_s: seconds spent drawing them (in this process or a worker).
        wait_s: seconds the training process waited for them (all of ``sample_s`` without workers).
        sample_cpu_s: CPU seconds of the process that drew them, while it did.
    """

    task: StepTask
    samples: list[SceneSample]
    sample_s: float
    wait_s: float
    sample_cpu_s: float = 0.0


class PhaseTimes:
    """Seconds per phase summed over steps: ``wait`` (for the samples), ``sample`` (drawing them, in this process
    or a loader worker), ``transfer`` (to the device: the host's time issuing the copies), ``compute`` (forward,
    backward, SGD step and the metric reduction, which waits for the device) and ``step`` (all of a step)."""

    NAMES = ("wait", "sample", "transfer", "compute", "step")

    def __init__(self) -> None:
        self.steps = 0
        self.seconds = dict.fromkeys(self.NAMES, 0.0)

    def add(self, **seconds: float) -> None:
        for name, value in seconds.items():
            self.seconds[name] += value

    def summary(self) -> dict:
        """Totals, per-step means and ``device_busy`` = compute / step (None before any step)."""
        per_step = {f"{n}_s": self.seconds[n] / self.steps if self.steps else None for n in self.NAMES}
        busy = self.seconds["compute"] / self.seconds["step"] if self.seconds["step"] > 0 else None
        return {"steps": self.steps, "total_s": {n: self.seconds[n] for n in self.NAMES}, "per_step": per_step,
                "device_busy": busy}


def step_tasks(seed: int, scene_ids, batch_scenes: int, steps_per_epoch: int, rank: int, world_size: int,
               start_epoch: int, end_epoch: int) -> Iterator[StepTask]:
    """Process ``rank``'s ``StepTask`` of every step from ``start_epoch`` to ``end_epoch`` (exclusive), in order:
    its slice of each global batch (``schedule.rank_slice``), each scene with its generator's entropy
    (``schedule.sample_seed``)."""
    for epoch in range(start_epoch, end_epoch):
        batches = epoch_batches(scene_ids, batch_scenes, seed, epoch)[:steps_per_epoch]
        for step, batch in enumerate(batches):
            local = rank_slice(batch, rank, world_size)
            yield StepTask(epoch, step, tuple((sid, tuple(sample_seed(seed, epoch, step, sid))) for sid in local))


def phase_line(phases: dict) -> str:
    """One line of a ``PhaseTimes.summary``: the device's busy share and the mean seconds per phase of a step (and
    the loader workers, when the summary names them)."""
    if not phases.get("steps"):
        return "no steps"
    p = phases["per_step"]
    workers = f", {phases['loader_workers']} loader workers" if "loader_workers" in phases else ""
    return (f"device busy {100 * phases['device_busy']:.0f} % of a {p['step_s']:.2f} s step (waiting for samples "
            f"{p['wait_s']:.2f} s, drawing them {p['sample_s']:.2f} s, transfer {p['transfer_s']:.2f} s, "
            f"compute {p['compute_s']:.2f} s{workers})")


def task_seed(seed: int, epoch: int, step: int) -> int:
    """Seed of torch's CPU generator while a step's samples are drawn (the same in every process)."""
    return int(np.random.SeedSequence([int(seed), int(epoch), int(step), 0x10AD]).generate_state(1)[0])


def prepare_step(data, task: StepTask, seed: int, progress=None) -> list[SceneSample]:
    """The samples of ``task``: each scene's from ``numpy.random.default_rng(entropy)``.

    torch's CPU generator is forked and seeded from (seed, epoch, step) meanwhile, so a draw from it inside the
    sampling is the same in every process and leaves the caller's generator as it was. ``progress(scene_id)`` is
    called before each scene (a worker reports which scene it is on). LoaderError naming the scene on any error.
    """
    samples = []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(task_seed(seed, task.epoch, task.step))
        for scene_id, entropy in task.scenes:
            if progress is not None:
                progress(scene_id)
            try:
                samples.append(data.sample(scene_id, np.random.default_rng(list(entropy))))
            except Exception as error:  # noqa: BLE001 -- every sampling failure becomes one line naming the scene
                raise LoaderError(f"scene {scene_id} ({task.where()}): {_one_line(error)}") from error
    return samples


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def samples_to_device(samples: Sequence[SceneSample], device) -> list[SceneSample]:
    """The samples with every tensor on ``device``: on CUDA pinned first and copied without blocking (the copies
    overlap the host's work until a kernel needs them); on the CPU the samples themselves."""
    device = torch.device(device)
    if device.type == "cpu":
        return list(samples)

    def move(value):
        if not isinstance(value, torch.Tensor):
            return value
        return value.pin_memory().to(device, non_blocking=True)

    return [s._replace(**{name: move(getattr(s, name)) for name in s._fields}) for s in samples]


class InlineLoader:
    """The reference loader: each step's samples drawn in this process when the step asks for them."""

    def __init__(self, data, tasks: Iterable[StepTask], seed: int):
        self.data, self.tasks, self.seed = data, iter(tasks), seed

    def __iter__(self) -> Iterator[LoadedStep]:
        for task in self.tasks:
            start, cpu = time.perf_counter(), time.process_time()
            samples = prepare_step(self.data, task, self.seed)
            elapsed = time.perf_counter() - start
            yield LoadedStep(task, samples, elapsed, elapsed, time.process_time() - cpu)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def resident_peak_bytes() -> int:
    """This process's resident high-water mark: ``VmHWM`` of /proc/self/status (that of this program: a spawned
    process's ``ru_maxrss`` still holds the peak of the process it was forked from before its exec), else
    ``ru_maxrss``."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _worker_main(index: int, data, seed: int, threads: int, tasks, results, parent_pid: int) -> None:
    """Worker ``index``'s loop: take a task, answer ``("scene", key, id)`` before each scene, then ``("done", key,
    samples, (seconds, CPU seconds), (index, peak bytes), teacher_uncached)`` or ``("error", key, message)``; leave
    on ``None`` or when the parent is gone (checked every ``POLL_S``)."""
    cap_threads(threads)
    while True:
        try:
            task = tasks.get(timeout=POLL_S)
        except queue.Empty:
            if os.getppid() != parent_pid:
                return
            continue
        if task is None:
            return
        start, cpu = time.perf_counter(), time.process_time()
        uncached = data.teacher_uncached
        try:
            samples = prepare_step(data, task, seed, lambda scene_id: results.put(("scene", task.key, scene_id)))
        except LoaderError as error:
            results.put(("error", task.key, str(error)))
            continue
        seconds = (time.perf_counter() - start, time.process_time() - cpu)
        results.put(("done", task.key, samples, seconds, (index, resident_peak_bytes()),
                     data.teacher_uncached - uncached))


class WorkerLoader:
    """Samples prepared ahead by ``workers`` spawned processes, handed out in step order.

    Args:
        data: the ``TrainingData`` (pickled to each worker at start: its caches fill there, not here).
        tasks: the steps, in the order they are trained.
        seed: the run's seed (:func:`prepare_step`).
        workers: processes (at least 1); each prepares one step ahead.
        threads: torch and numba threads of each worker (the training process's count, so the blend weights are
            computed as without workers).
        timeout_s: most seconds to wait for a step's samples before reporting a hung worker.
    """

    def __init__(self, data, tasks: Iterable[StepTask], seed: int, workers: int, threads: int, timeout_s: float):
        if workers < 1:
            raise ValueError(f"loader workers must be at least 1 for WorkerLoader, got {workers}")
        self.data, self.tasks, self.seed, self.timeout_s = data, iter(tasks), seed, float(timeout_s)
        context = torch_mp.get_context("spawn")
        self._tasks, self._results = context.Queue(), context.Queue()
        self._pending: deque[StepTask] = deque()
        self._ready: dict[tuple[int, int], tuple] = {}
        self._current: dict[tuple[int, int], str] = {}  # the scene a worker last said it is sampling
        self.peak_bytes: dict[int, int] = {}  # worker index -> its peak resident bytes, as last reported
        self.teacher_uncached = 0
        self._processes = [context.Process(target=_worker_main, name=f"ovgaussian-loader-{i}", daemon=True,
                                           args=(i, data, seed, threads, self._tasks, self._results, os.getpid()))
                           for i in range(workers)]
        try:
            for process in self._processes:
                try:
                    process.start()  # pickles ``data`` for the spawned process
                except (pickle.PicklingError, AttributeError, TypeError) as error:
                    raise LoaderError(f"loader workers: the training data cannot be sent to a worker process "
                                      f"({_one_line(error)}); use 0 loader workers") from error
            for _ in range(workers):
                self._submit()
        except BaseException:
            self.close()
            raise

    def _submit(self) -> None:
        task = next(self.tasks, None)
        if task is not None:
            self._pending.append(task)
            self._tasks.put(task)

    def __iter__(self) -> Iterator[LoadedStep]:
        while self._pending:
            task = self._pending.popleft()
            start = time.perf_counter()
            samples, (sample_s, sample_cpu_s) = self._wait_for(task, start)
            self._submit()  # keep one step per worker in flight
            yield LoadedStep(task, samples, sample_s, time.perf_counter() - start, sample_cpu_s)

    def _wait_for(self, task: StepTask, start: float) -> tuple[list[SceneSample], tuple[float, float]]:
        while task.key not in self._ready:
            waited = time.perf_counter() - start
            if waited > self.timeout_s:
                scene = self._current.get(task.key) or ", ".join(s for s, _ in task.scenes)
                raise LoaderError(f"scene {scene} ({task.where()}): no sample from the loader workers after "
                                  f"{self.timeout_s:g} s (a worker hung)")
            try:
                message = self._results.get(timeout=min(POLL_S, max(self.timeout_s - waited, 0.01)))
            except queue.Empty:
                self._check_alive(task)
                continue
            self._receive(message)
        message = self._ready.pop(task.key)
        if message[0] == "error":
            raise LoaderError(message[2])
        _, _, samples, seconds, _, uncached = message
        self.teacher_uncached += uncached
        return samples, seconds

    def _receive(self, message: tuple) -> None:
        kind, key = message[0], message[1]
        if kind == "scene":
            self._current[key] = message[2]
            return
        self._current.pop(key, None)
        if kind == "done":
            worker, peak = message[4]
            self.peak_bytes[worker] = max(peak, self.peak_bytes.get(worker, 0))
        self._ready[key] = message

    def _check_alive(self, task: StepTask) -> None:
        for process in self._processes:
            if not process.is_alive():
                scene = self._current.get(task.key) or ", ".join(s for s, _ in task.scenes)
                raise LoaderError(f"scene {scene} ({task.where()}): loader worker {process.name} exited "
                                  f"(code {process.exitcode}) without its samples")

    def worker_peak_bytes(self) -> int:
        """Sum of the workers' reported peak resident bytes: a bound on what they held at once."""
        return sum(self.peak_bytes.values())

    def close(self) -> None:
        """Ask every worker to stop, then terminate (and kill) any still running after ``STOP_GRACE_S``."""
        for _ in self._processes:
            try:
                self._tasks.put_nowait(None)
            except (ValueError, OSError):  # the queue is already closed
                break
        deadline = time.monotonic() + STOP_GRACE_S
        for process in self._processes:
            if process.pid is not None:
                process.join(timeout=max(deadline - time.monotonic(), 0.0))
        for process in self._processes:
            if process.pid is not None and process.is_alive():
                process.terminate()
                process.join(timeout=STOP_GRACE_S)
                if process.is_alive():
                    process.kill()
                    process.join(timeout=STOP_GRACE_S)
        for q in (self._tasks, self._results):
            q.cancel_join_thread()  # a queue with unread items must not block this process's exit
            q.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def step_loader(data, tasks: Iterable[StepTask], seed: int, workers: int, threads: int, timeout_s: float):
    """:class:`InlineLoader` for ``workers == 0``, else :class:`WorkerLoader` (a context manager either way)."""
    if workers == 0:
        return InlineLoader(data, tasks, seed)
    return WorkerLoader(data, tasks, seed, workers, threads, timeout_s)
