"""The splat zoo of the benchmark profile (``bench-suite --zoo``, issue #54 item 3): the split rendition, the cells
and checks on hand-made bench payloads, the runs' configs, and the profile's queue with the zoo (its stages faked:
they are the build, train and bench code tested elsewhere; the zoo runs end to end in benchmarks/)."""

from pathlib import Path

from dataclasses import replace

import numpy as np
import pytest

from ovgaussian.bench.bootstrap import bootstrap_miou
from ovgaussian.metrics import scores_from_confusion
from ovgaussian.suite import profile as S
from ovgaussian.suite import zoo as Z
from ovgaussian.suite.config import RUNS, ZOO_RENDITIONS, ZOO_RUNS, SuiteConfig
from seggaussian.core.gaussians import Gaussians
from seggaussian.core.rotations import quats_to_rotmats

NAMES = ["wall", "floor", "chair", "sofa"]
K = len(NAMES)


def test_split_splat_draws_each_child_from_its_parent_with_smaller_scales():
    n = 20000
    quat = np.array([0.9, 0.1, -0.3, 0.2])
    quat /= np.linalg.norm(quat)
    scales = np.array([0.05, 0.02, 0.01])
    parent = Gaussians.from_arrays(np.tile([1.0, -2.0, 0.5], (n, 1)), np.tile(quat, (n, 1)),
                                   np.tile(np.log(scales), (n, 1)), np.full(n, 0.3), np.zeros((n, 16, 3)) + 0.2)
    split = Z.split_splat(parent, np.random.default_rng(0))
    assert len(split.means) == 2 * n
    rot = quats_to_rotmats(quat[None])[0]
    expected = rot @ np.diag(scales ** 2) @ rot.T  # each child is drawn from the parent's Gaussian
    for half in (split.means[:n], split.means[n:]):
        assert np.allclose(half.mean(axis=0), [1.0, -2.0, 0.5], atol=3e-3 * 5)
        assert np.allclose(np.cov(half.T), expected, atol=0.05 * scales[0] ** 2)
    assert np.allclose(split.log_scales, np.log(scales / 1.6), atol=1e-6)
    assert np.allclose(split.opacity_logits, 0.3) and np.allclose(split.sh, 0.2)
    assert np.allclose(split.quats, np.tile(quat, (2 * n, 1)), atol=1e-6)
    empty = Gaussians.from_arrays(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 16, 3)))
    assert len(Z.split_splat(empty, np.random.default_rng(0)).means) == 0


def scene_mats(right: float, scenes: int, rng: np.random.Generator) -> np.ndarray:
    """[scenes, K, K + 1] confusion counts: about ``right`` of each class's points right, the rest spread."""
    mats = np.zeros((scenes, K, K + 1), np.int64)
    for s in range(scenes):
        for c in range(K):
            total = int(rng.integers(80, 120))
            mats[s, c, c] = int(round(right * total))
            mats[s, c, (c + 1) % K] = total - mats[s, c, c]
    return mats


def bench_payload(val: np.ndarray, xval: np.ndarray, scenes: dict) -> dict:
    """A bench payload holding 3D CSA (val) and CDA (xval) of these per-scene matrices, with their intervals."""
    classes = list(range(K))
    metrics = {}
    for metric, split, mats in (("CSA", "val", val), ("CDA", "xval", xval)):
        interval = bootstrap_miou(mats, classes, draws=300)
        metrics[metric] = {"miou": scores_from_confusion(mats.sum(axis=0), classes).miou,
                           "ci95": [interval.low, interval.high], "split": split, "classes": NAMES,
                           "num_scenes": len(mats), "per_class_iou": {}}
    return {"metrics": {"3d": metrics}, "vocabulary": {"names": NAMES, "unseen": []}, "dataset": {"scenes": scenes},
            "scene_confusion": {"val_3d": val.tolist(), "xval_3d": xval.tolist()}}


