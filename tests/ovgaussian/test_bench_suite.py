"""The benchmark profile's rows, tables and checks, on hand-made bench payloads (the stages themselves are
the bench, train and build code, tested elsewhere; the profile runs them in benchmarks/, not in CI)."""

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ovgaussian.metrics import scores_from_confusion
from ovgaussian.suite import profile as S
from ovgaussian.suite import report as R
from ovgaussian.suite.config import ABLATION_ROWS, RUNS, TABLE1_ROWS, SuiteConfig, Table1Row

NAMES = ["wall", "chair", "sofa"]


def payload(values: dict, ci_halfwidth=0.02, chair_iou=0.3):
    """A bench payload with the given {(dim, metric): mIoU} and intervals of +- ci_halfwidth."""
    metrics = {}
    for (dim, metric), v in values.items():
        metrics.setdefault(dim, {})[metric] = {
            "miou": v, "ci95": [v - ci_halfwidth, v + ci_halfwidth],
            "per_class_iou": {"wall": 0.9, "chair": chair_iou, "sofa": 0.0}}
    confusion = np.zeros((3, 4), int)
    confusion[0, 0], confusion[1, 1], confusion[2, 0] = 50, 5, 7
    return {"metrics": metrics, "vocabulary": {"names": NAMES, "unseen": ["sofa"]},
            "confusion": {"val_3d": confusion.tolist(), "val_2d": confusion.tolist(),
                          "train_2d": confusion.tolist()}}


ALL = [("3d", "CSA"), ("3d", "OVA"), ("3d", "CDA"), ("2d", "CSA"), ("2d", "OVA"), ("2d", "NVA"), ("2d", "CDA")]


def test_checks_need_intervals_apart_from_both_baselines():
    base = {k: 0.2 for k in ALL}
    reports = {"majority": payload({k: 0.05 for k in ALL}), "colour": payload(base),
               "full": payload({k: (0.7 if k == ("2d", "NVA") else 0.5) for k in ALL})}
    runs = {"text-2d-only": payload({k: 0.3 for k in ALL}), "no-adapter": payload({k: 0.4 for k in ALL}),
            "full": reports["full"]}
    result = R.checks(reports, "full", ("majority", "colour"), runs)
    assert all(ok for ok, _ in result.values()), result
    close = dict(reports, colour=payload({**base, ("2d", "CDA"): 0.47}))  # intervals overlap on 2D CDA
    result = R.checks(close, "full", ("majority", "colour"), runs)
    assert not result["full beats both baselines on 2D CDA, intervals apart"][0]
    assert result["full beats both baselines on 3D CSA, intervals apart"][0]
    zero = dict(reports, full=payload({k: 0.5 for k in ALL}, chair_iou=0.0))
    result = R.checks(zero, "full", ("majority", "colour"), runs)
    assert result["every seen class of the val rooms above 0 IoU (3D)"] == (False, "zero: chair")
    assert not result["NVA >= 60"][0]
    swapped = dict(runs, **{"no-adapter": payload({k: 0.6 for k in ALL})})
    assert not R.checks(reports, "full", ("majority", "colour"), swapped)["ablation rows order as the paper's"][0]


def test_the_nva_check_says_what_the_unseen_classes_decide():
    # train_2d: wall 50 right, chair 5 right, all 7 sofa (unseen) pixels predicted wall.
    reports = {"full": payload({k: 0.5 for k in ALL})}
    ok, detail = R.checks(reports, "full", (), {})["NVA >= 60"]
    assert not ok
    assert "with every unseen pixel right it would be 100.0" in detail
    assert "the seen classes score 100.0 with the unseen pixels left out" in detail
    wrong_chair = payload({k: 0.5 for k in ALL})
    counts = np.array(wrong_chair["confusion"]["train_2d"])
    counts[1, 1], counts[1, 0] = 0, 5  # chair never right: seen classes (50/55 + 0) / 2
    wrong_chair["confusion"]["train_2d"] = counts.tolist()
    assert f"seen classes score {100 * 50 / 55 / 2:.1f}" in R.nva_unseen_share(wrong_chair)
    assert "unseen classes' IoU: sofa 0.0" in R.nva_unseen_share(wrong_chair)


