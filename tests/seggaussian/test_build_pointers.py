"""The build cache keeps no copy of the shards: after the assembly a scene's tables are pointers into the shards.

Checked on three tiny synthetic scenes: the per-scene tables are gone and the cache is smaller than the shards; a
rebuild finds every stage cached and assembles the same bytes from the pointers, also when scenes move between
shard files; a removed or altered shard is a cache miss that rebuilds the same bytes; the gaussians stage's
uncompressed output of earlier versions is a clean miss; its compressed output reads back exactly.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from seggaussian import shards
from seggaussian.core.gaussians import Gaussians
from seggaussian.labels.config import OracleConfig
from seggaussian.pipeline import dataset as build_mod
from seggaussian.pipeline import fragments
from seggaussian.pipeline.assembly import split_dataset
from seggaussian.pipeline.config import BuildConfig, SplitConfig
from seggaussian.pipeline.stages import gaussians as gaussians_stage
from seggaussian.shards.config import ShardConfig
from seggaussian.shards.rows import SceneRows, read_scene_rows, rows_intact
from seggaussian.util.atomic import is_temp_name

pytest.importorskip("seggaussian.sources.synthetic.generate")


def _config(raw: Path, out: Path, **kw) -> BuildConfig:
    return BuildConfig(source="synthetic", root=raw, out=out, gaussians="oracle", progress=False,
                       oracle=OracleConfig(num_gaussians=1500), **kw)


def _public(ds: Path) -> dict[str, bytes]:
    return {str(p.relative_to(ds)): p.read_bytes() for p in sorted(ds.rglob("*"))
            if p.is_file() and ".build" not in p.parts}


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def built(raw, tmp_path_factory):
    out = tmp_path_factory.mktemp("pointers") / "dataset"
    report = build_mod.build_dataset(_config(raw, out))
    assert report.counts == {"built": 3, "skipped": 0, "failed": 0} and report.assembled
    return out


def _copy(ds: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(ds, out)  # copy2 keeps mtimes: the raw fingerprints and the cache stay as they were
    return out


def test_assembled_scenes_keep_pointers_not_tables_and_rebuild_the_same_bytes(built, raw, tmp_path):
    scene_dirs = sorted((built / ".build" / "scenes").iterdir())
    assert len(scene_dirs) == 3
    for d in scene_dirs:
        assert not (d / "gaussians.parquet").exists() and not (d / "views.parquet").exists()
        pointers = fragments.read_pointers(d)
        assert sorted(pointers) == ["gaussians", "views"]
        for table, entry in pointers.items():
            rows = SceneRows(**entry["rows"])
            assert rows.scene_id == d.name and rows.rows > 0 and rows_intact(built, rows)
            # the rows it points at are the scene's rows as the reader of the dataset sees them
            split = shards.find_split(built, d.name)
            record = shards.read_scene(built, split, d.name)
            expected = len(record.gaussians) if table == "gaussians" else len(record.views)
            assert read_scene_rows(built, rows).num_rows == expected == rows.rows
    record = json.loads((built / ".build" / "build.json").read_text())
    assert all(isinstance(f, dict) for v in record["scenes"].values() for f in v["fragments"].values())
    shard_bytes = _bytes(built / "gaussians") + _bytes(built / "views")
    assert _bytes(built / ".build") < shard_bytes
    # the same arguments again: nothing runs, nothing is written
    out = _copy(built, tmp_path)
    again = build_mod.build_dataset(_config(raw, out))
    assert again.counts == {"built": 0, "skipped": 3, "failed": 0} and not again.assembled
    # an assembly from the pointers alone (its state forgotten) writes the same bytes
    (out / ".build" / "assembly.json").unlink()
    report = build_mod.build_dataset(_config(raw, out))
    assert report.counts["skipped"] == 3 and report.assembled
    assert _public(out) == _public(built)


def _edit_record(out: Path, scene_id: str, official_split: str, shard_bytes: int) -> None:
    path = out / ".build" / "build.json"
    record = json.loads(path.read_text())
    record["scenes"][scene_id]["official_split"] = official_split
    record["config"]["shards"]["shard_bytes"] = shard_bytes
    path.write_text(json.dumps(record))


def test_moving_scenes_between_shard_files_reads_them_from_the_files_being_replaced(built, raw, tmp_path):
    out = _copy(built, tmp_path)
    splits = json.loads((out / "splits.json").read_text())["scenes"]
    mover = next(s for s, split in splits.items() if split == "train")
    # the train scene joins val, one scene a shard: its rows come from the train shard, which goes only at the end
    _edit_record(out, mover, "val", 1)
    split_dataset(out, SplitConfig(reassign=True))
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(manifest["files"]) == [f"{t}/{n}" for t in ("gaussians", "views")
                                         for n in ("val-00000-of-00002.parquet", "val-00001-of-00002.parquet",
                                                   "xval-00000-of-00001.parquet")]
    assert manifest["scenes"][mover]["split"] == "val"
    for scene_id, entry in manifest["scenes"].items():
        ours, theirs = (shards.read_scene(ds, split, scene_id) for ds, split in ((out, entry["split"]),
                                                                                    (built, splits[scene_id])))
        np.testing.assert_array_equal(ours.gaussians.means, theirs.gaussians.means)
        np.testing.assert_array_equal(ours.gaussians.extras["semantic"], theirs.gaussians.extras["semantic"])
        for a, b in zip(ours.views, theirs.views, strict=True):
            np.testing.assert_array_equal(a.semantic, b.semantic)
    # and back: the bytes of the first build
    _edit_record(out, mover, "train", ShardConfig().shard_bytes)
    split_dataset(out, SplitConfig(reassign=True))
    assert _public(out) == _public(built)
    assert not [p for p in out.rglob("*") if is_temp_name(p.name)]


def test_a_removed_or_altered_shard_is_a_miss_that_rebuilds_the_same_bytes(built, raw, tmp_path):
    out = _copy(built, tmp_path)
    manifest = json.loads((out / "manifest.json").read_text())
    gaussians_shard = next(rel for rel in manifest["files"] if rel.startswith("gaussians/train"))
    (out / gaussians_shard).unlink()
    report = build_mod.build_dataset(_config(raw, out))
    runs = {o.scene_id: o.stages_run for o in report.outcomes}
    assert {runs[s] for s in manifest["files"][gaussians_shard]["scenes"]} == {("transfer",)}
    assert _public(out) == _public(built)
    # one byte of a scene's column chunks changed, the size kept: that scene's views run again, no other stage
    views_shard = next(rel for rel in manifest["files"] if rel.startswith("views/train"))
    first = manifest["files"][views_shard]["scenes"][0]
    rows = SceneRows(**fragments.read_pointers(out / ".build" / "scenes" / first)["views"]["rows"])
    data = bytearray((out / views_shard).read_bytes())
    data[100] ^= 0xFF  # past the magic, inside the first row group: the first scene's
    (out / views_shard).write_bytes(bytes(data))
    assert not rows_intact(out, rows)
    with pytest.raises(shards.ShardError, match=f"{views_shard}.*scene {first}"):
        read_scene_rows(out, rows)
    report = build_mod.build_dataset(_config(raw, out))
    runs = {o.scene_id: o.stages_run for o in report.outcomes}
    assert runs[first] == ("views",) and sorted(runs.values()).count(()) == 2
    assert _public(out) == _public(built)


def test_an_uncompressed_gaussians_output_of_an_earlier_version_is_a_clean_miss(built, raw, tmp_path):
    out = _copy(built, tmp_path)
    scene_dir = sorted((out / ".build" / "scenes").iterdir())[0]
    g, truth = gaussians_stage.load_gaussians(scene_dir)
    (scene_dir / gaussians_stage.OUTPUTS[0]).unlink()
    np.savez(scene_dir / gaussians_stage.FORMER_OUTPUT, means=g.means, quats=g.quats, log_scales=g.log_scales,
             opacity_logits=g.opacity_logits, sh=g.sh, truth=truth)
    report = build_mod.build_dataset(_config(raw, out))
    runs = {o.scene_id: o.stages_run for o in report.outcomes}
    assert runs[scene_dir.name] == ("gaussians",)  # the same Gaussians again: transfer and views stay cached
    assert not (scene_dir / gaussians_stage.FORMER_OUTPUT).exists()
    assert _public(out) == _public(built)


@pytest.mark.parametrize("count,degree", [(0, 0), (257, 3)])
def test_the_gaussians_stage_output_reads_back_exactly(tmp_path, count, degree):
    rng = np.random.default_rng(0)
    f32 = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    g = Gaussians(f32(count, 3), f32(count, 4), f32(count, 3), f32(count), f32(count, (degree + 1) ** 2, 3))
    truth = rng.integers(0, 100, count).astype(np.int32) if count else None
    gaussians_stage.save_gaussians(tmp_path, g, truth)
    back, back_truth = gaussians_stage.load_gaussians(tmp_path)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        ours, theirs = getattr(back, name), getattr(g, name)
        assert ours.dtype == theirs.dtype and ours.shape == theirs.shape
        np.testing.assert_array_equal(ours, theirs)
    if truth is None:
        assert back_truth is None
    else:
        np.testing.assert_array_equal(back_truth, truth)
    assert [p.name for p in tmp_path.iterdir()] == [gaussians_stage.OUTPUTS[0]]  # no temporary left
