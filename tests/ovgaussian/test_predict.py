"""``ovgaussian predict``: labels every Gaussian of a real 3DGS file with a tiny randomly-initialized run."""

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ovgaussian.predict.query import class_colours, paint_gaussians, parse_vocabulary, read_cameras
from seggaussian.core.constants import IGNORE_LABEL, SH_C0
from shared_data import REALDATA

VOCAB = "chair, table, sofa,  wooden floor"


def _tiny_run(run_dir: Path) -> Path:
    """A run folder in the trainer's layout holding a randomly-initialized slim network."""
    import torch

    from ovgaussian.run.checkpoint import CONFIG_NAME, build_network, save_checkpoint
    from ovgaussian.model.config import OVGaussianNetConfig
    from ovgaussian.run.config import TextConfig, config_to_dict
    from seggaussian.util.atomic import write_json_atomic

    model_config = OVGaussianNetConfig.slim(embedding_width=384, blocks=(1,) * 8, voxel_size=0.2)
    net = build_network(model_config)
    write_json_atomic(run_dir / CONFIG_NAME, {
        "model": config_to_dict(model_config),
        "train": {"text": config_to_dict(TextConfig())},
        "vocabulary": {"class_ids": [0, 1, 2]},
    })
    save_checkpoint(run_dir, 0, net, torch.optim.SGD(net.parameters(), lr=0.1), {"global_step": 0})
    return run_dir


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return _tiny_run(tmp_path_factory.mktemp("run"))


def _camera_file(path: Path, gaussians) -> Path:
    from seggaussian.core.cameras import look_at

    centre = np.median(gaussians.means, axis=0)
    extent = float(np.percentile(np.linalg.norm(gaussians.means - centre, axis=1), 90))
    eye = centre + np.array([0.0, -2.5 * extent, 0.5 * extent])
    K = [[30.0, 0, 24], [0, 30.0, 16], [0, 0, 1]]
    path.write_text(json.dumps({"cameras": [
        {"name": "front", "width": 48, "height": 32, "K": K, "viewmat": look_at(eye, centre).tolist()},
    ]}))
    return path


@pytest.mark.parametrize("name", ["loadersgl_train-1000.ply", "v3dg_donut_fused_sh0.ply"])
def test_predict_real_file_cli(name, run_dir, tmp_path):
    from cli.ov_predict import command
    from seggaussian.io.ply.reader import read_gaussians_ply

    scene = REALDATA / name
    if not scene.is_file():
        pytest.skip(f"{scene} absent (shared real data not mounted)")
    original, _ = read_gaussians_ply(scene)
    out = tmp_path / "labelled.ply"
    args = [str(scene), "--run", str(run_dir), "--vocab", VOCAB, "--out", str(out), "--json"]
    if name.startswith("loadersgl"):
        args += ["--cameras", str(_camera_file(tmp_path / "cams.json", original))]
    result = CliRunner().invoke(command, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)  # stderr may carry the text model's loading progress
    labelled, _ = read_gaussians_ply(out)
    assert len(labelled) == len(original) == summary["num_gaussians"]
    from seggaussian.io.ply.header import read_ply_header

    assert "ovgaussian semantic 3 = wooden floor" in read_ply_header(out).comments
    labels = labelled.extras["semantic"]
    assert labels.dtype == np.int32 and labels.min() >= 0 and labels.max() < 4
    assert summary["vocabulary"] == ["chair", "table", "sofa", "wooden floor"]
    assert sum(summary["counts"].values()) == len(original)
    assert sum(summary["shares"].values()) == pytest.approx(1.0)
    # geometry untouched, colours = class colours in f_dc and in red/green/blue
    np.testing.assert_array_equal(labelled.means, original.means)
    colours = class_colours(4)[labels]
    np.testing.assert_array_equal(np.stack([labelled.extras[c] for c in ("red", "green", "blue")], 1), colours)
    np.testing.assert_allclose(labelled.dc_colors(), colours / 255.0, atol=1e-5)
    assert labelled.sh_degree == 0
    if name.startswith("loadersgl"):
        import cv2

        assert len(summary["label_maps"]) == 2
        label_png = cv2.imread(summary["label_maps"][0], cv2.IMREAD_UNCHANGED)
        assert label_png.shape == (32, 48) and label_png.dtype == np.uint16
        assert set(np.unique(label_png)) <= {0, 1, 2, 3, IGNORE_LABEL}