def test_nva_is_reached_by_the_full_model_or_a_named_method_row():
    reports = {"full": payload({k: 0.5 for k in ALL}), "stacked": payload({k: 0.55 for k in ALL}),
               "transductive": payload({k: 0.62 for k in ALL}), "colour": payload({k: 0.9 for k in ALL})}
    ok, detail = R.checks(reports, "full", (), {}, (), ("stacked", "transductive"))["NVA >= 60"]
    assert ok and detail.startswith("reached by transductive;")
    assert "full: NVA 50.0 [48.0, 52.0]" in detail and "stacked: NVA 55.0" in detail
    # a baseline reaching 60 counts for nothing; without the method row the check fails
    ok, detail = R.checks(reports, "full", ("colour",), {}, (), ("stacked",))["NVA >= 60"]
    assert not ok and detail.startswith("reached by no row;") and "transductive" not in detail


def test_tables_show_values_and_intervals():
    reports = {"full": payload({k: 0.5 for k in ALL})}
    table = R.format_table1(reports)
    assert "| full | 50.0 [48.0, 52.0] |" in table and table.count("\n") == 3
    ablation = R.format_ablation({"full": reports["full"]}, vs_available=False)
    assert "(off: no CLIP)" in ablation and "43.84" in ablation and ablation.count("| - |") >= 3
    classes = R.format_classes(reports)
    assert "| chair | 30.0 |" in classes


def test_a_table1_row_is_one_line_of_bench_options():
    config = SuiteConfig(out=Path("/tmp/profile"))
    row = Table1Row("full + stacking", run="full", options=(("min_alpha", 0.25),))
    bench = S.bench_config(config, Path("/tmp/profile/dataset"), row)
    assert bench.run == Path("/tmp/profile/runs/full") and bench.min_alpha == 0.25
    assert bench.max_views_per_scene == config.max_views and bench.num_classes == config.num_classes
    names = {spec.name for spec in RUNS}
    assert {r.run for r in TABLE1_ROWS if r.run} <= names and {r.run for r in ABLATION_ROWS} <= names
    assert {r.predictor for r in TABLE1_ROWS} >= {"majority", "nearest-colour", "model"}


def test_every_run_shares_the_schedule_and_differs_only_in_its_switches():
    config = SuiteConfig(out=Path("/tmp/profile"))
    configs = {spec.name: S.train_config(config, spec, Path("/tmp/d")) for spec in RUNS}
    full = configs["full"]
    assert full.voxel_size == config.voxel_size and full.loss.class_balance == config.class_balance
    for name, c in configs.items():
        assert (c.epochs, c.optim.lr, c.data.pixels_per_view) == (full.epochs, full.optim.lr, full.data.pixels_per_view)
    assert not configs["no-adapter"].use_adapter and configs["text-2d-only"].loss.no_3dt_align
    assert [n for n, c in configs.items() if c.loss.unlabelled_as_unseen] == ["transductive"]
    assert replace(configs["transductive"], loss=full.loss, out=full.out) == full  # only the switch differs
    assert {c.data.loss_gaussians for c in configs.values()} == {config.loss_gaussians}
    assert {c.data.scene_cache_size for c in configs.values()} == {config.scene_cache_size}
    subset = SuiteConfig(out=Path("/tmp/profile"), loss_gaussians=2048)
    assert {S.train_config(subset, spec, Path("/tmp/d")).data.loss_gaussians for spec in RUNS} == {2048}
    assert {c.loss.lovasz_weight for c in configs.values()} == {config.lovasz_weight}
    lovasz = SuiteConfig(out=Path("/tmp/profile"), lovasz_weight=0.5)
    assert {S.train_config(lovasz, spec, Path("/tmp/d")).loss.lovasz_weight for spec in RUNS} == {0.5}
    assert {c.voxel_geometry for c in configs.values()} == {False}
    shaped = SuiteConfig(out=Path("/tmp/profile"), voxel_geometry=True)
    assert {S.train_config(shaped, spec, Path("/tmp/d")).voxel_geometry for spec in RUNS} == {True}


