"""Checkpoint retention (``TrainConfig.keep_checkpoints``): the last N epochs plus the best, atomic removal, resume."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from ovgaussian.run.checkpoint import (
    BEST_NAME, CHECKPOINTS_DIR, LATEST_NAME, checkpoint_folders, latest_checkpoint, retain_checkpoints,
)
from ovgaussian.data.scene_source import InMemorySource
from ovgaussian.run.config import TrainConfig
from seggaussian.util import atomic
from seggaussian.util.atomic import is_temp_name, remove_dir_atomic, sweep_temps
from test_train import make_scene, text_stub, tiny_config, tiny_model_config


def fake_run(root: Path, losses: dict[int, float], latest: int | None = None) -> Path:
    """A run folder whose checkpoints/epoch-NNNN hold only state.json with the given epoch losses."""
    for epoch, loss in losses.items():
        folder = root / CHECKPOINTS_DIR / f"epoch-{epoch:04d}"
        folder.mkdir(parents=True)
        (folder / "state.json").write_text(json.dumps({"epoch": epoch, "metrics": {"loss": loss}}))
        (folder / "model.safetensors").write_bytes(b"x" * 64)
    latest = max(losses) if latest is None else latest
    (root / CHECKPOINTS_DIR / LATEST_NAME).write_text(
        json.dumps({"epoch": latest, "path": f"{CHECKPOINTS_DIR}/epoch-{latest:04d}"}))
    return root


def names(root: Path) -> list[str]:
    return sorted(p.name for p in (root / CHECKPOINTS_DIR).iterdir())


def test_keeps_the_last_n_and_the_best_and_points_best_json_at_it(tmp_path):
    run = fake_run(tmp_path, {1: 3.0, 2: 1.5, 3: 2.0, 4: 2.5, 5: 2.2})
    removed = retain_checkpoints(run, 2)
    assert sorted(p.name for p in removed) == ["epoch-0001", "epoch-0003"]
    assert names(run) == ["best.json", "epoch-0002", "epoch-0004", "epoch-0005", "latest.json"]
    best = json.loads((run / CHECKPOINTS_DIR / BEST_NAME).read_text())
    assert best == {"epoch": 2, "path": "checkpoints/epoch-0002", "loss": 1.5}
    assert latest_checkpoint(run).name == "epoch-0005"
    # the best among the last N: only N folders remain
    assert [p.name for p in retain_checkpoints(fake_run(tmp_path / "b", {1: 3.0, 2: 2.0, 3: 1.0}), 1)] == [
        "epoch-0001", "epoch-0002"]
    # idempotent: a second call removes nothing and leaves best.json as it is
    stamp = (run / CHECKPOINTS_DIR / BEST_NAME).stat().st_mtime_ns
    assert retain_checkpoints(run, 2) == []
    assert (run / CHECKPOINTS_DIR / BEST_NAME).stat().st_mtime_ns == stamp


def test_ties_missing_losses_zero_and_foreign_folders(tmp_path):
    run = fake_run(tmp_path / "tie", {1: 2.0, 2: 1.0, 3: 1.0, 4: 5.0, 5: 6.0})
    retain_checkpoints(run, 1)
    assert names(run) == ["best.json", "epoch-0002", "epoch-0005", "latest.json"]  # ties: the earliest
    # an epoch without a loss never counts as best; keep 0 removes nothing but still writes best.json
    run = fake_run(tmp_path / "keep", {1: 2.0, 2: 1.0, 3: 4.0})
    (run / CHECKPOINTS_DIR / "epoch-0002" / "state.json").write_text(json.dumps({"epoch": 2}))
    assert retain_checkpoints(run, 0) == []
    assert json.loads((run / CHECKPOINTS_DIR / BEST_NAME).read_text())["epoch"] == 1
    assert len(checkpoint_folders(run)) == 3
    # folders that are not complete epoch checkpoints are left alone
    run = fake_run(tmp_path / "foreign", {1: 1.0, 2: 2.0, 3: 3.0})
    (run / CHECKPOINTS_DIR / "epoch-0000").mkdir()  # no state.json: incomplete, not ours to judge
    (run / CHECKPOINTS_DIR / "notes").mkdir()
    retain_checkpoints(run, 1)
    assert names(run) == ["best.json", "epoch-0000", "epoch-0001", "epoch-0003", "latest.json", "notes"]
    with pytest.raises(ValueError, match="keep_last"):
        retain_checkpoints(run, -1)
    with pytest.raises(ValueError, match="keep_checkpoints"):
        TrainConfig(keep_checkpoints=-1)


def test_the_checkpoint_latest_json_points_at_is_never_removed(tmp_path):
    # a kill between writing epoch-0004 and moving latest.json leaves latest at epoch 3
    run = fake_run(tmp_path, {1: 1.0, 2: 2.0, 3: 3.0, 4: 4.0}, latest=3)
    retain_checkpoints(run, 1)
    assert names(run) == ["best.json", "epoch-0001", "epoch-0003", "epoch-0004", "latest.json"]


def test_removal_is_one_rename_and_a_killed_removal_leaves_a_swept_temp(tmp_path, monkeypatch):
    folder = tmp_path / "epoch-0001"
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "a.bin").write_bytes(b"1" * 1000)
    assert remove_dir_atomic(folder) and not folder.exists() and os.listdir(tmp_path) == []
    assert remove_dir_atomic(folder) is False  # already gone
    # interrupted deletion: the folder has left its name at once; what remains is a temporary
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "a.bin").write_bytes(b"1" * 1000)

    def interrupted(path, ignore_errors=False):
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic.shutil, "rmtree", interrupted)
    with pytest.raises(KeyboardInterrupt):
        remove_dir_atomic(folder)
    monkeypatch.undo()
    left = os.listdir(tmp_path)
    assert not folder.exists() and len(left) == 1 and is_temp_name(left[0])
    # the next run sweeps it once its writer is gone (here: renamed to a dead process's temp name)
    dead = _dead_pid()
    os.rename(tmp_path / left[0], tmp_path / f".epoch-0001.tmp-{dead}-00ff00ff")
    assert sweep_temps(tmp_path) == 1 and os.listdir(tmp_path) == []


def _dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


@pytest.fixture(scope="module")
def scenes():
    return [make_scene(s, per_box=30, views=2) for s in range(2)]  # batch of 2: one step per epoch


def test_training_keeps_n_plus_best_and_resume_gives_the_same_run(scenes, tmp_path):
    from safetensors.torch import load_file

    from ovgaussian.run.folder import read_metrics
    from ovgaussian.train.loop import train

    common = dict(source=InMemorySource(scenes), model_config=tiny_model_config(12), text_embeddings=text_stub())
    kept = train(tiny_config(tmp_path / "kept", 4, keep_checkpoints=1), **common)
    losses = {e["epoch"] + 1: e["loss"] for e in read_metrics(tmp_path / "kept", "epoch")}
    assert sorted(losses) == [1, 2, 3, 4]
    best = min(losses, key=lambda e: (losses[e], e))
    expected = sorted({4, best})
    assert sorted(checkpoint_folders(tmp_path / "kept")) == expected
    assert json.loads((tmp_path / "kept" / CHECKPOINTS_DIR / BEST_NAME).read_text())["epoch"] == best
    assert kept.checkpoint.name == "epoch-0004" and latest_checkpoint(tmp_path / "kept") == kept.checkpoint
    assert not [n for n in os.listdir(tmp_path / "kept" / CHECKPOINTS_DIR) if is_temp_name(n)]

    # interrupted after 2 epochs, resumed with retention: same weights, metrics and folders as the plain run
    part = tmp_path / "part"
    train(tiny_config(part, 4, keep_checkpoints=1, stop_after_epochs=2), **common)
    assert 1 <= len(checkpoint_folders(part)) <= 2
    resumed = train(tiny_config(part, 4, keep_checkpoints=1, resume=True), **common)
    a, b = load_file(str(kept.checkpoint / "model.safetensors")), load_file(str(resumed.checkpoint / "model.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert sorted(checkpoint_folders(part)) == expected
    assert read_metrics(part) == read_metrics(tmp_path / "kept")

    # a kill during the last removal left an extra complete folder: the next --resume removes it
    extra = part / CHECKPOINTS_DIR / f"epoch-{next(e for e in (1, 2, 3) if e not in expected):04d}"
    shutil.copytree(resumed.checkpoint, extra)
    (extra / "state.json").write_text(json.dumps({"epoch": 0, "metrics": {"loss": 1e9}}))
    train(tiny_config(part, 4, keep_checkpoints=1, resume=True), **common)
    assert sorted(checkpoint_folders(part)) == expected and not extra.exists()