def zoo_reports(shares: dict[str, float], baseline_right: float = 0.2) -> dict:
    """Bench payloads of every zoo rendition: the matched run 80 % right, the recipe at about ``shares`` times its
    mIoU (per rendition in ``shares``, else the same matrices), the baselines ``baseline_right``."""
    rng = np.random.default_rng(1)
    scenes = {"val": [f"v{i}" for i in range(6)], "xval": [f"x{i}" for i in range(5)]}
    reports = {}
    for r in ZOO_RENDITIONS:
        matched = (scene_mats(0.8, 6, rng), scene_mats(0.8, 5, rng))
        share = shares.get(r.name)
        # each class's IoU is right / (2 - right) here: the recipe's right share for ``share`` x the matched IoU
        iou = share * 0.8 / (2 - 0.8) if share is not None else None
        recipe = matched if share is None else (scene_mats(2 * iou / (1 + iou), 6, rng),
                                                 scene_mats(2 * iou / (1 + iou), 5, rng))
        reports[r.name] = {"recipe": bench_payload(*recipe, scenes), "matched": bench_payload(*matched, scenes)}
        for baseline in ("majority", "nearest-colour"):
            reports[r.name][baseline] = bench_payload(scene_mats(baseline_right, 6, rng),
                                                      scene_mats(baseline_right, 5, rng), scenes)
    return reports


ENOUGH = {r.name: [120_000, 130_000] for r in ZOO_RENDITIONS}


def test_zoo_checks_hold_the_recipe_to_its_matched_run_and_above_both_baselines():
    checks = Z.zoo_checks(Z.zoo_cells(zoo_reports({})), ENOUGH)
    assert len(checks) == 2 * len(ZOO_RENDITIONS) + 1 and all(ok for ok, _ in checks.values()), checks
    # the recipe at about 0.7 x on the scan fails there, and only there; 0.82 x passes on the never-trained split
    cells = Z.zoo_cells(zoo_reports({"scan": 0.7, "split": 0.82}))
    checks = Z.zoo_checks(cells, ENOUGH)
    failed = [name for name, (ok, _) in checks.items() if not ok]
    assert failed == ["zoo: the recipe on the scan (a Gaussian per vertex) >= 0.85 x the run trained on it alone "
                      "(matched-scan)"], failed
    ratio = cells["scan"]["recipe"]["CSA"].ratio
    assert 0.55 < ratio.low < ratio.value < ratio.high < 0.85  # the paired interval over the 6 val rooms
    assert cells["scan"]["matched"]["CSA"].ratio is None
    assert 0.8 < cells["split"]["recipe"]["CDA"].ratio.value < 0.85
    # a baseline as good as the recipe: intervals touch, the check fails on every rendition
    checks = Z.zoo_checks(Z.zoo_cells(zoo_reports({}, baseline_right=0.8)), ENOUGH)
    assert [ok for name, (ok, _) in checks.items() if "baselines" in name] == [False] * len(ZOO_RENDITIONS)
    few = dict(ENOUGH, **{"default-fit": [99_999, 150_000]})
    ok, detail = Z.zoo_checks(Z.zoo_cells(zoo_reports({})), few)[
        "zoo: the default-preset fit holds >= 100,000 Gaussians per room"]
    assert not ok and detail == "min 99,999, max 150,000 over 2 rooms"


def test_a_ratio_needs_the_same_rooms_on_both_sides():
    reports = zoo_reports({})
    matched = reports["scan"]["matched"]
    matched["dataset"] = {"scenes": {"val": ["other"] * 6, "xval": matched["dataset"]["scenes"]["xval"]}}
    cells = Z.zoo_cells(reports)
    assert cells["scan"]["recipe"]["CSA"].ratio is None and cells["scan"]["recipe"]["CDA"].ratio is not None
    ok, _ = Z.zoo_checks(cells, ENOUGH)["zoo: the recipe on the scan (a Gaussian per vertex) >= 0.85 x the run "
                                        "trained on it alone (matched-scan)"]
    assert not ok


