"""End to end on three tiny synthetic scenes: build -> split -> read back; cache, determinism, resume, failures."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from seggaussian.pipeline import dataset as build_mod
from seggaussian import shards
from seggaussian.pipeline import cache as build_cache
from seggaussian.pipeline import export
from seggaussian.labels import oracle
from seggaussian.pipeline.config import BuildConfig, SplitConfig
from seggaussian.labels.config import OracleConfig, TransferConfig
from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.pipeline.split import SceneSplitInfo, assign_splits, target_val_count
from seggaussian.pipeline.stages import transfer as transfer_stage
from seggaussian.pipeline.stages import views as views_stage

synthetic = pytest.importorskip("seggaussian.sources.synthetic.generate")


@pytest.fixture(scope="module", autouse=True)
def frozen_code_hash():
    """Other modules are being edited while tests run; freeze each code hash at its first value so that
    cache hits and misses in this file come only from what the tests change."""
    real, memo = build_cache.code_digest, {}

    def frozen(entry):
        if entry not in memo:
            memo[entry] = real(entry)
        return memo[entry]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(build_cache, "code_digest", frozen)
        yield


def _config(raw: Path, out: Path, **kw) -> BuildConfig:
    return BuildConfig(source="synthetic", root=raw, out=out, gaussians="oracle", progress=False,
                       oracle=OracleConfig(num_gaussians=1500), **kw)


def _public_files(ds: Path) -> dict[str, bytes]:
    return {str(p.relative_to(ds)): p.read_bytes() for p in sorted(ds.rglob("*"))
            if p.is_file() and ".build" not in p.parts}


def _mtimes(ds: Path) -> dict[str, int]:
    return {str(p.relative_to(ds)): p.stat().st_mtime_ns for p in sorted(ds.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def built(raw, tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "dataset"
    report = build_mod.build_dataset(_config(raw, out))
    return out, report


def test_build_split_and_read_back(built):
    ds, report = built
    assert report.counts == {"built": 3, "skipped": 0, "failed": 0}
    # CPU seconds of each stage that ran, occlusion and the Parquet writes apart, and of the build around the scenes
    for o in report.outcomes:
        assert set(o.cpu_seconds) == {"read", "gaussians", "transfer", "occlusion", "views", "shards"}, o.cpu_seconds
        assert all(v >= 0 for v in o.cpu_seconds.values()) and o.cpu_seconds["views"] > 0
    assert set(report.cpu_seconds) == {"discover", "assemble"}
    assert report.split_counts == {"train": 1, "val": 1, "xval": 1}
    splits = json.loads((ds / "splits.json").read_text())
    assert [s for s, v in splits["scenes"].items() if v == "xval"] == ["synroom0_s0"]
    assert set(splits["reasons"].values()) == {"official", "replica"}  # the synthetic tree has official lists
    names = read_class_names()
    for split in ("train", "val", "xval"):
        (scene_id,) = shards.list_scenes(ds, split)
        rec = shards.read_scene(ds, split, scene_id)
        assert rec.source == ("replica" if split == "xval" else "scannetpp")
        g = rec.gaussians
        assert len(g) > 1000 and np.isfinite(g.means).all()
        sem = g.extras["semantic"]
        assert ((sem < len(names)) | (sem == IGNORE_LABEL)).all()
        assert (g.extras["transfer_distance"] >= -1).all() and np.isfinite(g.extras["transfer_distance"]).all()
        assert len(rec.views) == 4 and {v.role for v in rec.views} == {"train", "novel"}
        for v in rec.views:
            assert v.rgb.shape == (v.camera.height, v.camera.width, 3)
            assert v.semantic.shape == v.instance.shape == (v.camera.height, v.camera.width)
            assert (v.semantic != IGNORE_LABEL).mean() > 0.5  # the oracle surface covers the views
    # plain pyarrow over the whole folder, and the footer
    table = pq.read_table(ds / "gaussians")
    assert table.num_rows == sum(o.info["num_gaussians"] for o in report.outcomes)
    footer = shards.read_footer(ds / "views" / "val-00000-of-00001.parquet")
    assert footer["seggaussian.class_names"] == list(names)
    assert footer["seggaussian.config_hash"] == json.loads((ds / "manifest.json").read_text())["config_hash"]
    # per-scene statistics reach the manifest and inspect
    info = shards.inspect_dataset(ds)
    assert {k: v["scenes"] for k, v in info["splits"].items()} == {"train": 1, "val": 1, "xval": 1}
    assert info["problems"] == []
    for o in report.outcomes:
        assert o.info["label_accuracy"]["accuracy"] >= 0.97, o.scene_id
        assert 0.0 <= o.info["transfer"]["ignored_share"] < 0.05


def test_load_dataset_if_installed(built, tmp_path):
    datasets = pytest.importorskip("datasets")
    from PIL import Image

    ds, _ = built
    loaded = datasets.load_dataset(str(ds), "views", cache_dir=str(tmp_path))
    assert set(loaded) == {"train", "val", "xval"}
    formats = set()
    for split in ("train", "val", "xval"):
        (scene_id,) = shards.list_scenes(ds, split)
        views = {v.name: v for v in shards.read_scene(ds, split, scene_id).views}
        assert loaded[split].num_rows == len(views)
        for row in loaded[split]:  # decoded images, pixel for pixel what the read API returns
            view = views[row["view_name"]]
            formats.add(row["rgb_format"])
            assert all(isinstance(row[c], Image.Image) for c in ("rgb", "semantic", "instance"))
            np.testing.assert_array_equal(np.asarray(row["rgb"]), view.rgb)
            for column in ("semantic", "instance"):
                assert row[column].mode in ("I;16", "I")
                np.testing.assert_array_equal(np.asarray(row[column]).astype(np.int32), getattr(view, column))
        assert any((np.asarray(r["semantic"]) == IGNORE_LABEL).any() for r in loaded[split])
    assert formats and formats <= {"jpeg", "png"}  # synthetic sources: their JPEGs, stored unchanged (PIL = cv2 here)


def test_rerun_changes_nothing_and_setting_change_reruns_downstream(built, raw):
    ds, _ = built
    before = _mtimes(ds)
    original = _public_files(ds)
    again = build_mod.build_dataset(_config(raw, ds))
    assert again.counts == {"built": 0, "skipped": 3, "failed": 0} and not again.assembled
    assert _mtimes(ds) == before
    # a tighter gate reruns transfer and views only; the Gaussians stay cached
    changed = build_mod.build_dataset(replace(_config(raw, ds), transfer=TransferConfig(max_distance=0.01)))
    assert {o.stages_run for o in changed.outcomes} == {("transfer", "views")}
    after = _mtimes(ds)
    stage_outputs = [k for k in before if k.endswith("gaussians_stage.parquet")]
    assert stage_outputs and all(after[k] == before[k] for k in stage_outputs)
    assert any(o.info["transfer"]["beyond_gate"] > 0 for o in changed.outcomes)
    # back to the default: same bytes as the first build
    back = build_mod.build_dataset(_config(raw, ds))
    assert {o.stages_run for o in back.outcomes} == {("transfer", "views")}
    assert _public_files(ds) == original


def test_killed_build_resumes_to_identical_bytes(built, raw, tmp_path, monkeypatch):
    ds, _ = built
    out = tmp_path / "resumed"
    calls = {"n": 0}
    real = views_stage.run_views

    def dying(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # like a kill: not caught per scene
        return real(*args, **kwargs)

    monkeypatch.setattr(views_stage, "run_views", dying)
    with pytest.raises(KeyboardInterrupt):
        build_mod.build_dataset(_config(raw, out))
    monkeypatch.setattr(views_stage, "run_views", real)
    assert not (out / "manifest.json").exists()
    resumed = build_mod.build_dataset(_config(raw, out))
    stages = {o.scene_id: o.stages_run for o in resumed.outcomes}
    assert sorted(stages.values()).count(()) == 1  # the scene finished before the kill is not redone
    assert ("views",) in stages.values()  # the interrupted scene resumes at its views stage
    first, second = _public_files(ds), _public_files(out)
    assert first.keys() == second.keys()
    for name in first:
        assert first[name] == second[name], name
    manifest = json.loads((out / "manifest.json").read_text())
    for rel, f in manifest["files"].items():
        assert shards.sha256_file(out / rel) == f["sha256"]


def test_corrupt_scene_fails_alone(built, raw, tmp_path):
    ds, _ = built
    bad_raw = tmp_path / "raw"
    shutil.copytree(raw, bad_raw)  # copy2 keeps mtimes: the other scenes stay cached
    out = tmp_path / "ds"
    shutil.copytree(ds, out)
    victim = sorted((bad_raw / "scannetpp" / "data").iterdir())[0]
    mesh = victim / "scans" / "mesh_aligned_0.05.ply"
    mesh.write_bytes(mesh.read_bytes()[:200])
    published = {p.relative_to(out): p.read_bytes() for p in out.rglob("*")
                 if p.is_file() and ".build" not in p.parts}
    report = build_mod.build_dataset(_config(bad_raw, out))
    status = {o.scene_id: o.status for o in report.outcomes}
    assert status[victim.name] == "failed"
    assert sorted(v for s, v in status.items() if s != victim.name) == ["skipped", "skipped"]
    (failed,) = [o for o in report.outcomes if o.status == "failed"]
    assert "mesh_aligned_0.05.ply" in failed.reason
    # policy: the newly failing scene keeps its last good copy; the published files do not change
    assert report.kept == (victim.name,)
    manifest = json.loads((out / "manifest.json").read_text())
    assert victim.name in manifest["scenes"] and len(manifest["scenes"]) == 3
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*")
            if p.is_file() and ".build" not in p.parts} == published
    # a scene that never built has no last good copy: it is left out
    fresh = tmp_path / "fresh"
    report = build_mod.build_dataset(_config(bad_raw, fresh))
    assert report.kept == () and victim.name not in json.loads((fresh / "manifest.json").read_text())["scenes"]


def test_cli_build_split_export(built, raw, tmp_path):
    from click.testing import CliRunner

    from cli.seggaussian_cli import main
    from seggaussian.io.ply.reader import read_gaussians_ply

    ds, _ = built
    runner = CliRunner()
    result = runner.invoke(main, ["build", "--root", str(raw), "--out", str(ds), "--gaussians", "oracle",
                                  "--oracle-gaussians", "1500", "--no-progress", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert payload["counts"] == {"built": 0, "skipped": 3, "failed": 0}
    assert all(s["cpu_seconds"] == {} for s in payload["scenes"])  # every stage cached: no CPU spent on a scene
    assert set(payload["cpu_seconds"]) == {"discover", "assemble"}
    result = runner.invoke(main, ["split", "--data", str(ds), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["counts"] == {"train": 1, "val": 1, "xval": 1}
    scene_id = shards.list_scenes(ds, "val")[0]
    out = tmp_path / "labelled.ply"
    result = runner.invoke(main, ["export-ply", str(ds), "--scene", scene_id, "--out", str(out)])
    assert result.exit_code == 0, result.output
    g, _ = read_gaussians_ply(out)
    rec = shards.read_scene(ds, "val", scene_id, views=False)
    np.testing.assert_array_equal(g.extras["semantic"], rec.gaussians.extras["semantic"])
    np.testing.assert_array_equal(g.extras["instance"], rec.gaussians.extras["instance"])
    np.testing.assert_array_equal(g.means, rec.gaussians.means)


def test_source_ply_imports_trained_plys(built, raw, tmp_path):
    ds, _ = built
    scene_id = shards.list_scenes(ds, "train")[0]
    ply_dir = tmp_path / "plys"
    export.export_scene_ply(ds, scene_id, ply_dir / f"{scene_id}.ply")
    out = tmp_path / "from_ply"
    report = build_mod.build_dataset(BuildConfig(source="ply", root=raw / "scannetpp", out=out, ply_dir=ply_dir,
                                                 scenes=(scene_id,), progress=False))
    (outcome,) = report.outcomes
    assert outcome.status == "built" and outcome.info["mode"] == "import", outcome.reason
    rec = shards.read_scene(out, shards.find_split(out, scene_id), scene_id, views=False)
    orig = shards.read_scene(ds, "train", scene_id, views=False)
    np.testing.assert_array_equal(rec.gaussians.means, orig.gaussians.means)
    np.testing.assert_array_equal(rec.gaussians.extras["semantic"], orig.gaussians.extras["semantic"])
    # a scene without a trained PLY fails alone, naming the reason
    other = BuildConfig(source="ply", root=raw / "scannetpp", out=tmp_path / "none", ply_dir=tmp_path / "empty",
                        progress=False)
    report = build_mod.build_dataset(other)
    assert all(o.status == "failed" and "no trained PLY" in o.reason for o in report.outcomes)


def test_oracle_transfer_accuracy_on_synthetic_scenes(raw):
    from seggaussian.sources import replica, scannetpp

    scenes = [scannetpp.read_scene(raw / "scannetpp", s) for s in scannetpp.list_scenes(raw / "scannetpp")]
    scenes += [replica.read_scene(raw / "replica", s) for s in replica.list_scenes(raw / "replica")]
    config = _config(raw, raw / "unused")
    for scene in scenes:
        rng = np.random.default_rng(0)
        g, truth = oracle.sample_oracle_gaussians(scene.points, scene.colors, scene.semantic, scene.faces,
                                                     OracleConfig(num_gaussians=20000), rng,
                                                     tuple(v.camera for v in scene.views))
        _, facts = transfer_stage.run_transfer(scene, g, truth, config)
        assert facts["label_accuracy"]["accuracy"] >= 0.99, (scene.scene_id, facts["label_accuracy"])


def test_code_change_reruns_the_stage(built, raw, tmp_path, monkeypatch):
    ds, _ = built
    out = tmp_path / "copy"
    shutil.copytree(ds, out)
    real = build_cache.code_digest
    monkeypatch.setattr(build_cache, "code_digest",
                        lambda entry: real(entry) + ("x" if entry == views_stage.__name__ else ""))
    report = build_mod.build_dataset(_config(raw, out))
    assert {o.stages_run for o in report.outcomes} == {("views",)}
    # the views stage alone read the labels back from the transfer's table: the same views, the same shards
    assert _public_files(out) == _public_files(ds)
    assert not list((out / ".build").rglob("labels.npz"))  # the cache keeps one copy of the labels


def test_process_pool_and_missing_ray(built, raw, tmp_path):
    ds, _ = built
    out = tmp_path / "copy"
    shutil.copytree(ds, out)
    before = _mtimes(out)
    # the workers are spawned fresh: they hash the code themselves (the frozen hashes of this file do not reach
    # them), so compare against the same dataset built in-process only when no module changed meanwhile
    report = build_mod.build_dataset(replace(_config(raw, out), jobs=2))
    assert report.counts["failed"] == 0 and len(report.outcomes) == 3
    if report.counts["skipped"] == 3:
        assert _mtimes(out) == before
    try:
        import ray  # noqa: F401
    except ImportError:
        with pytest.raises(RuntimeError, match="pip install"):
            build_mod.build_dataset(replace(_config(raw, out), executor="ray"))


@pytest.mark.slow
def test_killed_build_leaves_no_worker_fitting(raw, tmp_path):
    """`seggaussian build --jobs 2` killed (SIGKILL: no handler runs) while its two spawned workers fit leaves
    neither fitting: each watches the process that started it and exits once it is gone. The fits are given far
    more iterations than the test waits, so a worker without that watch would still be running."""
    import subprocess
    import sys

    from processes import assert_workers_end_with_their_parent, cpu_seconds

    repo = Path(__file__).resolve().parents[2]
    build = subprocess.Popen(
        [sys.executable, "-m", "cli.seggaussian_cli", "build", "--source", "synthetic", "--root", str(raw),
         "--out", str(tmp_path / "dataset"), "--jobs", "2", "--gaussians", "fit", "--fit-iterations", "1000000",
         "--no-progress"], cwd=repo, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def busy(workers):  # two workers past their start-up (imports), working on a scene each
        return sum(cpu_seconds(w) >= 5.0 for w in workers) >= 2

    assert_workers_end_with_their_parent(build, busy)


def test_split_rules():
    cfg = SplitConfig()
    scenes = {f"s{i:02d}": SceneSplitInfo("scannetpp", None) for i in range(12)}
    scenes.update({"r0": SceneSplitInfo("replica", None), "o1": SceneSplitInfo("scannetpp", "val")})
    first = assign_splits(scenes, cfg)
    assert first.assignments["r0"] == "xval" and first.assignments["o1"] == "val"
    assert first.counts["val"] == target_val_count(13, cfg.ratios) == 2
    # adding scenes never moves an existing one
    more = dict(scenes, **{f"n{i:02d}": SceneSplitInfo("scannetpp", None) for i in range(20)})
    second = assign_splits(more, cfg, previous=first.assignments)
    assert all(second.assignments[s] == first.assignments[s] for s in scenes)
    assert second.counts["val"] == target_val_count(33, cfg.ratios)
    # stable: the same input gives the same output; small sets keep one val scene
    assert assign_splits(scenes, cfg) == first
    assert target_val_count(2, cfg.ratios) == 1 and target_val_count(1, cfg.ratios) == 0
    assert target_val_count(280, cfg.ratios) == 50


def test_quats_from_z_axis_rotates_z_onto_the_normal():
    from seggaussian.core.rotations import quats_to_rotmats

    rng = np.random.default_rng(0)
    normals = np.concatenate([rng.normal(size=(50, 3)), [[0, 0, 1.0], [0, 0, -1.0], [1e-12, 0, -1.0]]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    q = oracle.quats_from_z_axis(normals)
    assert np.isfinite(q).all()
    rotated_z = quats_to_rotmats(q)[:, :, 2]
    np.testing.assert_allclose(rotated_z, normals, atol=1e-6)


def test_oracle_samples_lie_on_the_mesh_with_their_surface_label():
    pytest.importorskip("open3d")
    from seggaussian.core.cameras import Camera, intrinsics, look_at
    from seggaussian.labels.scoring import surface_labels

    # two labelled squares: floor (class 1) and a wall (class 2), seen by one camera
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 0], [1, 1, 0], [1, 1, 1], [0, 1, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    semantic = np.array([1, 1, 1, 1, 2, 2, 2, 2], np.int32)
    colors = np.full((8, 3), 128, np.uint8)
    cam = Camera(intrinsics(40, 40, 32, 24), look_at([0.5, -1.0, 0.8], [0.5, 0.7, 0.3]), 64, 48)
    for cameras in ((cam,), ()):
        g, truth = oracle.sample_oracle_gaussians(v, colors, semantic, faces, OracleConfig(num_gaussians=500),
                                                     np.random.default_rng(1), cameras)
        assert 0 < len(g) <= 500 and np.isfinite(g.log_scales).all()
        on_floor = np.abs(g.means[:, 2]) < 1e-6
        on_wall = np.abs(g.means[:, 1] - 1) < 1e-6
        assert (on_floor | on_wall).all()
        assert set(truth.tolist()) == {1, 2}
        # away from the shared edge, the truth is the surface's own label
        clear = (g.means[:, 2] > 0.05) | (g.means[:, 1] < 0.95)
        np.testing.assert_array_equal(truth[clear], np.where(on_floor, 1, 2)[clear])
        np.testing.assert_array_equal(surface_labels(g.means, v, faces, semantic)[clear], truth[clear])
    # a point cloud: Gaussians on the points, truth = their labels
    g, truth = oracle.sample_oracle_gaussians(v, colors, semantic, None, OracleConfig(num_gaussians=20),
                                                 np.random.default_rng(1))
    assert len(g) == 20 and set(truth.tolist()) <= {1, 2}
    empty, t0 = oracle.sample_oracle_gaussians(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32),
                                                  None, OracleConfig(), np.random.default_rng(0))
    assert len(empty) == 0 and len(t0) == 0


def test_ray_executor_builds_the_same_bytes(built, raw, tmp_path, monkeypatch):
    """Scenes as Ray tasks on a local Ray instance give byte-identical shards to the local executor."""
    ray = pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'seggaussian[ray]')")
    import ray._private.ray_constants as ray_constants

    # Ray was imported already: its switch RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 (the node address is 127.0.0.1, not
    # the machine's outward one), read at import, is set on the module
    monkeypatch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", False)
    ds, _ = built
    out = tmp_path / "ray"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        assert {n["NodeManagerAddress"] for n in ray.nodes()} == {"127.0.0.1"}
        report = build_mod.build_dataset(replace(_config(raw, out), executor="ray"))
    finally:
        ray.shutdown()
    assert report.counts["failed"] == 0 and report.counts["built"] == 3
    assert [n.address for n in report.nodes] == ["127.0.0.1"]
    local, remote = _public_files(ds), _public_files(out)
    shards = [name for name in local if name.endswith(".parquet")]
    assert shards and all(local[name] == remote[name] for name in shards)


def test_export_ply_color_by_writes_palette_colours_and_legend(built, tmp_path):
    from click.testing import CliRunner

    from cli.seggaussian_cli import main
    from seggaussian.io.ply.reader import read_gaussians_ply
    from seggaussian.labels.palette import IGNORE_RGB, label_colours

    ds, _ = built
    scene_id = shards.list_scenes(ds, "train")[0]
    rec = shards.read_scene(ds, "train", scene_id, views=False)
    for by in ("semantic", "instance"):
        out = tmp_path / f"{by}.ply"
        result = CliRunner().invoke(main, ["export-ply", str(ds), "--scene", scene_id, "--out", str(out),
                                           "--color-by", by, "--json"])
        assert result.exit_code == 0, result.output
        g, _ = read_gaussians_ply(out)
        labels = rec.gaussians.extras[by]
        np.testing.assert_array_equal(g.extras[by], labels)                      # labels stay as properties
        np.testing.assert_allclose(g.dc_colors() * 255, label_colours(labels), atol=1e-3)
        assert g.sh_degree == rec.gaussians.sh_degree and not g.sh[:, 1:].any()  # higher bands zeroed
        legend = json.loads((tmp_path / f"{by}.legend.json").read_text())
        assert legend["by"] == by and legend["ignore"]["rgb"] == list(IGNORE_RGB)
        assert sum(e["count"] for e in legend["entries"]) == len(g)
        if by == "semantic":
            assert {e["name"] for e in legend["entries"]} <= set(read_class_names()) | {"ignore"}
        assert (tmp_path / f"{by}.legend.png").stat().st_size > 0
        assert not list(tmp_path.glob(".*"))                                      # no temp files left


@pytest.mark.parametrize("suffix", [".spz", ".ksplat"])
def test_source_ply_reads_other_splat_formats(built, raw, tmp_path, suffix):
    from seggaussian.io.formats import write_gaussians
    from seggaussian.io.ksplat import BLOCK_SIZE, DEFAULT_RANGE, bucket_layout

    ds, _ = built
    scene_id = shards.list_scenes(ds, "train")[0]
    orig = shards.read_scene(ds, "train", scene_id, views=False)
    ply_dir = tmp_path / "splats"
    write_gaussians(ply_dir / f"{scene_id}{suffix}", orig.gaussians)
    report = build_mod.build_dataset(BuildConfig(source="ply", root=raw / "scannetpp", out=tmp_path / "from_splat",
                                                 ply_dir=ply_dir, scenes=(scene_id,), progress=False))
    (outcome,) = report.outcomes
    assert outcome.status == "built" and outcome.info["mode"] == "import", outcome.reason
    rec = shards.read_scene(tmp_path / "from_splat", shards.find_split(tmp_path / "from_splat", scene_id), scene_id,
                            views=False)
    assert len(rec.gaussians) == len(orig.gaussians)
    if suffix == ".spz":
        np.testing.assert_allclose(rec.gaussians.means, orig.gaussians.means, atol=0.5 / 4096 + 1e-6)
    else:                                              # level 1 (default): bucket order, 2.5 m / 32767 steps
        expected = orig.gaussians.means[bucket_layout(orig.gaussians.means).order]
        np.testing.assert_allclose(rec.gaussians.means, expected, atol=BLOCK_SIZE / 4 / DEFAULT_RANGE[1] + 1e-6)