def test_bench_suite_cli_maps_its_options_loss_gaussians_0_to_every_gaussian_lovasz_weight_and_ensemble(monkeypatch, tmp_path):
    from click.testing import CliRunner

    from cli.ov_bench_suite import command

    seen = []

    def record(config, log=None):
        seen.append(config)
        raise ValueError("stop here: only the config is checked")

    monkeypatch.setattr(S, "run_suite", record)
    for args, expected in (([], 15000), (["--loss-gaussians", "0"], None),
                           (["--loss-gaussians", "512"], 512)):
        CliRunner().invoke(command, ["--out", str(tmp_path), *args])
        assert seen.pop().loss_gaussians == expected
    CliRunner().invoke(command, ["--out", str(tmp_path), "--lovasz-weight", "0.25"])
    assert seen.pop().lovasz_weight == 0.25
    CliRunner().invoke(command, ["--out", str(tmp_path)])
    assert seen.pop().ensemble is False
    CliRunner().invoke(command, ["--out", str(tmp_path), "--ensemble"])
    assert seen.pop().ensemble is True
    CliRunner().invoke(command, ["--out", str(tmp_path)])
    assert seen.pop().voxel_geometry is False
    CliRunner().invoke(command, ["--out", str(tmp_path), "--voxel-geometry"])
    assert seen.pop().voxel_geometry is True


def test_calibrated_stacking_row_uses_the_calibration_run_and_is_checked_for_ova():
    config = SuiteConfig(out=Path("/tmp/profile"))
    row = next(r for r in TABLE1_ROWS if r.stacking_run is not None)
    bench = S.bench_config(config, Path("/tmp/profile/dataset"), row)
    assert bench.run == Path("/tmp/profile/runs/full")
    assert bench.stacking_run == Path("/tmp/profile/runs") / row.stacking_run
    calibration = next(spec for spec in RUNS if spec.name == row.stacking_run)
    held_out = S.train_config(config, calibration, Path("/tmp/d")).data.holdout_classes
    assert held_out and not S.train_config(config, RUNS[0], Path("/tmp/d")).data.holdout_classes
    assert {r.options for r in TABLE1_ROWS} >= {(("prompt_ensemble", True),), (("generative", True),)}
    base = {k: 0.2 for k in ALL}
    stacked = payload({**base, ("3d", "OVA"): 0.05, ("2d", "OVA"): 0.04})
    stacked["predictor"] = {"stacking": {"gamma": 0.3}}
    reports = {"full": payload(base), "stacked": stacked}
    name = "OVA > 0 in 3D and 2D with calibrated stacking (stacked), gamma recorded"
    assert R.checks(reports, "full", (), {}, ("stacked",))[name][0]
    no_gamma = dict(reports, stacked={**stacked, "predictor": {}})
    assert not R.checks(no_gamma, "full", (), {}, ("stacked",))[name][0]
    zero_2d = payload({**base, ("3d", "OVA"): 0.05, ("2d", "OVA"): 0.0})
    zero_2d["predictor"] = stacked["predictor"]
    assert not R.checks(dict(reports, stacked=zero_2d), "full", (), {}, ("stacked",))[name][0]


def test_tasks_give_their_values_in_order_with_one_or_two_processes():
    import os

    tasks = [S.Task(f"t{i}", os.getpid, ()) for i in range(3)] + [S.Task("sum", sum, ((1, 2, 3),))]
    said = []
    values, times = S.run_tasks(tasks, 1, said.append)
    assert values == [os.getpid()] * 3 + [6] and [t.name for t in times] == ["t0", "t1", "t2", "sum"]
    values, times = S.run_tasks(tasks, 2, said.append)
    assert values[3] == 6 and os.getpid() not in values[:3] and 1 <= len(set(values[:3])) <= 2
    assert [t.name for t in times] == ["t0", "t1", "t2", "sum"] and all(t.wall >= 0 and t.cpu >= 0 for t in times)
    assert any("sum: done" in m for m in said)