def test_the_zoo_table_names_every_rendition_scorer_and_matched_run():
    table = Z.format_zoo(Z.zoo_cells(zoo_reports({"scan": 0.7})), ENOUGH)
    for r in ZOO_RENDITIONS:
        assert r.label in table and r.matched_run in table
    for label in ("recipe (zoo)", "trained on the rendition alone", "majority (baseline)", "nearest-colour (baseline)",
                  "recipe / matched [paired 95 %]", "| recipe trains on it | yes | yes | yes | yes | no |",
                  "120,000 / 125,000 / 130,000"):
        assert label in table
    assert "3D CSA (val rooms)" in table and "3D CDA (xval rooms)" in table


def test_the_zoo_runs_are_the_recipe_and_one_model_per_rendition_on_the_profile_schedule():
    config = SuiteConfig(out=Path("/tmp/profile"), zoo=True)
    datasets = Z.zoo_datasets(config, Path("/tmp/d"), Path("/tmp/o"))
    full = S.train_config(config, RUNS[1], datasets["splats"])
    configs = {spec.name: S.train_config(config, spec, datasets[spec.trained_on],
                                         tuple(datasets[r] for r in spec.also_trains_on)) for spec in ZOO_RUNS}
    recipe = configs["zoo"]
    zoo = "/tmp/profile/zoo"
    assert recipe.data.renditions == (Path(f"{zoo}/default-fit"), Path(f"{zoo}/scan"), Path("/tmp/o"))
    assert recipe.data.dataset == Path("/tmp/d") and recipe.data.off_surface_augment and recipe.surface_radius == 0.15
    assert recipe.data.colour_augment
    configs["full"] = full
    configs["full-oracle"] = S.train_config(config, {s.name: s for s in RUNS}["full-oracle"], datasets["oracle"])
    for name, dataset in (("matched-default-fit", f"{zoo}/default-fit"), ("matched-scan", f"{zoo}/scan"),
                          ("matched-split", f"{zoo}/split"), ("full", "/tmp/d"), ("full-oracle", "/tmp/o")):
        c = configs[name]
        assert c.data.dataset == Path(dataset) and not c.data.renditions
        assert not c.data.off_surface_augment and c.surface_radius == 0.0 and c.epochs == full.epochs
        # recoloured as the recipe and every run of the profile are: the ratio measures the renditions, not the
        # colour augment
        assert c.data.colour_augment and c == replace(full, out=c.out, data=replace(full.data, dataset=c.data.dataset))
    assert all(spec.colour_augment for spec in RUNS + ZOO_RUNS)
    for name, c in configs.items():
        assert (c.optim.lr, c.data.pixels_per_view, c.voxel_size, c.loss.lovasz_weight) == (
            full.optim.lr, full.data.pixels_per_view, full.voxel_size, full.loss.lovasz_weight)
        assert c.epochs == (3 if name == "zoo" else 1) * full.epochs == (3 if name == "zoo" else 1) * config.epochs
    names = {spec.name for spec in RUNS + ZOO_RUNS}
    assert {r.matched_run for r in ZOO_RENDITIONS} <= names and len(names) == len(RUNS) + len(ZOO_RUNS)
    assert [r.name for r in ZOO_RENDITIONS if not r.recipe_trains] == ["split"]
    assert set(ZOO_RUNS[0].also_trains_on) | {"splats"} == {r.name for r in ZOO_RENDITIONS if r.recipe_trains}
    assert Z.default_fit_config(config).iterations == config.zoo_fit_iterations
    assert Z.default_fit_config(config).densify_every == 100  # the default preset's schedule, not rescaled


def full_payload(scenes: dict, right: float) -> dict:
    """A payload with every metric Table 1's checks read, and the zoo's 3D matrices."""
    rng = np.random.default_rng(int(right * 100))
    p = bench_payload(scene_mats(right, 6, rng), scene_mats(right, 5, rng), scenes)
    ious = {n: right for n in NAMES}
    for dim in ("3d", "2d"):
        for metric in ("CSA", "OVA", "CDA", "NVA"):
            base = p["metrics"]["3d"].get(metric, {"miou": right, "ci95": [right - 0.01, right + 0.01]})
            p["metrics"].setdefault(dim, {})[metric] = {**base, "per_class_iou": ious}
    confusion = np.eye(K, K + 1, dtype=np.int64).tolist()
    p["confusion"] = {"val_3d": confusion, "val_2d": confusion, "train_2d": confusion}
    return p


