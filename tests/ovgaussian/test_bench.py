"""Benchmark protocol with stand-in predictors, stand-in scenes and a one-contributor-per-pixel blend."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from ovgaussian.bench import baselines as baseline
from ovgaussian.bench.evaluate import evaluate, result_to_dict, table1_header, table1_row
from ovgaussian.predict.view_labels import BlendFunctions
from ovgaussian.text.vocabulary import make_vocabulary, to_vocabulary_labels
from seggaussian.core.constants import IGNORE_LABEL, SH_C0, read_class_names
from seggaussian.core.gaussians import Gaussians

I = IGNORE_LABEL
NAMES = read_class_names()
ID = {n: NAMES.index(n) for n in NAMES}
# K = 7: wall floor chair + the four unseen classes (curtain bookshelf sofa bed), in this order
VOCAB = make_vocabulary([ID["wall"], ID["floor"], ID["chair"], ID["curtain"], ID["bookshelf"], ID["sofa"], ID["bed"]])
W, F, C, SOFA = 0, 1, 2, 5  # vocabulary indices


# --- stand-ins ---------------------------------------------------------------------------------
def fake_blend(gaussians, camera, top_k):
    """``camera`` is a stand-in: an [H, W] map of the Gaussian seen at each pixel (-1 = nothing)."""
    ids = np.asarray(camera)[..., None].astype(np.int64)
    weights = (ids >= 0).astype(np.float32)

    def rows(r0, r1):
        return SimpleNamespace(ids=ids[r0:r1], weights=weights[r0:r1],
                               residual_alpha=np.zeros((r1 - r0, ids.shape[1]), np.float32))

    return SimpleNamespace(height=ids.shape[0], rows=rows)


def fake_render(blend, vectors):
    gathered = vectors[np.maximum(blend.ids, 0)]  # [H, W, K, F]
    return (gathered * blend.weights[..., None]).sum(axis=2)


FUNCS = BlendFunctions(fake_blend, fake_render)


def make_scene(scene_id, semantic, views=(), colours=None):
    semantic = np.asarray(semantic, dtype=np.int32)
    n = semantic.size
    rng = np.random.default_rng(0)
    sh = np.zeros((n, 1, 3), np.float32)
    if colours is not None:
        sh[:, 0] = (np.asarray(colours, np.float32) - 0.5) / SH_C0
    g = Gaussians.from_arrays(rng.normal(size=(n, 3)), np.tile([1, 0, 0, 0], (n, 1)), np.full((n, 3), -3.0),
                              np.zeros(n), sh, extras={"semantic": semantic})
    view_records = []
    for name, role, pixel_ids in views:
        pixel_ids = np.asarray(pixel_ids)
        gt = np.where(pixel_ids >= 0, semantic[np.maximum(pixel_ids, 0)], I).astype(np.int32)
        view_records.append(SimpleNamespace(name=name, role=role, camera=pixel_ids, rgb=None, semantic=gt, instance=None))
    return SimpleNamespace(scene_id=scene_id, source="synthetic", gaussians=g, views=view_records)


Oracle = baseline.GroundTruthPredictor


class Constant:
    name = "constant"

    def __init__(self, class_id):
        self.class_id = class_id

    def encode(self, scene):
        return np.zeros((len(scene.gaussians), 1), np.float32)

    def classify(self, vectors, class_ids):
        return np.tile((np.asarray(class_ids) == self.class_id).astype(np.float64), (vectors.shape[0], 1))


class Remap(Oracle):
    """The oracle with some top-100 ids replaced before encoding (a predictor that confuses classes)."""

    def __init__(self, mapping):
        self.mapping = mapping

    def encode(self, scene):
        v = super().encode(scene)
        out = v.copy()
        for src, dst in self.mapping.items():
            out[:, src] = 0
            out[:, dst] += v[:, src]
        return out


def dataset():
    """val: one scene, train: one scene with a novel view, xval: one scene with wall and chair only."""
    val = make_scene(
        "val0",
        [ID["wall"], ID["wall"], ID["chair"], ID["sofa"], I, ID["toilet"]],
        views=[("v0", "train", [[0, 1, 2], [3, -1, 5]]), ("v1", "novel", [[4, 0, 0], [-1, -1, 3]])],
    )
    train = make_scene(
        "tr0",
        [ID["floor"], ID["chair"], ID["bed"], ID["wall"]],
        views=[("t0", "train", [[0, 0, 1], [2, 3, 3]]), ("n0", "novel", [[1, 1, 2], [0, -1, 3]])],
    )
    xval = make_scene("xv0", [ID["wall"], ID["chair"], ID["chair"], I],
                      views=[("x0", "train", [[0, 1, 2], [3, 3, -1]])])
    return {"val": [val], "train": [train], "xval": [xval]}


def run(predictor, **kwargs):
    return evaluate(predictor, dataset(), VOCAB, functions=FUNCS, **kwargs)


def miou(result, dim, metric):
    return result.results[(dim, metric)].scores.miou


# --- tests -------------------------------------------------------------------------------------
def test_vocabulary_and_label_mapping():
    assert VOCAB.names == ("wall", "floor", "chair", "curtain", "bookshelf", "sofa", "bed")
    np.testing.assert_array_equal(VOCAB.unseen, [3, 4, 5, 6])
    labels = np.array([ID["chair"], ID["toilet"], I, ID["bed"]], np.int32)
    np.testing.assert_array_equal(to_vocabulary_labels(labels, VOCAB), [C, I, I, 6])
    with pytest.raises(ValueError, match="scene x.*neither a top-100 id"):
        to_vocabulary_labels(np.array([100, -2]), VOCAB, "scene x")
    with pytest.raises(ValueError, match="duplicate"):
        make_vocabulary([0, 0])


def test_oracle_scores_one_everywhere():
    result = run(Oracle())
    for key, r in result.results.items():
        assert r.scores.miou == pytest.approx(1.0), key
    assert set(result.results) == {("3d", "CSA"), ("3d", "OVA"), ("3d", "CDA"),
                                   ("2d", "CSA"), ("2d", "OVA"), ("2d", "NVA"), ("2d", "CDA")}
    assert "| oracle | 100.00 | 100.00 | 100.00 | 100.00 | 100.00 | 100.00 | 100.00 |" == table1_row("oracle", result)
    # uncovered pixels of the val views have no ground truth here: nothing unpredicted
    assert result.results[("2d", "CSA")].scores.num_unpredicted == 0


def test_constant_predictor_hand_computed():
    result = run(Constant(ID["wall"]), dims=("3d",), metrics=("CSA", "OVA"))
    # 3D val: scored Gaussians wall, wall, chair, sofa (ignore and toilet are not scored)
    # IoU wall = 2/4, chair = 0/1, sofa = 0/1 -> CSA = (0.5 + 0 + 0) / 3; OVA over unseen: only sofa -> 0
    assert miou(result, "3d", "CSA") == pytest.approx(0.5 / 3)
    assert miou(result, "3d", "OVA") == 0.0
    r = result.results[("3d", "CSA")]
    assert r.scores.num_samples == 4
    np.testing.assert_array_equal(r.scores.scored_classes, [W, C, SOFA])

    result = run(Constant(ID["sofa"]), dims=("3d", "2d"), metrics=("CSA", "OVA"))
    assert miou(result, "3d", "OVA") == pytest.approx(1 / 4)  # sofa: TP 1, FP 3
    assert miou(result, "3d", "CSA") == pytest.approx(0.25 / 3)
    # 2D val views: covered pixels map to Gaussians 0,1,2,3,5 (v0) and 4,0,0,3 (v1)
    # scored (GT in vocabulary): v0 wall, wall, chair, sofa; v1 wall, wall, sofa -> 7 pixels, 2 sofa
    # v0 pixel (1,1) and v1 pixels (1,0),(1,1) are uncovered with IGNORE ground truth: not scored
    assert result.results[("2d", "CSA")].scores.num_samples == 7
    assert miou(result, "2d", "OVA") == pytest.approx(2 / 7)
    assert miou(result, "2d", "CSA") == pytest.approx((2 / 7) / 3)


def test_uncovered_pixel_with_label_is_a_miss():
    scene = make_scene("s", [ID["wall"], ID["floor"]], views=[("v", "train", [[0, 1]])])
    scene.views[0].semantic[0, 1] = ID["floor"]
    scene.views[0].camera[0, 1] = -1  # the floor pixel is not covered by any Gaussian
    result = evaluate(Oracle(), {"val": [scene]}, VOCAB, metrics=("CSA",), dims=("2d",), functions=FUNCS)
    s = result.results[("2d", "CSA")].scores
    assert s.num_unpredicted == 1
    assert s.iou[W] == 1.0 and s.iou[F] == 0.0 and s.miou == pytest.approx(0.5)


def test_ova_scores_unseen_classes_only():
    # seen classes confused (chair -> floor, wall -> floor), unseen ones right
    result = run(Remap({ID["chair"]: ID["floor"], ID["wall"]: ID["floor"]}))
    assert miou(result, "3d", "OVA") == 1.0 and miou(result, "2d", "OVA") == 1.0
    assert miou(result, "3d", "CSA") < 1.0 and miou(result, "2d", "CSA") < 1.0
    np.testing.assert_array_equal(result.results[("3d", "OVA")].classes, VOCAB.unseen)


def test_cda_scores_common_classes_only():
    result = run(Remap({ID["chair"]: ID["sofa"]}), metrics=("CDA",))
    np.testing.assert_array_equal(result.common_classes, [W, C])
    # xval 3D: wall right; both chairs predicted sofa -> chair IoU 0, wall IoU 1; sofa's FP not averaged
    assert miou(result, "3d", "CDA") == pytest.approx(0.5)
    assert np.isfinite(result.results[("3d", "CDA")].scores.iou[SOFA])  # scored in the matrix, not averaged
    # a predictor perfect on the common classes scores 1.0 whatever it does elsewhere
    result = run(Remap({ID["floor"]: ID["bed"]}), metrics=("CDA",))
    assert miou(result, "3d", "CDA") == 1.0 and miou(result, "2d", "CDA") == 1.0


def test_nva_uses_novel_views_of_train_scenes_only():
    # wrong on every val scene label (val has no floor/bed), right on the train scene
    result = run(Remap({ID["wall"]: ID["bed"], ID["chair"]: ID["bed"], ID["sofa"]: ID["bed"]}),
                 metrics=("NVA", "CSA"))
    nva = result.results[("2d", "NVA")]
    assert nva.split == "train" and nva.num_views == 1 and nva.num_scenes == 1
    assert nva.scores.num_samples == 5  # the novel view's covered, labelled pixels
    assert ("3d", "NVA") not in result.results
    assert miou(result, "2d", "CSA") == 0.0
    # the remap does hit the train scene (wall, chair -> bed), so NVA is below 1 but above 0
    assert 0.0 < nva.scores.miou < 1.0


def test_empty_split_reports_none_not_nan():
    result = evaluate(Oracle(), {"val": []}, VOCAB, metrics=("CSA", "CDA"), dims=("3d",), functions=FUNCS)
    assert miou(result, "3d", "CSA") is None and miou(result, "3d", "CDA") is None
    payload = result_to_dict(result)
    text = json.dumps(payload, allow_nan=True)
    assert "NaN" not in json.dumps(payload["row"])
    assert payload["row"]["3d_CSA"] is None
    assert "|" in table1_header() and table1_row("x", result).count("-") == 7
    assert text


def test_bad_predictor_output_named():
    class Bad(Oracle):
        def encode(self, scene):
            return super().encode(scene)[:-1]

    with pytest.raises(ValueError, match="scene val0: predictor returned vectors of shape"):
        run(Bad(), dims=("3d",), metrics=("CSA",))

    class NaNs(Oracle):
        def encode(self, scene):
            v = super().encode(scene)
            v[0, 0] = np.nan
            return v

    with pytest.raises(ValueError, match="non-finite"):
        run(NaNs(), dims=("3d",), metrics=("CSA",))
    with pytest.raises(ValueError, match="unknown metrics"):
        run(Oracle(), metrics=("XYZ",))
    with pytest.raises(ValueError, match="NVA exists in 2D only"):
        run(Oracle(), metrics=("NVA",), dims=("3d",))


def test_json_payload_has_per_class_iou():
    payload = result_to_dict(run(Oracle()))
    csa = payload["metrics"]["3d"]["CSA"]
    assert csa["per_class_iou"]["wall"] == 1.0 and csa["per_class_iou"]["floor"] is None  # absent: not scored
    assert payload["vocabulary"]["common"] == ["wall", "chair"]
    assert payload["vocabulary"]["unseen"] == ["curtain", "bookshelf", "sofa", "bed"]
    json.dumps(payload, allow_nan=False)


def test_baselines_fit_on_train_split_only():
    palette = {ID["wall"]: (0.9, 0.9, 0.9), ID["floor"]: (0.4, 0.2, 0.1), ID["chair"]: (0.1, 0.1, 0.8),
               ID["bed"]: (0.8, 0.1, 0.1), ID["sofa"]: (0.1, 0.8, 0.1)}
    labels = [ID["wall"]] * 5 + [ID["floor"]] * 3 + [ID["chair"]] * 2 + [ID["bed"]] * 2
    train = make_scene("tr", labels, colours=[palette[c] for c in labels])
    stats = baseline.collect_class_statistics([train])
    assert stats.counts[ID["wall"]] == 5 and stats.counts[ID["bed"]] == 0  # unseen class dropped
    np.testing.assert_allclose(stats.colour_sums[ID["floor"]] / 3, palette[ID["floor"]], atol=1e-6)

    test_labels = [ID["wall"], ID["floor"], ID["chair"], ID["sofa"]]
    val = make_scene("va", test_labels, colours=[palette[c] for c in test_labels],
                     views=[("v", "train", [[0, 1], [2, 3]])])
    colour = baseline.NearestColourPredictor(stats)
    result = evaluate(colour, {"val": [val]}, VOCAB, metrics=("CSA", "OVA"), functions=FUNCS)
    # seen classes right, the sofa (unseen) can never be predicted
    for dim in ("3d", "2d"):
        s = result.results[(dim, "CSA")].scores
        # the green sofa is nearest to the brown floor: floor TP 1, FP 1
        assert s.iou[W] == 1.0 and s.iou[C] == 1.0 and s.iou[F] == 0.5 and s.iou[SOFA] == 0.0
        assert miou(result, dim, "OVA") == 0.0

    majority = baseline.MajorityPredictor(stats)
    result = evaluate(majority, {"val": [val]}, VOCAB, metrics=("CSA",), dims=("3d",), functions=FUNCS)
    assert result.results[("3d", "CSA")].scores.iou[W] == pytest.approx(1 / 4)


def test_default_thresholds_match_the_renderer():
    from ovgaussian.predict.config import DEFAULT_MIN_ALPHA
    from seggaussian.render import DEFAULT_TOP_K, LABEL_MIN_ALPHA
    from ovgaussian.bench.config import BenchConfig

    assert DEFAULT_MIN_ALPHA == LABEL_MIN_ALPHA
    assert BenchConfig().blend_top_k == DEFAULT_TOP_K


def test_real_renderer_oracle_matches_rendered_label_maps():
    """With the real blend weights, an oracle's 2D labels equal render_label_maps of the same Gaussians."""
    import torch

    from ovgaussian.bench.evaluate import predict_view_labels
    from ovgaussian.predict.view_labels import default_blend_functions
    from seggaussian.core.cameras import Camera, intrinsics, look_at
    from seggaussian.render import render_label_maps

    rng = np.random.default_rng(3)
    n = 60
    labels = rng.choice([ID["wall"], ID["chair"], ID["sofa"], ID["toilet"]], size=n).astype(np.int32)
    g = Gaussians.from_arrays(rng.uniform(-1, 1, (n, 3)) * [1, 1, 0.2], np.tile([1, 0, 0, 0], (n, 1)),
                              np.full((n, 3), np.log(0.15)), np.full(n, 2.0), np.zeros((n, 1, 3)),
                              extras={"semantic": labels})
    cam = Camera(intrinsics(20, 20, 16, 12), look_at([0, 0, 3], [0, 0, 0], up=(0, 1, 0)), 32, 24)
    funcs = default_blend_functions()
    blender = funcs.blend(g, cam, 16)
    scene = SimpleNamespace(gaussians=g)
    pred = predict_view_labels(Oracle(), Oracle().encode(scene), blender, VOCAB, funcs, 0.5)
    for band_rows in (1, 5, 24):  # streamed in bands of rows: the same labels as one band
        np.testing.assert_array_equal(
            predict_view_labels(Oracle(), Oracle().encode(scene), blender, VOCAB, funcs, 0.5, band_rows=band_rows), pred)
    stored = render_label_maps(blender.rows(0, 24), torch.as_tensor(labels.astype(np.int64)),
                               torch.zeros(n, dtype=torch.int64), len(NAMES)).semantic.numpy()
    gt = to_vocabulary_labels(stored, VOCAB)
    covered = gt != I
    assert covered.sum() > 50
    np.testing.assert_array_equal(pred[covered], gt[covered])