def test_a_task_starts_only_after_the_tasks_it_comes_after():
    """Two workers: 'late' waits for 'slow' (its clock reading is after slow's end), 'free' does not (it runs
    beside slow). CLOCK_REALTIME readings of separate processes compare."""
    import time

    slow = S.Task("slow", subprocess.check_output, (["sh", "-c", "sleep 3; date +%s.%N"],))
    tasks = [slow, S.Task("late", time.time, (), ("slow",)), S.Task("free", time.time, ())]
    values, times = S.run_tasks(tasks, 2, lambda m: None)
    slow_end = float(values[0])
    assert values[1] >= slow_end > values[2]
    assert [t.name for t in times] == ["slow", "late", "free"]
    values, _ = S.run_tasks(tasks, 1, lambda m: None)  # one after the other: in list order
    assert values[2] >= values[1] >= float(values[0])
    with pytest.raises(ValueError, match="not an earlier task"):
        S.run_tasks([S.Task("a", time.time, (), ("b",)), S.Task("b", time.time, ())], 2, lambda m: None)
    with pytest.raises(ValueError, match="not an earlier task"):
        S.run_tasks([S.Task("a", time.time, (), ("missing",))], 1, lambda m: None)


def test_a_free_process_starts_the_first_ready_task_in_list_order():
    tasks = [S.Task("fit", len, ((),)), S.Task("cheap", len, ((),)), S.Task("train", len, ((),), ("fit",)),
             S.Task("bench", len, ((),), ("train",)), S.Task("other", len, ((),))]
    assert S.first_ready(tasks, [1, 2, 3, 4], set()) == 1  # train waits for fit
    assert S.first_ready(tasks, [2, 3, 4], {"cheap"}) == 4
    assert S.first_ready(tasks, [2, 3, 4], {"cheap", "fit"}) == 2  # once ready, train goes before what follows it
    assert S.first_ready(tasks, [4, 3, 2], {"fit", "train"}) == 2  # list order, not the order of ``waiting``
    assert S.first_ready(tasks, [3], {"fit"}) is None
    said = []
    values, _ = S.run_tasks(tasks, 2, said.append)
    assert values == [0] * 5
    started = [m.removesuffix(" (started)") for m in said if m.endswith("(started)")]
    assert started.index("train") > started.index("fit") and started.index("bench") > started.index("train")
    assert sorted(started) == sorted(t.name for t in tasks)


def test_a_profile_folder_refuses_other_settings_and_accepts_its_own(tmp_path):
    from ovgaussian.suite.profile import SETTINGS_NAME, check_settings

    config = SuiteConfig(out=tmp_path, progress=False)
    check_settings(config)                                     # first run: recorded
    recorded = json.loads((tmp_path / SETTINGS_NAME).read_text())
    assert recorded["replica_scenes"] == config.replica_scenes and "out" not in recorded
    check_settings(replace(config, jobs=1, progress=True))    # display and processes change no result
    with pytest.raises(ValueError, match=r"other settings \(replica_scenes 16 -> 8\); use a new --out"):
        check_settings(replace(config, replica_scenes=8))
    with pytest.raises(ValueError, match="class_balance"):
        check_settings(replace(config, class_balance=0.5))
    # a folder recorded before a setting existed was made with that setting's value of the time, and only with it
    older = {k: v for k, v in recorded.items() if k != "lovasz_weight"}
    (tmp_path / SETTINGS_NAME).write_text(json.dumps(older))
    check_settings(replace(config, lovasz_weight=0.0))
    with pytest.raises(ValueError, match=r"lovasz_weight 0\.0 -> 1\.0"):
        check_settings(replace(config, lovasz_weight=1.0))
    # likewise voxel geometry, a later setting: a folder recorded without it was trained without it
    (tmp_path / SETTINGS_NAME).write_text(json.dumps({k: v for k, v in recorded.items() if k != "voxel_geometry"}))
    check_settings(replace(config, voxel_geometry=False))
    with pytest.raises(ValueError, match=r"voxel_geometry False -> True"):
        check_settings(replace(config, voxel_geometry=True))


def test_a_rerun_keeps_the_times_of_the_invocations_before_it(tmp_path):
    path = tmp_path / "suite.json"
    assert S.invocation_history(path) == []
    first = {"times": [{"name": "train: full", "wall_s": 1329.0, "cpu_s": 1313.0}], "total": {"wall_s": 2404.0}}
    path.write_text(json.dumps({"config": {}, **first}))  # written before suite.json had a history
    assert S.invocation_history(path) == [first]
    second = {"times": [], "total": {"wall_s": 7.0}}
    path.write_text(json.dumps({**second, "history": [first, second]}))
    assert S.invocation_history(path) == [first, second]
    path.write_text("{not json")
    assert S.invocation_history(path) == []


