"""The build's records: one scene task (sent to workers), what building it did, and the whole build's report; and
the clock of their CPU seconds per stage (``CpuClock``: every thread of this process, ``time.process_time``).

``CpuClock``'s parts nest: a part measured inside another is counted in its own name and left out of the enclosing
one, so the parts add up to the CPU time spent inside the outermost ones. It lives here, not in ``seggaussian.util``:
the util package is in every stage's code digest (``seggaussian.pipeline.cache``), this module in none, and the stage
code that is handed a clock only calls its ``measure``.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, NamedTuple


class SceneTask(NamedTuple):
    """One scene to build (picklable; sent to workers).

    Fields:
        scene_id: the source's scene id.
        domain: reader used: ``scannetpp`` or ``replica``.
        root: the layout root passed to the reader.
        fingerprint: sha256 of the scene's raw files (relative path, size, mtime) and the reader code.
        trained_ply: a trained 3DGS PLY for this scene, or None.
        official_split: ``train`` / ``val`` from the official lists, or None.
        transform_file: ``<ply_dir>/<scene>.transform.json`` beside the trained splat (its frame: a
            ``seggaussian.frames`` transform spec file), or None when the splat is in the scene's frame.
    """

    scene_id: str
    domain: str
    root: Path
    fingerprint: str
    trained_ply: Path | None
    official_split: str | None
    transform_file: Path | None = None


class SceneOutcome(NamedTuple):
    """What building one scene did.

    Fields:
        scene_id, domain, official_split: as in the task.
        status: ``built`` (a stage ran), ``skipped`` (every stage cached) or ``failed``.
        stages_run: names of the stages that ran.
        reason: the error (type and message) for a failed scene.
        info: JSON-ready facts copied into the manifest (counts, transfer statistics, accuracy).
        fragments: {table: cached per-scene Parquet path}.
        keys: {stage: key}.
        seconds: wall time.
        cpu_seconds: CPU seconds (every thread of the process that built the scene) of what ran: ``read`` (the raw
            scene), ``gaussians``, ``transfer`` (less the two below), ``occlusion`` (the label points and Gaussians
            the views never see), ``views`` (rendering, encoding), ``shards`` (writing the scene's Parquet tables).
            Kept out of ``info``: the manifest holds only what the inputs determine.
    """

    scene_id: str
    domain: str
    official_split: str | None
    status: str
    stages_run: tuple
    reason: str | None
    info: dict
    fragments: dict
    keys: dict
    seconds: float
    cpu_seconds: dict = {}


class BuildReport(NamedTuple):
    """Result of ``build_dataset``: per-scene outcomes, split counts, files, whether shards were rewritten."""

    dataset: Path
    outcomes: list
    split_counts: dict
    files: int
    bytes: int
    assembled: bool
    synthesized: list
    seconds: float
    #: Failed scenes whose last good copy stays in the shards (see ``build_record.write_build_record``).
    kept: tuple = ()
    #: Temporaries of killed earlier runs removed from the dataset folder at the start.
    swept: int = 0
    #: CPU seconds of the build process outside the scenes: ``discover`` (raw tree, fingerprints), ``assemble``
    #: (build record, split-named shards, manifest); each scene's own are in its outcome's ``cpu_seconds``.
    cpu_seconds: dict = {}
    #: (index, count) of the slice a sliced build built (nothing assembled), None for a whole build.
    shard: tuple | None = None
    #: The Ray nodes that passed the storage check before the scenes were sent (``ray_tasks.NodeCheck``).
    nodes: tuple = ()

    @property
    def counts(self) -> dict:
        return {s: sum(1 for o in self.outcomes if o.status == s) for s in ("built", "skipped", "failed")}


def failed_outcome(task: SceneTask, reason: str, seconds: float, trace: str | None = None) -> SceneOutcome:
    """The outcome of a scene that failed with ``reason`` (the traceback appended when given)."""
    return SceneOutcome(task.scene_id, task.domain, task.official_split, "failed", (),
                        reason + (f"\n{trace}" if trace else ""), {}, {}, {}, seconds)


def crashed_outcome(task: SceneTask, exc: BaseException) -> SceneOutcome:
    """The outcome of a scene whose worker (a pool process, a Ray task with its retries used up) raised ``exc``
    instead of returning: that scene fails, the build goes on. The reason keeps the error's first line."""
    text = str(exc).strip().splitlines()
    return failed_outcome(task, f"worker crashed: {type(exc).__name__}: {text[0] if text else ''}", 0.0)


class CpuClock:
    """CPU seconds per named part (``seconds``); ``measure(name)`` times one part, nested parts excluded."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._inner: list[float] = []  # per open part: CPU seconds of the parts nested in it

    @contextmanager
    def measure(self, name: str) -> Iterator[None]:
        start = time.process_time()
        self._inner.append(0.0)
        try:
            yield
        finally:
            spent = time.process_time() - start
            nested = self._inner.pop()
            self.seconds[name] = self.seconds.get(name, 0.0) + spent - nested
            if self._inner:
                self._inner[-1] += spent

    def rounded(self, digits: int = 3) -> dict[str, float]:
        """``seconds`` rounded (for records and JSON)."""
        return {name: round(value, digits) for name, value in self.seconds.items()}