def test_predict_is_deterministic_and_consistent_with_bench_predictor(run_dir, tmp_path):
    from ovgaussian.predict.config import PredictConfig
    from ovgaussian.predict.query import label_gaussians, load_model_predictor
    from seggaussian.io.ply.reader import read_gaussians_ply

    scene = REALDATA / "loadersgl_train-1000.ply"
    if not scene.is_file():
        pytest.skip(f"{scene} absent")
    g, _ = read_gaussians_ply(scene)
    predictor = load_model_predictor(run_dir)
    config = PredictConfig(run=run_dir, vocabulary=parse_vocabulary(VOCAB), chunk_rows=97)
    a = label_gaussians(predictor, g, config)
    b = label_gaussians(load_model_predictor(run_dir), g, PredictConfig(run=run_dir, vocabulary=config.vocabulary))
    np.testing.assert_array_equal(a.labels, b.labels)  # chunking and reloading change nothing
    # the same labels by hand: argmax cos(phi(s), text)
    import torch

    s = torch.as_tensor(predictor.encode_gaussians(g))
    with torch.no_grad():
        d = predictor.model.phi(s)
    text = predictor.text_embeddings(config.vocabulary)
    cos = torch.nn.functional.cosine_similarity(d[:, None, :], text[None], dim=-1)
    np.testing.assert_array_equal(a.labels, cos.argmax(1).numpy())


def test_vocabulary_parsing():
    assert parse_vocabulary(" chair,table ,, sofa  bed ") == ("chair", "table", "sofa bed")
    with pytest.raises(ValueError, match="no class names"):
        parse_vocabulary(" , ")
    with pytest.raises(ValueError, match="duplicate"):
        parse_vocabulary("chair, Chair")


def test_paint_modes():
    from seggaussian.core.gaussians import Gaussians

    rng = np.random.default_rng(0)
    g = Gaussians.from_arrays(rng.normal(size=(5, 3)), rng.normal(size=(5, 4)), rng.normal(size=(5, 3)),
                              rng.normal(size=5), rng.normal(size=(5, 4, 3)))
    labels = np.array([0, 1, 1, 2, 0])
    colours = class_colours(3)
    assert len({tuple(c) for c in colours}) == 3
    rgb_only = paint_gaussians(g, labels, colours, "rgb")
    np.testing.assert_array_equal(rgb_only.sh, g.sh)
    np.testing.assert_array_equal(rgb_only.extras["red"], colours[labels, 0])
    dc_only = paint_gaussians(g, labels, colours, "f_dc")
    assert "red" not in dc_only.extras and dc_only.sh.shape == (5, 1, 3)
    np.testing.assert_allclose(0.5 + SH_C0 * dc_only.sh[:, 0], colours[labels] / 255.0, atol=1e-6)
    with pytest.raises(ValueError, match="colour mode"):
        paint_gaussians(g, labels, colours, "hsv")


def test_camera_file_errors_name_the_field(tmp_path):
    bad = tmp_path / "cams.json"
    bad.write_text(json.dumps({"cameras": [{"name": "a", "width": 4, "height": 4, "K": np.eye(3).tolist()}]}))
    with pytest.raises(ValueError, match=r"cams.json: cameras\[0\]: missing field 'viewmat' or 'c2w'"):
        read_cameras(bad)
    bad.write_text("{")
    with pytest.raises(ValueError, match="cams.json: cannot read"):
        read_cameras(bad)
    bad.write_text(json.dumps([{"width": 4, "height": 4, "K": np.eye(3).tolist(), "c2w": np.eye(4).tolist()}]))
    ((name, cam),) = read_cameras(bad)
    assert name == "camera000" and cam.width == 4


def test_refuses_to_overwrite_input(run_dir, tmp_path):
    from ovgaussian.predict.config import PredictConfig
    from ovgaussian.predict.query import run_predict

    p = tmp_path / "x.ply"
    p.write_bytes(b"")
    with pytest.raises(ValueError, match="refusing to overwrite"):
        run_predict(p, p, PredictConfig(run=run_dir, vocabulary=("a",)))


class _NearestAxisPredictor:
    """Scores a Gaussian's classes by its position's coordinates (class i: coordinate i), no model."""

    checkpoint = None
    trained_names = ()

    def encode_gaussians(self, gaussians):
        return gaussians.means.astype(np.float32)

    def score_names(self, vectors, names):
        return vectors[:, : len(names)]