def test_the_control_row_is_a_run_trained_and_scored_on_oracle_gaussians_and_the_share_is_checked():
    control = [r for r in TABLE1_ROWS if r.scored_on == "oracle"]
    trained = {spec.name: spec.trained_on for spec in RUNS}
    # the controls (plain and with class offsets, single run and two-seed ensemble) and the full run on oracle
    assert sorted(trained[r.run] for r in control) == ["oracle"] * 4 + ["splats"]
    assert all(trained[name] == "oracle" for r in control if trained[r.run] == "oracle" for name in r.ensemble)
    assert trained["full-oracle"] == "oracle" and trained["full"] == "splats"
    ensemble = SuiteConfig(ensemble=True)
    assert S.table1_rows(replace(ensemble, splats="oracle")) == tuple(r for r in TABLE1_ROWS if r.scored_on == "splats")
    assert S.table1_rows(ensemble) == TABLE1_ROWS
    assert S.table1_rows(SuiteConfig()) == tuple(r for r in TABLE1_ROWS if not r.ensemble)  # the default: no ensemble
    pairs = R.control_pairs(TABLE1_ROWS, trained)
    assert pairs == [("OVGaussian (full)", "control: full trained and scored on oracle Gaussians"),
                     ("full + class offsets", "control + class offsets"),
                     ("full, 2 training seeds (ensemble)", "control, 2 training seeds (ensemble)"),
                     ("full, 2 training seeds + class offsets", "control, 2 training seeds + class offsets")]
    assert [r.label for r in TABLE1_ROWS if r.fit_recipe] == ["full, 2 training seeds + class offsets"]
    reports = {"full": payload({k: 0.45 for k in ALL}), "control": payload({k: 0.48 for k in ALL}),
               "full + offsets": payload({k: 0.40 for k in ALL}), "control + offsets": payload({k: 0.50 for k in ALL})}
    both = [("full", "control"), ("full + offsets", "control + offsets")]
    # without a recipe the full model's pair decides; the other pair is in the detail
    ((name, (ok, detail)),) = R.control_checks(reports, both, "fit").items()
    assert ok and name.endswith("(full)") and "full: fitted 45.0 [43.0, 47.0] vs oracle 48.0" in detail
    assert "93.8 %" in detail and "the other methods: full + offsets: fitted 40.0" in detail and "80.0 %" in detail
    # the recipe's pair decides, whatever the others give
    ((name, (ok, detail)),) = R.control_checks(reports, both, "fit", recipe="full + offsets").items()
    assert not ok and name.endswith("(full + offsets)") and detail.startswith("full + offsets: fitted 40.0")
    reports["full + offsets"] = payload({k: 0.46 for k in ALL})
    reports["full"] = payload({k: 0.40 for k in ALL})
    ((name, (ok, detail)),) = R.control_checks(reports, both, "fit", recipe="full + offsets").items()
    assert ok and "92.0 %" in detail and "full: fitted 40.0" in detail
    assert not list(R.control_checks(reports, both, "fit").values())[0][0]  # 40 / 48: the full pair alone fails
    assert R.control_checks(reports, both, "fit", recipe="missing") == R.control_checks(reports, both, "fit")
    assert R.control_checks(reports, [("full", "control")], "oracle") == {}  # an oracle profile has no such check
    assert R.control_checks(reports, [], "fit") == {}
    assert SuiteConfig().splats == "fit" and not SuiteConfig().ablation