def test_the_profile_queues_the_zoo_after_what_each_task_needs(tmp_path, monkeypatch):
    config = SuiteConfig(out=tmp_path / "p", zoo=True, jobs=2, progress=False)
    splats, oracle = tmp_path / "p" / "dataset", tmp_path / "p" / "dataset-oracle"
    scenes = {"val": [f"v{i}" for i in range(6)], "xval": [f"x{i}" for i in range(5)]}
    trained, queue = {}, []

    def fake_tasks(tasks, jobs, say):  # one after the other, each only once what it comes after is done
        done = set()
        for task in tasks:
            assert set(task.after) <= done, (task.name, task.after)
            queue.append((task.name, task.after))
            done.add(task.name)
        return [task.fn(*task.args) for task in tasks], [S.StageTime(t.name, 1.0, 1.0) for t in tasks]

    def fake_train(config, spec, dataset, renditions=()):
        trained[spec.name] = (dataset, renditions)
        return S.run_dir(config, spec.name)

    def fake_bench(config, bench, path):
        right = 0.1 if bench.predictor != "model" else 0.7
        return full_payload(scenes, right)

    monkeypatch.setattr(S, "build_data", lambda c: S.SuiteData(splats, oracle))
    monkeypatch.setattr(S, "split_sizes", lambda d: {"train": 45, "val": 11, "xval": 16})
    monkeypatch.setattr(S, "run_tasks", fake_tasks)
    monkeypatch.setattr(S, "train_run", fake_train)
    monkeypatch.setattr(S, "bench_row", fake_bench)
    monkeypatch.setattr(Z, "build_rendition", lambda *args: args)
    monkeypatch.setattr(Z, "scored_gaussians", lambda dataset: [123_456] * 11)
    report = S.run_suite(config)
    after = dict(queue)
    zoo = tmp_path / "p" / "zoo"
    assert trained["zoo"] == (splats, (zoo / "default-fit", zoo / "scan", oracle))
    assert trained["matched-default-fit"] == (zoo / "default-fit", ())
    assert trained["full-oracle"] == (oracle, ()) and trained["full"] == (splats, ())
    assert after["zoo: build default-fit"] == ("zoo: fit default-fit 1/2", "zoo: fit default-fit 2/2")
    assert after["train: matched-default-fit"] == ("zoo: build default-fit",)
    assert after["train: zoo"] == ("zoo: build default-fit", "zoo: build scan") and after["train: full"] == ()
    assert after["bench: zoo split recipe"] == ("train: zoo", "zoo: build split")
    assert after["bench: zoo oracle matched"] == ("train: full-oracle",)
    assert after["bench: zoo splats matched"] == ("train: full",)
    assert after["bench: zoo scan nearest-colour"] == ("zoo: build scan",)
    assert sum(name.startswith("bench: zoo") for name in after) == len(ZOO_RENDITIONS) * len(Z.ZOO_SCORERS)
    zoo_checks = {k: v for k, v in report.checks.items() if k.startswith("zoo:")}
    assert len(zoo_checks) == 2 * len(ZOO_RENDITIONS) + 1 and all(ok for ok, _ in zoo_checks.values()), zoo_checks
    assert (tmp_path / "p" / "zoo.md").read_text() == report.zoo and "matched-split" in report.zoo
    assert (tmp_path / "p" / "zoo.json").is_file()
    # without --zoo nothing of it is queued or written
    queue.clear()
    trained.clear()
    plain = S.run_suite(SuiteConfig(out=tmp_path / "q", jobs=2, progress=False))
    assert plain.zoo == "" and not any("zoo" in name for name, _ in queue) and "zoo" not in trained
    with pytest.raises(ValueError, match="needs --splats fit"):
        S.run_suite(SuiteConfig(out=tmp_path / "r", zoo=True, splats="oracle"))


