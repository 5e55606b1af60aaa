"""Stage sweeps: Pareto marking, the k-NN vote against its reference and the shipped transfer, quick
sweeps of every stage on one tiny synthetic scene, JSON round trip, table, plot and CLI."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from seggaussian.labels.config import TransferConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.render import render_label_maps
from seggaussian.render.results import BlendWeights
from seggaussian.tools.sweep.pareto import (
    PARETO_TIME_TOLERANCE,
    QUALITY_TOLERANCE,
    StageSweepResult,
    Trial,
    mark_pareto,
    one_at_a_time,
    pareto_mask,
)
from seggaussian.tools.sweep.run import run_stage_sweep
from seggaussian.tools.sweep.config import StageSweepConfig, quick_config, with_params
from seggaussian.tools.sweep.data import SweepDataError, prepare_data
from seggaussian.tools.sweep.render import labelled_only_blend
from seggaussian.tools.sweep.report import default_verdict, format_table, write_markdown
from seggaussian.labels.transfer import transfer_labels
from seggaussian.labels.vote import transfer_labels_vote, transfer_labels_vote_reference, vote

I = IGNORE_LABEL


# --- Pareto front on hand-made trials -------------------------------------------------------------------
def _trial(seconds, quality, knob="k", default=False):
    return Trial("transfer", knob, {"x": seconds}, seconds, quality, {}, default)


def test_pareto_marking_hand_made():
    #            0: fast+bad  1: dominated by 0  2: slow+good  3: best quality  4: dominated by 3  5: NaN
    seconds = [1.0, 2.0, 3.0, 5.0, 6.0, 0.5]
    quality = [0.5, 0.4, 0.8, 0.9, 0.9, math.nan]
    assert pareto_mask(seconds, quality).tolist() == [True, False, True, True, False, False]
    marked = mark_pareto([_trial(s, q) for s, q in zip(seconds, quality)])
    assert [t.pareto for t in marked] == [True, False, True, True, False, False]


def test_pareto_ties_and_tolerance():
    # identical rows: neither dominates the other
    assert pareto_mask([1.0, 1.0], [0.5, 0.5]).tolist() == [True, True]
    # same quality, 10% slower: dominated without tolerance, kept with a 15% tolerance (timing noise)
    assert pareto_mask([1.0, 1.1], [0.5, 0.5]).tolist() == [True, False]
    assert pareto_mask([1.0, 1.1], [0.5, 0.5], 0.15).tolist() == [True, True]
    # within the tolerance a better quality still wins
    assert pareto_mask([1.0, 1.1], [0.5, 0.6], 0.15).tolist() == [False, True]
    # far faster (beyond the tolerance) with equal quality dominates
    assert pareto_mask([1.0, 2.0], [0.5, 0.5], 0.15).tolist() == [True, False]
    assert pareto_mask([], []).tolist() == []
    # qualities within the quality tolerance are ties: the faster row dominates, a slower one never wins
    assert pareto_mask([1.0, 2.0], [0.5, 0.5005], 0.15, 1e-3).tolist() == [True, False]
    assert pareto_mask([1.0, 1.1], [0.5, 0.5005], 0.15, 1e-3).tolist() == [True, True]
    assert pareto_mask([1.0, 2.0], [0.5, 0.6], 0.15, 1e-3).tolist() == [True, True]


def test_one_at_a_time_rows():
    rows = one_at_a_time({"a": 1, "b": "x"}, {"a": (1, 2, 3), "b": ("x", "y")})
    assert rows == [("base", {"a": 1, "b": "x"}), ("a", {"a": 2, "b": "x"}), ("a", {"a": 3, "b": "x"}),
                    ("b", {"a": 1, "b": "y"})]


def test_default_verdict_names_dominating_row():
    trials = mark_pareto([_trial(2.0, 0.5, "base", default=True), _trial(1.0, 0.6, "fast")])
    result = StageSweepResult("transfer", "label_accuracy", trials, ["s"], [], {}, {})
    verdict = default_verdict(result)
    assert "NOT on the Pareto front" in verdict and "fast" in verdict
    ok = StageSweepResult("transfer", "label_accuracy", mark_pareto([_trial(1.0, 0.6, "base", True)]), [], [], {}, {})
    assert "is Pareto-optimal" in default_verdict(ok)


# --- k-NN vote ------------------------------------------------------------------------------------------
def test_vote_majority_and_ties():
    labels = np.array([[1, 2, 2], [1, 2, 3], [5, 5, 6], [7, 8, 8]])
    valid = np.array([[True, True, True], [True, True, True], [False, False, False], [True, True, False]])
    # row 0: 2 wins 2:1; row 1: three-way tie -> nearest; row 2: nothing valid; row 3: 8 twice but slot 2 invalid
    assert vote(labels, valid).tolist() == [2, 1, I, 7]


@pytest.mark.parametrize("backend", ["scipy", "open3d"])
def test_vote_k1_equals_shipped_transfer(backend):
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (400, 3))
    semantic = rng.integers(0, 5, 400).astype(np.int32)
    semantic[::7] = I
    means = rng.uniform(-0.2, 1.2, (300, 3))
    means[3] = np.nan
    points = np.concatenate([points, points[:50]])  # exact duplicates: the spacing skips them in both
    semantic = np.concatenate([semantic, semantic[:50]])
    cfg = replace(TransferConfig(), backend=backend, box_margin=0.0)
    shipped = transfer_labels(means, points, semantic, np.zeros(len(points), np.int32), None, cfg)
    labels, gate = transfer_labels_vote(means, points, semantic, 1, cfg)
    assert gate == pytest.approx(shipped.stats.gate) and shipped.stats.spacing > 0
    np.testing.assert_array_equal(labels, shipped.semantic)
    assert labels[3] == I
    assert (labels == I).sum() > 1 + (shipped.stats.beyond_gate + shipped.stats.outside_box)  # unlabelled nearest


@pytest.mark.parametrize("k", [1, 3, 5])
@pytest.mark.parametrize("candidates", ["all", "labelled"])
def test_vote_matches_brute_force_reference(k, candidates):
    rng = np.random.default_rng(k)
    points = rng.uniform(0, 1, (150, 3))
    semantic = rng.integers(0, 3, 150).astype(np.int32)
    semantic[:40] = I
    means = rng.uniform(0, 1, (80, 3))
    cfg = replace(TransferConfig(), max_distance=0.12, candidates=candidates)
    labels, gate = transfer_labels_vote(means, points, semantic, k, cfg)
    assert gate == 0.12
    np.testing.assert_array_equal(labels, transfer_labels_vote_reference(means, points, semantic, k, 0.12, candidates))
    assert (labels == I).any() and (labels != I).any()  # the gate both keeps and rejects


def test_vote_empty_inputs():
    cfg = TransferConfig()
    labels, _ = transfer_labels_vote(np.zeros((4, 3)), np.zeros((0, 3)), np.zeros(0, np.int32), 3, cfg)
    assert labels.tolist() == [I] * 4
    labels, _ = transfer_labels_vote(np.zeros((0, 3)), np.ones((5, 3)), np.zeros(5, np.int32), 3, cfg)
    assert labels.shape == (0,)


# --- quick sweeps on one tiny synthetic scene ---------------------------------------------------------
@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("stage_sweep")
    prepare_data(quick_config("transfer", work_dir=path))  # synthesized once for every stage
    return path


def _check_result(result: StageSweepResult, lo: float, hi: float) -> None:
    assert result.trials, "the table has no rows"
    assert any(t.pareto for t in result.trials)
    for t in result.trials:
        assert t.seconds > 0
        assert lo <= t.quality <= hi, (t.knob, t.quality)
    # Pareto flags agree with a direct recomputation
    again = mark_pareto(result.trials, PARETO_TIME_TOLERANCE, QUALITY_TOLERANCE[result.stage])
    assert [t.pareto for t in result.trials] == [t.pareto for t in again]
    # JSON round trip
    text = json.dumps(result.to_dict())
    back = StageSweepResult.from_dict(json.loads(text))
    assert back.trials == result.trials and back.stage == result.stage and back.scenes == result.scenes
    table = format_table(result)
    assert table.count("\n") == len(result.trials) + 1


def test_quick_transfer(work):
    result = run_stage_sweep(quick_config("transfer", work_dir=work))
    _check_result(result, 0.0, 1.0)
    by = {(t.knob, str(t.settings[t.knob] if t.knob != "base" else "")): t for t in result.trials}
    base = by[("base", "")]
    # the backends give the same labels; vertices only (no mesh samples) uses fewer label points
    assert by[("backend", "open3d")].quality == pytest.approx(base.quality, abs=0.01)
    assert by[("mesh_sample_spacing", "0.0")].metrics["label_points"] < base.metrics["label_points"]
    assert base.quality > 0.2 and base.settings["candidates"] == "all"
    for t in result.trials:
        m = t.metrics
        assert m["ignored_share"] + m["wrong_label_share"] == pytest.approx(1.0 - m["label_accuracy"])
        kept = m["unlabelled_kept"] * m["unlabelled"]
        assert t.quality == pytest.approx((m["correct"] + kept) / m["gaussians"])
    # the synthetic room has unlabelled surfaces (rug, clutter, masked disc): the labelled-only rule spills
    labelled_only = by[("candidates", "labelled")]
    assert base.metrics["unlabelled"] > 0
    assert base.metrics["unlabelled_kept"] > labelled_only.metrics["unlabelled_kept"]
    assert base.metrics["spacing_median"] > 0.0  # measured between distinct points, never 0


def test_quick_render(work):
    result = run_stage_sweep(quick_config("render", work_dir=work))
    _check_result(result, 0.0, 1.0)
    rows = {t.knob + str(t.settings.get(t.knob)): t for t in result.trials}
    base = rows["base" + "None"]
    assert base.is_default  # quick keeps the shipped top_k / min_alpha / scale
    fast, ref = rows["backendfast"], rows["backendreference"]
    # the fast and the reference paths agree at the tiny width
    assert fast.quality == pytest.approx(ref.quality, abs=0.02)
    assert fast.metrics["feature_residual_mean"] == pytest.approx(ref.metrics["feature_residual_mean"], abs=1e-3)
    # fewer contributors -> more weight left out of the blend weights
    assert rows["top_k2"].metrics["residual_alpha_mean"] > base.metrics["residual_alpha_mean"]
    # the former rule (unlabelled contributors do not vote) labels more pixels of unlabelled surfaces
    before = rows["votelabelled_only"]
    assert base.metrics["unlabelled_pixels"] > 0
    assert base.metrics["unlabelled_kept"] >= before.metrics["unlabelled_kept"]
    assert base.settings["vote"] == "ignore_occludes" and base.quality >= before.quality - 1e-9
    for t in result.trials:
        assert 0.0 <= t.metrics["feature_residual_mean"] <= 1.0
        assert 0.0 <= t.metrics["residual_alpha_mean"] <= 1.0


def test_quick_fit(work):
    config = quick_config("fit", work_dir=work)
    base = dict(config.fit.base, iterations=4, eval_every=2, densify_from=2, densify_until=2, densify_every=2,
                max_gaussians=300)
    config = replace(config, fit=replace(config.fit, base=base, iterations=(2,), downscale=(), max_gaussians=(),
                                         patience=()))
    result = run_stage_sweep(config)
    _check_result(result, 5.0, 60.0)  # novel-view PSNR in dB
    assert [t.knob for t in result.trials] == ["base", "iterations"]
    assert [t.metrics["iterations_run"] for t in result.trials] == [4, 2]
    assert not any(t.is_default for t in result.trials)  # quick overrides the shipped FitConfig
    for t in result.trials:
        assert 0.0 <= t.metrics["novel_ssim"] <= 1.0 and 0.0 <= t.metrics["novel_l1"] <= 1.0


def test_quick_build(work):
    result = run_stage_sweep(quick_config("build", work_dir=work))
    _check_result(result, 0.0, 1.0)
    fresh, rerun = result.trials
    assert fresh.settings["cache"] == "off" and rerun.settings["cache"] == "on"
    assert fresh.metrics["stages_run"] == 3 and fresh.metrics["stages_cached"] == 0
    assert rerun.metrics["stages_run"] == 0 and rerun.metrics["stages_cached"] == 3
    assert rerun.quality == 1.0 and rerun.is_default and rerun.pareto
    from seggaussian.tools.sweep.report import format_build_scenes

    per_scene = format_build_scenes(result).splitlines()
    assert len(per_scene) == 2 + 2 * len(result.scenes)
    assert "gaussians,transfer,views" in per_scene[2] and per_scene[3].count("gaussians,transfer,views") == 1
    assert "ray" not in str(result.skipped) or "not installed" in str(result.skipped)


def test_markdown_and_plot(work, tmp_path):
    trials = mark_pareto([_trial(1.0, 0.5, "base", True), _trial(0.5, 0.4, "fast"), _trial(2.0, 0.7, "slow")])
    result = StageSweepResult("transfer", "label_accuracy", trials, ["s"], ["executor ray: missing"],
                              {"cpus": 2, "load_average_1min": 9.0, "under_load": True}, {})
    md = write_markdown([result], tmp_path / "stages.md", "seggaussian bench --stage transfer")
    text = md.read_text()
    assert "seggaussian bench --stage transfer" in text and "measured under load" in text and "| PD |" in text
    pytest.importorskip("matplotlib")
    from seggaussian.tools.sweep.report import plot_trials

    png = plot_trials([result], tmp_path / "plot.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- errors and CLI -------------------------------------------------------------------------------------
def test_bad_data_errors(tmp_path):
    with pytest.raises(SweepDataError, match="does not exist"):
        prepare_data(StageSweepConfig(stage="transfer", data=tmp_path / "missing"))
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "manifest.json").write_text("{}")
    with pytest.raises(SweepDataError, match="built DATASET"):
        prepare_data(StageSweepConfig(stage="transfer", data=tmp_path / "ds"))
    with pytest.raises(ValueError, match="stage must be one of"):
        StageSweepConfig(stage="nope")


def test_cli_quick_json(work, tmp_path):
    from click.testing import CliRunner

    from cli.seg_bench import command

    out = CliRunner().invoke(command, ["--stage", "transfer", "--quick", "--work-dir", str(work), "--json"])
    assert out.exit_code == 0, out.output
    payload = json.loads(out.stdout)  # progress goes to stderr, the JSON document alone to stdout
    assert "[bench] transfer base" in out.stderr
    result = StageSweepResult.from_dict(payload["results"][0])
    assert result.stage == "transfer" and result.trials
    assert payload["summary"].startswith("bench transfer:")
    # re-render the saved JSON without re-running
    saved = tmp_path / "t.json"
    saved.write_text(out.stdout)
    out2 = CliRunner().invoke(command, ["--from-json", str(saved), "--markdown", str(tmp_path / "s.md")])
    assert out2.exit_code == 0, out2.output
    assert "| mark |" in (tmp_path / "s.md").read_text()


def test_with_params_overrides_and_errors():
    config = with_params(StageSweepConfig(stage="fit"), ("iterations=100,200", "patience=", "eval_scale=0.5"),
                         ("downscale=4", "iterations=200"))
    assert config.fit.iterations == (100, 200) and config.fit.patience == () and config.fit.eval_scale == 0.5
    assert config.fit.base == {"downscale": 4.0, "iterations": 200}
    config = with_params(StageSweepConfig(stage="build"), ("cache=off,on", "executors=local"))
    assert config.build.cache == (False, True) and config.build.executors == ("local",)
    with pytest.raises(ValueError, match="--param 'nope=1'"):
        with_params(StageSweepConfig(stage="render"), ("nope=1",))
    with pytest.raises(ValueError, match="--param 'top_k=x'"):
        with_params(StageSweepConfig(stage="render"), ("top_k=x",))
    with pytest.raises(ValueError, match="FitConfig field"):
        with_params(StageSweepConfig(stage="fit"), (), ("nope=1",))


def test_labelled_only_replay_is_the_former_vote():
    # the former rule, written out per pixel: only labelled contributors vote, coverage uses all weights
    rng = np.random.default_rng(3)
    h, w, k, n = 6, 7, 5, 12
    ids = rng.integers(-1, n, (h, w, k))
    weights = np.where(ids >= 0, rng.random((h, w, k)) * 0.3, 0.0).astype(np.float32)
    residual = (rng.random((h, w)) * 0.2).astype(np.float32)
    semantic = rng.integers(0, 3, n)
    semantic[rng.random(n) < 0.4] = I
    blend = BlendWeights(torch.as_tensor(ids), torch.as_tensor(weights), torch.as_tensor(residual))
    replay = render_label_maps(labelled_only_blend(blend, torch.as_tensor(semantic)), torch.as_tensor(semantic),
                               torch.zeros(n, dtype=torch.int64), 3, min_alpha=0.4).semantic.numpy()
    expected = np.full((h, w), I)
    for y in range(h):
        for x in range(w):
            if weights[y, x].sum() + residual[y, x] < 0.4:
                continue
            tally: dict[int, float] = {}
            for j in range(k):  # front-most first: ties keep the earlier label
                if ids[y, x, j] >= 0 and weights[y, x, j] > 0 and semantic[ids[y, x, j]] != I:
                    tally[int(semantic[ids[y, x, j]])] = tally.get(int(semantic[ids[y, x, j]]), 0.0) + weights[y, x, j]
            if tally:
                expected[y, x] = max(tally, key=lambda c: tally[c])  # first maximum in insertion order
    np.testing.assert_array_equal(replay, expected)
    shipped = render_label_maps(blend, torch.as_tensor(semantic), torch.zeros(n, dtype=torch.int64), 3, min_alpha=0.4)
    assert (shipped.semantic.numpy() == I).sum() > (replay == I).sum()  # ignore now wins some pixels