# --- end to end through real shards, the real renderer and the CLI --------------------------------
def _write_tiny_dataset(root):
    """3 scenes (train, val, xval) of labelled Gaussian blobs with views rendered by the real renderer."""
    import torch

    from seggaussian import shards
    from seggaussian.shards.config import ShardConfig
    from seggaussian.core.cameras import Camera, intrinsics, look_at
    from seggaussian.render import render_label_maps

    funcs = __import__("ovgaussian.bench.evaluate", fromlist=["x"]).default_blend_functions()
    config = ShardConfig(row_group_bytes=4096)
    plan = {"tr0": ("train", ["wall", "floor", "chair", "toilet"]), "va0": ("val", ["wall", "chair", "sofa", "bed"]),
            "xv0": ("xval", ["wall", "chair"])}
    scenes = {}
    for j, (sid, (split, classes)) in enumerate(plan.items()):
        rng = np.random.default_rng(j)
        n = 160
        labels = np.array([ID[classes[i % len(classes)]] for i in range(n)], np.int32)
        centres = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, len(classes), endpoint=False)])
        means = centres[np.arange(n) % len(classes)] * 0.8 + rng.normal(scale=0.15, size=(n, 3))
        colours = np.array([[0.2 + 0.15 * (ID[c] % 5), 0.3, 0.6] for c in classes])[np.arange(n) % len(classes)]
        g = Gaussians.from_arrays(means, np.tile([1, 0, 0, 0], (n, 1)), np.full((n, 3), np.log(0.12)), np.full(n, 3.0),
                                  ((colours - 0.5) / SH_C0)[:, None, :],
                                  extras={"semantic": labels, "instance": np.arange(n, dtype=np.int32) % 7,
                                          "transfer_distance": np.zeros(n, np.float32)})
        rows = []
        for i, role in enumerate(("train", "train", "novel")):
            cam = Camera(intrinsics(18, 18, 16, 12), look_at([0.3 * i, 0.2, 3.0], [0, 0, 0], up=(0, 1, 0)), 32, 24)
            blend = funcs.blend(g, cam, 16).rows(0, 24)
            maps = render_label_maps(blend, torch.as_tensor(labels.astype(np.int64)),
                                     torch.zeros(n, dtype=torch.int64), len(NAMES))
            sem = maps.semantic.numpy().astype(np.int32)
            rows.append(shards.ViewRow(f"frame{i:06d}.jpg", role, cam, shards.encode_rgb(np.zeros((24, 32, 3), np.uint8)),
                                       shards.encode_label_map(sem), shards.encode_label_map(np.zeros_like(sem)),
                                       float((sem != I).mean())))
        frag = {}
        for table_name, table in (("gaussians", shards.gaussians_table(sid, g)), ("views", shards.views_table(sid, rows))):
            frag[table_name] = root / "cache" / sid / f"{table_name}.parquet"
            shards.write_parquet_atomic(frag[table_name], table_name, [table], config)
        scenes[sid] = {"fragments": frag, "source": "replica" if split == "xval" else "scannetpp"}
    dataset = root / "dataset"
    shards.write_dataset(dataset, {sid: split for sid, (split, _) in plan.items()}, scenes, config, NAMES, "h")
    return dataset


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    return _write_tiny_dataset(tmp_path_factory.mktemp("bench"))


