"""Parquet shards: round trip, footer metadata, row groups per scene, determinism, atomic/unchanged writes."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from seggaussian import shards
from seggaussian.shards.config import ShardConfig
from seggaussian.core.cameras import Camera, intrinsics, look_at
from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.core.gaussians import Gaussians
from seggaussian.shards import read as shard_read
from seggaussian.shards.schema import SCHEMA_VERSION


def _gaussians(rng, n, degree=0):
    k = (degree + 1) ** 2
    g = Gaussians.from_arrays(rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 3)) - 3,
                              rng.normal(size=n), rng.normal(size=(n, k, 3)))
    sem = rng.integers(0, 100, n).astype(np.int32)
    sem[::7] = IGNORE_LABEL
    return g.with_extras(semantic=sem, instance=rng.integers(0, 40, n).astype(np.int32),
                         multilabel=rng.integers(0, 100, (n, 3)).astype(np.int32),
                         transfer_distance=rng.uniform(0, 0.05, n).astype(np.float32))


def _views(rng, count, w=24, h=16):
    rows, raw = [], []
    for i in range(count):
        cam = Camera(intrinsics(20, 20, w / 2, h / 2), look_at([2.0, i, 1.0], [0, 0, 0]), w, h)
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        sem = rng.integers(0, 100, (h, w)).astype(np.int32)
        sem[0] = IGNORE_LABEL
        inst = rng.integers(0, 3000, (h, w)).astype(np.int32)
        inst[-1, -1] = IGNORE_LABEL - 1  # the top bits of the 16-bit maps
        rows.append(shards.ViewRow(f"frame{i:06d}.jpg", "novel" if i % 8 == 7 else "train", cam,
                                   shards.encode_rgb(rgb), shards.encode_label_map(sem),
                                   shards.encode_label_map(inst), float((sem != IGNORE_LABEL).mean())))
        raw.append((rgb, sem, inst, cam))
    return rows, raw


def _write_fragments(tmp_path, rng, sizes, degrees=None, views=3):
    config = ShardConfig(row_group_bytes=4096)
    scenes, truth = {}, {}
    for j, (sid, n) in enumerate(sizes.items()):
        g = _gaussians(rng, n, (degrees or {}).get(sid, 0))
        rows, raw = _views(rng, views)
        frag = {}
        for table_name, table in (("gaussians", shards.gaussians_table(sid, g)), ("views", shards.views_table(sid, rows))):
            frag[table_name] = tmp_path / "cache" / sid / f"{table_name}.parquet"
            shards.write_parquet_atomic(frag[table_name], table_name, [table], config)
        scenes[sid] = {"fragments": frag, "source": "scannetpp", "num_gaussians": n, "num_views": views,
                       "transfer": {"ignored": int((g.extras["semantic"] == IGNORE_LABEL).sum()), "ignored_share": 0.1,
                                    "class_histogram": {"3": 5}, "distance_quantiles": {"q50": 0.01, "q99": 0.04}}}
        truth[sid] = (g, raw)
    return scenes, truth, config


def test_round_trip_and_footer(tmp_path):
    rng = np.random.default_rng(0)
    scenes, truth, config = _write_fragments(tmp_path, rng, {"a": 500, "b": 0, "c": 300, "d": 200},
                                             degrees={"c": 3})
    names = read_class_names()
    assignments = {"a": "train", "b": "train", "c": "val", "d": "xval"}
    ds = tmp_path / "ds"
    manifest = shards.write_dataset(ds, assignments, scenes, config, names, "cfg123")
    assert shards.list_scenes(ds, "train") == ["a", "b"]
    assert shards.list_scenes(ds, "val") == ["c"]
    for sid, split in assignments.items():
        rec = shards.read_scene(ds, split, sid)
        g, raw = truth[sid]
        assert rec.scene_id == sid and rec.source == "scannetpp"
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(rec.gaussians, name), getattr(g, name))
        for name in ("semantic", "instance", "multilabel", "transfer_distance"):
            np.testing.assert_array_equal(rec.gaussians.extras[name], g.extras[name])
        assert len(rec.views) == len(raw)
        for v, (rgb, sem, inst, cam) in zip(rec.views, raw):
            np.testing.assert_array_equal(v.rgb, rgb)
            np.testing.assert_array_equal(v.semantic, sem)
            np.testing.assert_array_equal(v.instance, inst)
            np.testing.assert_array_equal(v.camera.K, cam.K)
            np.testing.assert_array_equal(v.camera.viewmat, cam.viewmat)
    # footer metadata
    path = ds / "gaussians" / "train-00000-of-00001.parquet"
    footer = shards.read_footer(path)
    assert footer["seggaussian.schema_version"] == SCHEMA_VERSION
    assert footer["seggaussian.class_names"] == list(names)
    assert footer["seggaussian.config_hash"] == "cfg123"
    assert footer["seggaussian.split"] == "train" and footer["seggaussian.table"] == "gaussians"
    # manifest: rows, bytes, sha256 per file
    for rel, f in manifest["files"].items():
        assert (ds / rel).stat().st_size == f["bytes"]
        assert shards.sha256_file(ds / rel) == f["sha256"]
        assert pq.ParquetFile(ds / rel).metadata.num_rows == f["rows"]
    assert json.loads((ds / "manifest.json").read_text()) == manifest
    card = (ds / "README.md").read_text()
    assert card.startswith("---\nconfigs:") and "path: gaussians/train-*.parquet" in card


def test_row_groups_never_span_scenes_and_are_sized_in_bytes(tmp_path):
    rng = np.random.default_rng(1)
    scenes, _, config = _write_fragments(tmp_path, rng, {"a": 700, "b": 650})
    ds = tmp_path / "ds"
    shards.write_dataset(ds, {"a": "train", "b": "train"}, scenes, config, ["x"], "h")
    pf = pq.ParquetFile(ds / "gaussians" / "train-00000-of-00001.parquet")
    assert pf.metadata.num_row_groups > 2  # 4 KiB groups
    seen = []
    for i in range(pf.metadata.num_row_groups):
        ids = set(pf.read_row_group(i, columns=["scene_id"]).column(0).to_pylist())
        assert len(ids) == 1
        seen.append(ids.pop())
    assert seen == sorted(seen)
    assert shard_read._scene_row_groups(pf, "b", ds) == [i for i, s in enumerate(seen) if s == "b"]


def test_shards_split_by_bytes_and_stale_files_removed(tmp_path):
    rng = np.random.default_rng(2)
    scenes, _, _ = _write_fragments(tmp_path, rng, {f"s{i}": 300 for i in range(4)})
    ds = tmp_path / "ds"
    small = ShardConfig(row_group_bytes=4096, shard_bytes=1)
    shards.write_dataset(ds, {s: "train" for s in scenes}, scenes, small, ["x"], "h")
    names = sorted(p.name for p in (ds / "gaussians").iterdir())
    assert names == [f"train-{i:05d}-of-00004.parquet" for i in range(4)]
    for s in scenes:
        assert len(shards.read_scene(ds, "train", s).gaussians) == 300
    shards.write_dataset(ds, {s: "train" for s in scenes}, scenes, ShardConfig(row_group_bytes=4096), ["x"], "h")
    assert sorted(p.name for p in (ds / "gaussians").iterdir()) == ["train-00000-of-00001.parquet"]
    # moving every scene to val removes the train shards
    shards.write_dataset(ds, {s: "val" for s in scenes}, scenes, ShardConfig(row_group_bytes=4096), ["x"], "h")
    assert sorted(p.name for p in (ds / "gaussians").iterdir()) == ["val-00000-of-00001.parquet"]


def _dead_pid() -> int:
    """The pid of a process that has exited (what a killed writer leaves in its temp names)."""
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def test_deterministic_bytes_and_unchanged_files_keep_mtime(tmp_path):
    rng = np.random.default_rng(3)
    scenes, _, config = _write_fragments(tmp_path, rng, {"a": 100, "b": 50})
    a, b = tmp_path / "one", tmp_path / "two"
    shards.write_dataset(a, {"a": "train", "b": "val"}, scenes, config, ["x"], "h")
    shards.write_dataset(b, {"a": "train", "b": "val"}, scenes, config, ["x"], "h")
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    mtimes = {rel: (a / rel).stat().st_mtime_ns for rel in files}
    shards.write_dataset(a, {"a": "train", "b": "val"}, scenes, config, ["x"], "h")
    assert {rel: (a / rel).stat().st_mtime_ns for rel in files} == mtimes
    assert not [p for p in a.rglob(".*tmp*")]
    # a temp file left by a killed writer is cleaned up by the next write
    dead = _dead_pid()
    (a / "gaussians" / f".train-00000-of-00001.parquet.tmp-{dead}").write_bytes(b"partial")
    shards.write_dataset(a, {"a": "train", "b": "val"}, scenes, config, ["x"], "h")
    assert not [p for p in a.rglob(".*tmp*")]


def test_plain_pyarrow_and_iter_scenes(tmp_path):
    rng = np.random.default_rng(4)
    scenes, _, config = _write_fragments(tmp_path, rng, {"a": 40, "b": 60})
    ds = tmp_path / "ds"
    shards.write_dataset(ds, {"a": "train", "b": "train"}, scenes, config, ["x"], "h")
    table = pq.read_table(ds / "gaussians")
    assert table.num_rows == 100
    assert [r.scene_id for r in shards.iter_scenes(ds, "train")] == ["a", "b"]
    views = pq.read_table(ds / "views" / "train-00000-of-00001.parquet")
    assert set(views.column("rgb_format").to_pylist()) == {"png"}


def test_load_dataset_if_installed(tmp_path):
    datasets = pytest.importorskip("datasets")
    rng = np.random.default_rng(5)
    scenes, _, config = _write_fragments(tmp_path, rng, {"a": 40, "b": 60})
    ds = tmp_path / "ds"
    shards.write_dataset(ds, {"a": "train", "b": "val"}, scenes, config, ["x"], "h")
    loaded = datasets.load_dataset("parquet", data_files={"train": str(ds / "gaussians" / "train-*.parquet"),
                                                         "val": str(ds / "gaussians" / "val-*.parquet")},
                                   cache_dir=str(tmp_path / "hf"))
    assert loaded["train"].num_rows == 40 and loaded["val"].num_rows == 60


def _assert_views_match(loaded_split, records: dict) -> int:
    """Every row of a ``load_dataset(..., "views")`` split decodes to the pixels ``read_scene`` returns;
    ``records``: scene id -> SceneRecord. Returns the number of rows checked."""
    from PIL import Image

    by_name = {(sid, v.name): v for sid, rec in records.items() for v in rec.views}
    for row in loaded_split:
        view = by_name.pop((row["scene_id"], row["view_name"]))
        for column in ("rgb", "semantic", "instance"):
            assert isinstance(row[column], Image.Image), column
        assert row["rgb"].mode == "RGB"
        np.testing.assert_array_equal(np.asarray(row["rgb"]), view.rgb)
        for column in ("semantic", "instance"):
            image = row[column]
            assert image.mode in ("I;16", "I"), image.mode  # 16 bit, never 8
            assert image.size == (view.camera.width, view.camera.height)
            np.testing.assert_array_equal(np.asarray(image).astype(np.int32), getattr(view, column))
    assert not by_name, f"views missing from load_dataset: {sorted(by_name)}"
    return len(loaded_split)


def test_load_dataset_views_decode_images(tmp_path):
    """``load_dataset(DATASET, "views")`` (the card's configs and features) gives PIL images equal to what
    ``read_scene`` decodes: RGB exactly, the 16-bit label maps exactly (65535 and 65534 included)."""
    datasets = pytest.importorskip("datasets")
    rng = np.random.default_rng(5)
    scenes, truth, config = _write_fragments(tmp_path, rng, {"a": 40, "b": 60, "c": 10})
    ds = tmp_path / "ds"
    assignments = {"a": "train", "b": "train", "c": "val"}
    shards.write_dataset(ds, assignments, scenes, config, ["x"], "h")
    views = datasets.load_dataset(str(ds), "views", cache_dir=str(tmp_path / "hf"))
    assert set(views) == {"train", "val"}
    for split in ("train", "val"):
        records = {s: shards.read_scene(ds, split, s) for s in shards.list_scenes(ds, split)}
        assert _assert_views_match(views[split], records) == 3 * len(records)
    sem = np.asarray(views["train"][0]["semantic"])
    inst = np.asarray(views["train"][0]["instance"])
    assert (sem == IGNORE_LABEL).any() and (inst == IGNORE_LABEL - 1).any()
    # the raw pixels are the ones written (not only equal to our own decoder's)
    rgb, sem_truth, inst_truth, _ = truth["a"][1][0]
    first = next(r for r in views["train"] if r["scene_id"] == "a")
    np.testing.assert_array_equal(np.asarray(first["rgb"]), rgb)
    np.testing.assert_array_equal(np.asarray(first["semantic"]).astype(np.int32), sem_truth)
    np.testing.assert_array_equal(np.asarray(first["instance"]).astype(np.int32), inst_truth)
    # the other columns keep their types; the card's features match the shards' Arrow schemas
    features = views["train"].features
    inferred = datasets.Features.from_arrow_schema(pq.read_schema(ds / "views" / "train-00000-of-00001.parquet"))
    assert set(features) == set(inferred)
    for name in features:
        if name in ("rgb", "semantic", "instance"):
            assert isinstance(features[name], datasets.Image) and inferred[name] == datasets.Value("binary")
        else:
            assert features[name] == inferred[name], name
    gaussians = datasets.load_dataset(str(ds), "gaussians", cache_dir=str(tmp_path / "hf"))
    inferred = datasets.Features.from_arrow_schema(pq.read_schema(ds / "gaussians" / "train-00000-of-00001.parquet"))
    assert gaussians["train"].features == inferred
    assert gaussians["train"].num_rows == 100 and gaussians["val"].num_rows == 10
    np.testing.assert_array_equal(np.asarray(gaussians["val"]["means"], np.float32), truth["c"][0].means)


def test_image_columns_stay_binary_and_old_cards_still_read(tmp_path):
    """The shards keep the 1.0 layout: image columns are plain ``binary`` (PNG/JPEG bytes), no ``huggingface``
    schema metadata; only the card declares them as images. A dataset written before the card declared
    features (old card) reads the same through the read API, and ``load_dataset`` gives it bytes."""
    rng = np.random.default_rng(8)
    scenes, truth, config = _write_fragments(tmp_path, rng, {"a": 30})
    ds = tmp_path / "ds"
    shards.write_dataset(ds, {"a": "train"}, scenes, config, ["x"], "h")
    schema = pq.read_schema(ds / "views" / "train-00000-of-00001.parquet")
    for column in ("rgb", "semantic", "instance"):
        assert schema.field(column).type == pa.binary() and not schema.field(column).nullable
    assert b"huggingface" not in (schema.metadata or {})
    card = (ds / "README.md").read_text()
    header = card.split("---\n")[1]
    for column in ("rgb", "semantic", "instance"):
        assert f"  - name: {column}\n    dtype: image\n" in header
    # an old card: configs only, no dataset_info
    old_header = header.split("dataset_info:\n")[0] + "tags:\n" + header.split("\ntags:\n")[1]
    (ds / "README.md").write_text("---\n" + old_header + "---\n\n# old card\n")
    rec = shards.read_scene(ds, "train", "a", verify=True)
    for v, (rgb, sem, inst, _) in zip(rec.views, truth["a"][1]):
        np.testing.assert_array_equal(v.rgb, rgb)
        np.testing.assert_array_equal(v.semantic, sem)
        np.testing.assert_array_equal(v.instance, inst)
    datasets = pytest.importorskip("datasets")
    views = datasets.load_dataset(str(ds), "views", cache_dir=str(tmp_path / "hf"))
    row = views["train"][0]
    assert isinstance(row["rgb"], bytes)
    np.testing.assert_array_equal(shards.decode_label_map(row["semantic"]), rec.views[0].semantic)
    # rewriting the dataset restores the card (the shards stay untouched)
    mtimes = {p: p.stat().st_mtime_ns for p in ds.rglob("*.parquet")}
    shards.write_dataset(ds, {"a": "train"}, scenes, config, ["x"], "h")
    assert (ds / "README.md").read_text() == card
    assert {p: p.stat().st_mtime_ns for p in ds.rglob("*.parquet")} == mtimes


def test_card_features_follow_the_schemas():
    from seggaussian.shards import card

    lines = card.feature_lines("views")
    assert lines[:2] == ["- name: scene_id", "  dtype: string"]
    assert "\n".join(lines).count("dtype: image") == 3
    i = lines.index("- name: K")
    assert lines[i + 1:i + 3] == ["  sequence: float64", "  length: 9"]
    g = card.feature_lines("gaussians")
    i = g.index("- name: sh")
    assert g[i + 1] == "  sequence: float32" and not g[i + 2].startswith("  length")
    with pytest.raises(ValueError, match="no Hugging Face dtype"):
        card._dtype(pa.date32())


def test_label_map_encoding_and_errors(tmp_path):
    labels = np.array([[0, 1], [IGNORE_LABEL, 65534]])
    assert shards.decode_label_map(shards.encode_label_map(labels)).tolist() == labels.tolist()
    with pytest.raises(ValueError, match="outside"):
        shards.encode_label_map(np.array([[70000]]))
    with pytest.raises(shards.ShardError, match="16-bit"):
        shards.decode_label_map(shards.encode_rgb(np.zeros((2, 2, 3), np.uint8)))
    with pytest.raises(shards.ShardError, match="manifest.json"):
        shards.list_scenes(tmp_path, "train")
    g = Gaussians.from_arrays(np.zeros((2, 3)), np.ones((2, 4)), np.zeros((2, 3)), np.zeros(2), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="transfer_distance"):
        shards.gaussians_table("a", g.with_extras(semantic=np.zeros(2), instance=np.zeros(2)))
    with pytest.raises(ValueError, match="NaN"):
        shards.gaussians_table("a", g.with_extras(semantic=np.zeros(2), instance=np.zeros(2),
                                                  transfer_distance=np.array([0.0, np.nan])))


def test_inspect_dataset(tmp_path):
    rng = np.random.default_rng(6)
    scenes, _, config = _write_fragments(tmp_path, rng, {"a": 40, "b": 60, "r": 10})
    ds = tmp_path / "ds"
    shards.write_dataset(ds, {"a": "train", "b": "val", "r": "xval"}, scenes, config, read_class_names(), "h")
    info = shards.inspect_dataset(ds)
    assert {k: v["scenes"] for k, v in info["splits"].items()} == {"train": 1, "val": 1, "xval": 1}
    assert info["splits"]["val"]["gaussians"] == 60
    assert info["splits"]["train"]["class_histogram"] == {"bed" if read_class_names()[3] == "bed" else read_class_names()[3]: 5}
    assert info["problems"] == []
    (ds / "views" / "val-00000-of-00001.parquet").unlink()
    assert any("missing" in p for p in shards.inspect_dataset(ds)["problems"])


# --- corrupted shards: named by inspect --verify, by training and by the benchmark -----------------------
def _corrupt(dataset, how: str):
    """Truncate, or flip bytes in place (same size), of the gaussians shard of the train split."""
    manifest = json.loads((dataset / shards.MANIFEST_NAME).read_text())
    rel = next(r for r in manifest["files"] if r.startswith("gaussians/train"))
    path = dataset / rel
    data = bytearray(path.read_bytes())
    if how == "truncated":
        data = data[: len(data) // 2]
    else:  # flip bytes in the middle of the data pages: same size, the footer still parses
        for i in range(len(data) // 3, len(data) // 3 + 64):
            data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    return rel, manifest["files"][rel]["scenes"]


@pytest.fixture
def corrupted_dataset(tmp_path, request):
    from test_bench import _write_tiny_dataset

    dataset = _write_tiny_dataset(tmp_path / "tiny")
    rel, scenes = _corrupt(dataset, request.param)
    shard_read._VERIFIED.clear()
    return dataset, rel, scenes, request.param


@pytest.mark.parametrize("corrupted_dataset", ["truncated", "flipped"], indirect=True)
def test_corrupted_shard_is_named_by_inspect_train_and_bench(corrupted_dataset, tmp_path):
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main as ov_main
    from cli.seggaussian_cli import main as seg_main

    dataset, rel, scenes, how = corrupted_dataset
    # inspect: sizes always, sha256 with --verify
    plain = CliRunner().invoke(seg_main, ["inspect", str(dataset), "--json"])
    if how == "truncated":
        assert plain.exit_code == 1 and rel in plain.output
    else:
        assert plain.exit_code == 0, plain.output  # same size: only the checksum can tell
    verified = CliRunner().invoke(seg_main, ["inspect", str(dataset), "--verify", "--json"])
    assert verified.exit_code == 1
    problems = json.loads(verified.stdout)["problems"]
    assert len(problems) == 1 and rel in problems[0] and scenes[0] in problems[0]
    # the read API: the file and the scene are named, with and without --verify
    # (a flip that still decodes to finite values is only caught by the checksum)
    for verify in (False, True):
        shard_read._VERIFIED.clear()
        try:
            shards.read_scene(dataset, "train", scenes[0], verify=verify)
        except shards.ShardError as exc:
            assert str(dataset / rel) in str(exc) and scenes[0] in str(exc), str(exc)
        else:
            assert how == "flipped" and not verify
    # training and the benchmark, through their CLIs, with --verify
    for cli, argv in ((ov_main, ["train", "--data", str(dataset), "--out", str(tmp_path / "run"), "--epochs", "1",
                                 "--model-preset", "slim", "--verify", "--no-progress"]),
                      (ov_main, ["bench", "--data", str(dataset), "--predictor", "majority", "--verify",
                                 "--out", str(tmp_path / "b.json"), "--no-progress"])):
        shard_read._VERIFIED.clear()
        result = CliRunner().invoke(cli, argv)
        assert result.exit_code == 1 and "Traceback" not in result.output, result.output
        assert str(dataset / rel) in result.output and scenes[0] in result.output, result.output