def test_the_check_gives_the_ratio_with_its_interval_paired_over_the_same_val_rooms():
    rng = np.random.default_rng(0)
    k = 3
    control = rng.integers(0, 5, size=(6, k, k + 1))
    control[:, np.arange(k), np.arange(k)] += rng.integers(20, 60, size=(6, k))
    fitted = control.copy()
    fitted[:, np.arange(k), np.arange(k)] -= 8  # every room loses the same share of its hits to misses
    fitted[:, np.arange(k), k] += 8
    rooms = [f"room{i}" for i in range(6)]

    def with_rooms(value, mats, ids):
        report = payload({key: value for key in ALL})
        report["dataset"] = {"scenes": {"val": ids}}
        report["scene_confusion"] = {"val_3d": mats.tolist()}
        return report

    top, bottom = scores_from_confusion(fitted.sum(0)).miou, scores_from_confusion(control.sum(0)).miou
    reports = {"full": with_rooms(top, fitted, rooms), "control": with_rooms(bottom, control, rooms)}
    interval = R.paired_csa_ratio(reports["full"], reports["control"])
    assert interval.value == pytest.approx(top / bottom) and interval.scenes == 6
    assert interval.low <= interval.value <= interval.high
    ((_, (_, detail)),) = R.control_checks(reports, [("full", "control")], "fit").items()
    assert f"paired 95 % interval over the 6 val rooms: {100 * interval.low:.1f}-{100 * interval.high:.1f} %" in detail
    # other rooms, or another order, or no per-room matrices: no paired interval, the ratio alone
    reports["control"] = with_rooms(bottom, control, rooms[::-1])
    assert R.paired_csa_ratio(reports["full"], reports["control"]) is None
    ((_, (_, detail)),) = R.control_checks(reports, [("full", "control")], "fit").items()
    assert "paired" not in detail and f"{100 * top / bottom:.1f} %" in detail
    assert R.paired_csa_ratio(payload({key: 0.4 for key in ALL}), reports["control"]) is None


def test_ensemble_rows_score_the_run_with_its_other_seeds_and_are_opt_out():
    config = SuiteConfig(out=Path("/tmp/profile"))
    specs = {spec.name: spec for spec in RUNS}
    rows = [r for r in TABLE1_ROWS if r.ensemble]
    assert len(rows) == 4 and {r.run for r in rows} == {"full", "full-oracle"}
    for row in rows:
        bench = S.bench_config(config, Path("/tmp/profile/dataset"), row)
        assert bench.run == Path("/tmp/profile/runs") / row.run
        assert bench.ensemble_runs == tuple(Path("/tmp/profile/runs") / name for name in row.ensemble)
        main = S.train_config(config, specs[row.run], Path("/tmp/d"))
        for name in row.ensemble:  # a member is the same recipe, trained with another seed and nothing else
            member = S.train_config(config, specs[name], Path("/tmp/d"))
            assert member.seed != main.seed and specs[name].trained_on == specs[row.run].trained_on
            assert replace(member, seed=main.seed, out=main.out) == main
    plain = S.bench_config(config, Path("/tmp/d"), next(r for r in TABLE1_ROWS if r.label == "OVGaussian (full)"))
    assert plain.ensemble_runs == ()
    without = S.table1_rows(replace(config, ensemble=False))
    assert without == tuple(r for r in TABLE1_ROWS if not r.ensemble)
    assert [p for p in R.control_pairs(without, {s.name: s.trained_on for s in RUNS})
            if "seeds" in p[0]] == []


def test_the_ensemble_switch_is_not_a_setting_of_the_folder(tmp_path):
    config = SuiteConfig(out=tmp_path, progress=False, ensemble=False)
    S.check_settings(config)
    S.check_settings(replace(config, ensemble=True))  # adds runs and rows, changes none that exist


def test_the_profiles_worker_processes_end_when_the_suite_is_killed(tmp_path):
    """A suite killed (SIGKILL: no handler runs) while its two worker processes are busy leaves neither running:
    each watches the process that started it and exits once it is gone."""
    import sys
    import time

    from processes import assert_workers_end_with_their_parent

    script = (
        "import time\n"
        "from ovgaussian.suite.profile import Task, run_tasks\n"
        "run_tasks([Task('a', time.sleep, (120,)), Task('b', time.sleep, (120,))], 2, print)\n"
    )
    suite = subprocess.Popen([sys.executable, "-c", script], cwd=tmp_path)
    started: list[float] = []

    def ready(workers):  # two workers + the resource tracker, then 1 s for the workers to pick up their tasks
        if len(workers) < 3:
            return False
        started.append(time.monotonic())
        return time.monotonic() - started[0] >= 1.0

    assert_workers_end_with_their_parent(suite, ready, start_timeout=60.0)