def test_run_bench_oracle_on_real_shards(tiny_dataset):
    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.bench.config import BenchConfig

    report = run_bench(BenchConfig(dataset=tiny_dataset, num_classes=20, progress=False), predictor=Oracle())
    row = report.payload["row"]
    assert set(row) == {"3d_CSA", "3d_OVA", "3d_CDA", "2d_CSA", "2d_OVA", "2d_NVA", "2d_CDA"}
    for key, value in row.items():
        assert value == pytest.approx(1.0), key
    assert report.payload["vocabulary"]["common"] == ["wall", "chair"]
    assert report.payload["dataset"]["scenes"] == {"train": ["tr0"], "val": ["va0"], "xval": ["xv0"]}
    assert len(report.payload["dataset"]["manifest_sha256"]) == 64
    assert report.payload["metrics"]["2d"]["NVA"]["num_views"] == 1
    assert report.payload["metrics"]["2d"]["CSA"]["num_views"] == 3


def test_bench_cli_baseline_writes_json(tiny_dataset, tmp_path):
    from click.testing import CliRunner

    from cli.ov_bench import command

    out = tmp_path / "b.json"
    result = CliRunner().invoke(command, ["--data", str(tiny_dataset), "--predictor", "majority", "--classes", "20",
                                          "--out", str(out), "--no-progress"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("| method | 3D CSA | 3D OVA | 3D CDA | 2D CSA")
    assert lines[2].startswith("| majority |") and lines[-1].startswith("bench K=20 majority:")
    payload = json.loads(out.read_text())
    assert payload["predictor"] == {"kind": "majority", "fitted_on": "train"}
    # majority class of the train split among the vocabulary: wall/floor/chair tie (toilet is outside K=20)
    assert payload["row"]["3d_OVA"] == 0.0  # an unseen class is never the training majority
    result = CliRunner().invoke(command, ["--data", str(tiny_dataset), "--classes", "20"])
    assert result.exit_code != 0 and "--run is required" in result.output


def test_views_are_streamed_in_bands_and_nothing_is_cached(tiny_dataset, tmp_path):
    from ovgaussian.bench.evaluate import run_bench
    from ovgaussian.predict.view_labels import default_blend_functions
    from ovgaussian.bench.config import BenchConfig

    real = default_blend_functions()
    bands = []

    def recording_blend(gaussians, camera, top_k):
        blender = real.blend(gaussians, camera, top_k)
        full_rows = blender.rows

        def rows(r0, r1):
            bands.append(r1 - r0)
            return full_rows(r0, r1)

        return SimpleNamespace(height=blender.height, rows=rows)

    before = sorted(p for p in tiny_dataset.rglob("*"))
    whole = run_bench(BenchConfig(dataset=tiny_dataset, num_classes=20, progress=False, band_rows=1000),
                      predictor=Constant(ID["chair"]))
    banded = run_bench(BenchConfig(dataset=tiny_dataset, num_classes=20, progress=False, band_rows=5),
                       predictor=Constant(ID["chair"]), functions=BlendFunctions(recording_blend, real.render))
    assert banded.payload["confusion"] == whole.payload["confusion"]
    assert banded.payload["row"] == whole.payload["row"]
    assert bands and max(bands) == 5 and sum(bands) == 7 * 24  # 7 views of 24 rows, never more than 5 at once
    assert sorted(p for p in tiny_dataset.rglob("*")) == before  # no per-view blend cache written anywhere


def test_ground_truth_predictor_refuses_labels_outside_the_top100():
    g = Gaussians.from_arrays(np.zeros((2, 3)), np.tile([1, 0, 0, 0], (2, 1)), np.zeros((2, 3)), np.zeros(2),
                              np.zeros((2, 1, 3)), extras={"semantic": np.array([0, len(NAMES)], np.int32)})
    with pytest.raises(ValueError, match="scene s1: Gaussian labels outside the 100 top-100 ids"):
        Oracle().encode(SimpleNamespace(scene_id="s1", gaussians=g))
    g.extras["semantic"] = np.array([ID["sofa"], I], np.int32)  # IGNORE is no label: a zero vector
    vectors = Oracle().encode(SimpleNamespace(scene_id="s1", gaussians=g))
    assert vectors.sum(axis=1).tolist() == [1.0, 0.0] and vectors[0, ID["sofa"]] == 1.0