@pytest.mark.slow
def test_the_split_and_scan_renditions_are_datasets_of_the_same_rooms_split_and_labels(tmp_path):
    from seggaussian import shards
    from seggaussian.labels.config import OracleConfig
    from seggaussian.pipeline.config import BuildConfig
    from seggaussian.pipeline.dataset import build_dataset
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    config = SuiteConfig(out=tmp_path, scenes=3, replica_scenes=1, width=48, views=6, gaussians=600, zoo=True)
    synthesize(tmp_path / "raw" / "scannetpp", 3, 0, "scannetpp", SynthConfig(width=48, num_views=6))
    synthesize(tmp_path / "raw" / "replica", 1, 0, "replica", SynthConfig(width=48, num_views=6))
    base = tmp_path / "dataset"  # oracle Gaussians stand in for the profile's fits (no fit in a test)
    build_dataset(BuildConfig(source="synthetic", root=tmp_path / "raw", out=base, gaussians="oracle", progress=False,
                              oracle=OracleConfig(num_gaussians=600), split=Z.split_config(config)))
    manifest = shards.read_manifest(base)["scenes"]
    for name in ("split", "scan"):
        out = Z.build_rendition(config, name, base, base)
        assert out == tmp_path / "zoo" / name
        other = shards.read_manifest(out)["scenes"]
        assert {k: v["split"] for k, v in other.items()} == {k: v["split"] for k, v in manifest.items()}
        for scene_id, entry in manifest.items():
            g = shards.read_scene(out, entry["split"], scene_id, views=False).gaussians
            if name == "split":
                parent = shards.read_scene(base, entry["split"], scene_id, views=False).gaussians
                assert len(g.means) == 2 * len(parent.means) == 1200
                # the children, read back through the PLY and the build, lie within their parent's extent
                reach = 5 * np.exp(parent.log_scales.astype(np.float64)).max(axis=1)
                offset = np.linalg.norm(g.means - np.tile(parent.means, (2, 1)), axis=1)
                assert np.all(offset < np.tile(reach, 2)) and np.median(offset) > 0
                assert np.allclose(g.log_scales, np.tile(parent.log_scales, (2, 1)) - np.log(1.6), atol=1e-5)
            else:
                assert len(g.means) > 600 and np.all(np.exp(g.log_scales).std(axis=1) < 1e-6)  # isotropic
    assert Z.scored_gaussians(tmp_path / "zoo" / "split") == [1200] * sum(
        v["split"] in ("val", "xval") for v in manifest.values())
    kept = sorted((tmp_path / "zoo" / "ply-split").glob("*.ply"))
    stamps = [p.stat().st_mtime_ns for p in kept]
    Z.build_rendition(config, "split", base, base)  # a rebuild keeps the split splats (its build cache holds)
    assert [p.stat().st_mtime_ns for p in kept] == stamps and len(kept) == len(manifest)


def test_a_finished_run_is_reused_only_at_its_own_number_of_epochs_and_recipe(tmp_path, monkeypatch):
    from dataclasses import replace

    from ovgaussian.run.config import config_to_dict
    from seggaussian.util.atomic import write_json_atomic

    calls = []

    def fake_train(c):  # what train records of a run: its config.json
        calls.append(c.epochs)
        c.out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(c.out / "config.json", {"train": config_to_dict(c)})

    monkeypatch.setattr(S, "train", fake_train)
    config = SuiteConfig(out=tmp_path, epochs=3)
    recipe = ZOO_RUNS[0]
    S.train_run(config, recipe, tmp_path / "d")
    S.train_run(config, recipe, tmp_path / "d")  # finished at 3 x 3 epochs: reused
    assert calls == [9]
    S.train_run(SuiteConfig(out=tmp_path, epochs=6), ZOO_RUNS[1], tmp_path / "d")  # another run: trains
    S.train_run(SuiteConfig(out=tmp_path, epochs=4), recipe, tmp_path / "d")  # 12 epochs now: trains again
    assert calls == [9, 6, 12]
    # the recipe changed in the code since the run finished: refused, naming what changed, not reused silently
    with pytest.raises(ValueError, match=r"runs/zoo: finished with another recipe .*data\.colour_augment"):
        S.train_run(SuiteConfig(out=tmp_path, epochs=4), replace(recipe, colour_augment=not recipe.colour_augment),
                    tmp_path / "d")
    # its training data rebuilt since it finished: refused too
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "manifest.json").write_text("{}")
    with pytest.raises(ValueError, match=r"another recipe or data .*\(its training data\)"):
        S.train_run(SuiteConfig(out=tmp_path, epochs=4), recipe, tmp_path / "d")
    assert calls == [9, 6, 12]


