"""``ovgaussian view`` as one library call: load the scene and the run, build the viewer, then serve or export.

The run is used exactly as ``ovgaussian predict`` uses it (``load_model_predictor``: its model, text encoder and
text cache; ``encode_gaussians`` for the semantic vectors); nothing is downloaded.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from pathlib import Path
from typing import Callable, NamedTuple

from ovgaussian.run.checkpoint import CONFIG_NAME, read_json
from ovgaussian.predict.query import load_model_predictor
from ovgaussian.view.app import QueryViewer
from ovgaussian.view.calibration import CalibrationResult, run_calibration
from ovgaussian.view.config import ViewConfig
from ovgaussian.view.field import QueryField
from ovgaussian.view.relevancy import DEFAULT_TEMPERATURE
from ovgaussian.view.scene import load_view_scene
from ovgaussian.view.state import ViewerState
from seggaussian.core.constants import read_class_names


def run_vocabulary(run: Path) -> tuple[str, ...]:
    """The class names a run was trained on, in its column order (``config.json``: ``vocabulary.names``, else the
    top-100 names of ``vocabulary.class_ids``); ``()`` when it records neither."""
    vocabulary = read_json(Path(run) / CONFIG_NAME).get("vocabulary", {})
    names = tuple(vocabulary.get("names") or ())
    if names:
        return names
    ids = vocabulary.get("class_ids") or ()
    all_names = read_class_names()
    return tuple(all_names[int(i)] for i in ids if 0 <= int(i) < len(all_names))


def run_temperature(run: Path | None) -> float:
    """The softmax temperature a run was trained at (``config.json``: ``train.loss.temperature``), the scale of its
    scores; ``DEFAULT_TEMPERATURE`` when there is no run or it records none."""
    if run is None:
        return DEFAULT_TEMPERATURE
    value = read_json(Path(run) / CONFIG_NAME).get("train", {}).get("loss", {}).get("temperature")
    if value is None:
        return DEFAULT_TEMPERATURE
    if not float(value) > 0:
        raise ValueError(f"{Path(run) / CONFIG_NAME}: train.loss.temperature must be > 0, got {value}")
    return float(value)


def build_state(config: ViewConfig, predictor=None, progress: Callable[[str], None] | None = None) -> ViewerState:
    """The scene of ``config`` and, with a run (or a ready ``predictor``), its language field and vocabulary."""
    say = progress or (lambda _message: None)
    scene = load_view_scene(config.scene, config.dataset, config.scene_id, config.frame, config.on_invalid,
                            config.cameras)
    say(f"view: {len(scene.gaussians):,} Gaussians from {scene.source}")
    if predictor is None and config.run is None:
        if config.vocabulary or config.queries:
            raise ValueError(f"{scene.source}: --vocab and --query need a trained run (--run RUN)")
        return ViewerState(scene)
    if predictor is None:
        predictor = load_model_predictor(config.run, config.checkpoint, device=config.device)
    vocabulary = tuple(config.vocabulary)
    if not vocabulary and config.run is not None:
        vocabulary = run_vocabulary(config.run)
    if not vocabulary:
        raise ValueError(f"{config.run}: the run records no training vocabulary; give the class names with --vocab")
    start = time.perf_counter()
    vectors = predictor.encode_gaussians(scene.gaussians)
    field = QueryField.from_predictor(predictor, vectors)
    temperature = run_temperature(config.run)
    calibration = CalibrationResult({}, None, "relevancy offsets 0 (--no-calibrate)")
    if config.run is not None and config.calibrate:
        calibration = run_calibration(config.run, predictor, vocabulary, config.negatives, temperature, say,
                                      dataset=config.dataset)
    elif config.run is None:
        calibration = CalibrationResult({}, None, "relevancy offsets 0 (no run folder)")
    say(f"view: {calibration.note}")
    state = ViewerState(scene, field, vocabulary, config.negatives, temperature, calibration.offsets,
                        calibration.note)
    field.scores(state.competitors)  # the text encoder's first load, and the competitors' columns, before any query
    say(f"view: language field of {len(field):,} Gaussians ready in {time.perf_counter() - start:.1f} s")
    return state


class ViewReport(NamedTuple):
    """What ``run_view`` did: the JSON summary and, for ``--export``, the file written."""

    summary: dict
    export: Path | None = None


def _summary(config: ViewConfig, state: ViewerState, viewer) -> dict:
    return {
        "source": state.scene.source,
        "num_gaussians": int(len(state.scene.gaussians)),
        "details": state.scene.details,
        "run": None if config.run is None else str(config.run),
        "modes": list(state.modes),
        "mode": viewer.mode,
        "queries": list(viewer.queries),
        "threshold": float(viewer.threshold_input.value),
        "vocabulary": list(state.vocabulary),
        "negatives": list(state.negatives) if state.field is not None else [],
        "temperature": state.temperature if state.field is not None else None,
        "relevancy_offsets": dict(state.offsets) if state.field is not None else {},
        "relevancy_calibration": state.calibration_note if state.field is not None else None,
        "status": None if viewer.last is None else viewer.last.status,
        "cameras": len(state.scene.cameras),
        "start_camera": None if viewer.start_camera is None else state.scene.cameras[viewer.start_camera].name,
    }


#: How often the serving loop looks at its stop event (seconds): the delay between Ctrl-C and the shutdown.
STOP_POLL_SECONDS = 0.2


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event):
    """While inside, Ctrl-C and SIGTERM only set ``stop`` (main thread only; the handlers are restored after), so an
    interrupt never lands inside the server's or the GUI's code half-way through a call, nor between printing the
    URL and serving."""
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run_view(config: ViewConfig, *, predictor=None, progress: Callable[[str], None] | None = None,
             stop: threading.Event | None = None, on_ready: Callable | None = None) -> ViewReport:
    """Serve the viewer until ``stop`` is set or Ctrl-C (``KeyboardInterrupt``), or with ``config.export`` write
    the file and return at once. ``on_ready(viewer)`` is called once the server is up (its URL is known)."""
    if config.export is not None and Path(config.export).suffix.lower() not in (".html", ".viser"):
        raise ValueError(f"{config.export}: export to .html (self-contained page) or .viser (viser recording)")
    state = build_state(config, predictor, progress)
    exporting = config.export is not None
    viewer = QueryViewer(state, host="127.0.0.1" if exporting else config.host, port=0 if exporting else config.port,
                         mode=config.mode, queries=config.queries, threshold=config.threshold)
    try:
        summary = _summary(config, state, viewer)
        if exporting:
            size = viewer.export(config.export)
            summary.update(export=str(config.export), export_bytes=size)
            return ViewReport(summary, Path(config.export))
        summary.update(url=viewer.url, host=config.host, port=viewer.port)
        started = time.monotonic()
        with _stop_on_signals(stop or threading.Event()) as stopping:
            if on_ready is not None:
                on_ready(viewer)
            while not stopping.wait(STOP_POLL_SECONDS):
                pass
        summary.update(_summary(config, state, viewer), url=viewer.url, host=config.host, port=viewer.port,
                       served_seconds=round(time.monotonic() - started, 1))
        return ViewReport(summary)
    finally:
        viewer.stop()