def test_predict_writes_labelled_gltf(tmp_path):
    """A .glb scene in, a .glb out: the labels as the _SEMANTIC attribute (the counts of the summary), the
    vocabulary and its colours in the file's extras, the class colours as its DC colour."""
    from ovgaussian.predict.config import PredictConfig
    from ovgaussian.predict.query import run_predict
    from seggaussian.core.gaussians import Gaussians
    from seggaussian.io.formats import write_gaussians
    from seggaussian.io.gltf import read_gltf

    rng = np.random.default_rng(4)
    n = 300
    scene = Gaussians.from_arrays(rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.uniform(-4, -2, (n, 3)),
                                  rng.normal(size=n), rng.normal(0, 0.3, (n, 4, 3)))
    glb = tmp_path / "scene.glb"
    write_gaussians(glb, scene)
    out = tmp_path / "labelled.glb"
    config = PredictConfig(run=tmp_path, vocabulary=("wall", "floor", "chair"), colour_mode="f_dc")
    report = run_predict(glb, out, config, predictor=_NearestAxisPredictor())
    summary = report.summary
    assert summary["scene_format"] == "gltf" and summary["out_format"] == "gltf"
    labelled = read_gltf(out)
    labels = labelled.gaussians.extras["semantic"]
    names = labelled.legend["semantic"]["names"]
    np.testing.assert_array_equal(labels, np.argmax(scene.means, axis=1))
    assert names == ["wall", "floor", "chair"] and summary["counts"] == {
        name: int((labels == i).sum()) for i, name in enumerate(names)}
    colours = np.asarray(labelled.legend["semantic"]["rgb"], np.float64)[labels]
    assert np.abs(labelled.gaussians.dc_colors() * 255 - colours).max() < 0.01


def test_predict_reads_and_writes_other_formats_with_legend(run_dir, tmp_path):
    from cli.ov_predict import command
    from seggaussian.io.formats import read_gaussians, write_gaussians
    from seggaussian.io.ply.reader import read_gaussians_ply

    scene = REALDATA / "loadersgl_train-1000.ply"
    if not scene.is_file():
        pytest.skip(f"{scene} absent (shared real data not mounted)")
    original, _ = read_gaussians_ply(scene)
    spz = tmp_path / "scene.spz"
    write_gaussians(spz, original)
    out = tmp_path / "labelled.compressed.ply"
    result = CliRunner().invoke(command, [str(spz), "--run", str(run_dir), "--vocab", VOCAB, "--out", str(out),
                                          "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["scene_format"] == "spz" and summary["out_format"] == "compressed_ply"
    labelled, _, fmt = read_gaussians(out)
    assert fmt == "compressed_ply" and len(labelled) == len(original)
    legend = json.loads((tmp_path / "labelled.compressed.legend.json").read_text())
    assert [e["name"] for e in legend["entries"]] == [n for n in summary["vocabulary"] if summary["counts"][n]]
    # every Gaussian shows one of the legend's colours (within the compressed colour step)
    colours = np.array([e["rgb"] for e in legend["entries"]], np.float64)
    distance = np.abs(labelled.dc_colors()[:, None, :] * 255 - colours[None]).max(axis=2).min(axis=1)
    assert distance.max() < 1.5
    # --color-by none keeps the scene's colours and writes no legend
    plain = tmp_path / "plain.ply"
    result = CliRunner().invoke(command, [str(spz), "--run", str(run_dir), "--vocab", VOCAB, "--out", str(plain),
                                          "--color-by", "none"])
    assert result.exit_code == 0, result.output
    kept, _ = read_gaussians_ply(plain)
    decoded, _, _ = read_gaussians(spz)
    np.testing.assert_array_equal(kept.sh, decoded.sh)
    assert "semantic" in kept.extras and not (tmp_path / "plain.legend.json").exists()
    # a .ksplat scene in, a .ksplat out (--format wins over the name)
    from seggaussian.io.ksplat import write_ksplat

    ksplat = tmp_path / "scene.ksplat"
    write_ksplat(ksplat, original, compression_level=0)
    out = tmp_path / "labelled.bin"
    result = CliRunner().invoke(command, [str(ksplat), "--run", str(run_dir), "--vocab", VOCAB, "--out", str(out),
                                          "--format", "ksplat", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["scene_format"] == "ksplat" and summary["out_format"] == "ksplat"
    labelled, _, fmt = read_gaussians(out)
    assert fmt == "ksplat" and len(labelled) == len(original)