def test_a_bench_report_is_reused_only_for_the_weights_it_scored(tmp_path, monkeypatch):
    from ovgaussian.bench.config import BenchConfig

    folders = {}
    for name in ("run", "calibration"):  # a run and a stacking calibration run, one checkpoint each
        folders[tmp_path / name] = tmp_path / name / "checkpoints" / "epoch-0001"
        folders[tmp_path / name].mkdir(parents=True)
        (folders[tmp_path / name] / "model.safetensors").write_bytes(b"weights one")
    monkeypatch.setattr(S, "latest_checkpoint", lambda r: folders[r])
    scored = []

    def fake_bench(bench):  # records the weights it scored as run_bench's payload does
        scored.append(bench.predictor if bench.stacking_run is None else "stacked")
        predictor = {"checkpoint_sha256": S.weights_sha256(folders[bench.run])} if bench.run else {}
        if bench.stacking_run is not None:
            predictor["stacking"] = {"checkpoint_sha256": S.weights_sha256(folders[bench.stacking_run])}
        payload = {"predictor": predictor, "dataset": S.dataset_fingerprint(bench.dataset)}
        return type("Report", (), {"payload": payload})()

    monkeypatch.setattr(S, "run_bench", fake_bench)
    bench = BenchConfig(dataset=tmp_path, run=tmp_path / "run")
    path = tmp_path / "row.json"
    first = S.bench_row(SuiteConfig(out=tmp_path), bench, path)
    assert S.bench_row(SuiteConfig(out=tmp_path), bench, path) == first and len(scored) == 1  # same weights: reused
    (folders[tmp_path / "run"] / "model.safetensors").write_bytes(b"weights two")  # the run retrained
    again = S.bench_row(SuiteConfig(out=tmp_path), bench, path)
    assert len(scored) == 2 and again != first
    # a stacking row: its calibration run's weights count too
    stacked, stacked_path = replace(bench, stacking_run=tmp_path / "calibration"), tmp_path / "stacked.json"
    S.bench_row(SuiteConfig(out=tmp_path), stacked, stacked_path)
    S.bench_row(SuiteConfig(out=tmp_path), stacked, stacked_path)  # reused
    (folders[tmp_path / "calibration"] / "model.safetensors").write_bytes(b"weights two")  # calibration retrained
    S.bench_row(SuiteConfig(out=tmp_path), stacked, stacked_path)
    assert scored == ["model", "model", "stacked", "stacked"]
    del scored[2:]
    baseline, baseline_path = BenchConfig(dataset=tmp_path, predictor="majority"), tmp_path / "baseline.json"
    S.bench_row(SuiteConfig(out=tmp_path), baseline, baseline_path)
    S.bench_row(SuiteConfig(out=tmp_path), baseline, baseline_path)  # a baseline on the same data: reused
    assert scored == ["model", "model", "majority"]
    (tmp_path / "manifest.json").write_text("{}")  # the dataset rebuilt: every report of it is scored again
    S.bench_row(SuiteConfig(out=tmp_path), bench, path)
    S.bench_row(SuiteConfig(out=tmp_path), baseline, baseline_path)
    assert scored == ["model", "model", "majority", "model", "majority"]
