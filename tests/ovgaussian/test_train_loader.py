"""Loader workers of the trainer (``ovgaussian.train.loader``, ``TrainConfig.loader_workers``): the same samples and
weights for every worker count and across a resume; a worker's error or hang ends the run with one line naming the
scene, and no worker outlives the run."""

from __future__ import annotations

import json
import multiprocessing
import time

import pytest
import torch

from ovgaussian.data.scene_source import InMemorySource
from ovgaussian.data.training_data import TrainingData
from ovgaussian.run.config import DataConfig
from ovgaussian.text.vocabulary import training_vocabulary
from ovgaussian.train.loader import InlineLoader, LoaderError, StepTask, WorkerLoader
from ovgaussian.train.schedule import sample_seed
from test_train import _run_digest, _write_shards, make_scene, text_stub, tiny_config, tiny_model_config


@pytest.fixture(scope="module")
def scenes():
    return [make_scene(s) for s in range(4)]


def _no_children_left() -> bool:
    """No process started by this one is still running (a second for the exits to be reaped)."""
    deadline = time.monotonic() + 1.0
    while multiprocessing.active_children() and time.monotonic() < deadline:
        time.sleep(0.05)
    return not multiprocessing.active_children()


class BrokenAfterScan(InMemorySource):
    """Scenes in memory, but ``broken`` fails to load on every read after the scan's (as a shard file damaged
    after the split was scanned). The read count travels with the object to a worker."""

    def __init__(self, records, broken: str):
        super().__init__(records)
        self.broken, self.reads = broken, {}

    def read_scene(self, scene_id: str):
        self.reads[scene_id] = self.reads.get(scene_id, 0) + 1
        if scene_id == self.broken and self.reads[scene_id] > 1:
            raise OSError(f"{scene_id}/gaussians.parquet: truncated file")
        return super().read_scene(scene_id)


def hanging_blend(*args, **kwargs):
    """A blend-weight function that does not return within the test's timeout (a hung worker); were the worker waited
    on, the run would fail after 300 s with another message."""
    time.sleep(300)


def _tasks(scene_ids, steps: int):
    return [StepTask(0, step, tuple((sid, tuple(sample_seed(0, 0, step, sid))) for sid in scene_ids))
            for step in range(steps)]


def test_worker_samples_equal_the_in_process_reference(scenes):
    """Two workers and the in-process loader: the same steps in order, every tensor of every sample equal."""
    data = TrainingData(InMemorySource(scenes), DataConfig(blend_top_k=8, pixels_per_view=200, splat_augment=True),
                        training_vocabulary(20))
    tasks = _tasks(["scene01", "scene03"], 3)
    reference = list(InlineLoader(data, tasks, 0))
    with WorkerLoader(data, tasks, 0, workers=2, threads=1, timeout_s=120) as loader:
        loaded = list(loader)
        assert 0 < loader.worker_peak_bytes()
    assert _no_children_left()
    assert [s.task for s in loaded] == [s.task for s in reference] == tasks
    for ours, theirs in zip(loaded, reference):
        for a, b in zip(ours.samples, theirs.samples):
            assert (a.scene_id, a.view_name, a.image_size) == (b.scene_id, b.view_name, b.image_size)
            for name in a._fields:
                if isinstance(getattr(a, name), torch.Tensor):
                    assert torch.equal(getattr(a, name), getattr(b, name)), name
    # different steps draw differently (the comparison above is not between constant samples)
    assert not torch.equal(reference[0].samples[0].pixels, reference[1].samples[0].pixels)


@pytest.mark.slow
def test_weights_are_bitwise_equal_for_0_1_and_2_workers_and_across_a_resume(scenes, tmp_path):
    """Checkpoint tensors (weights, momentum, buffers) and metrics hash equal for 0, 1 and 2 loader workers, and for
    a run stopped after one epoch with 2 workers and resumed with 1."""
    from ovgaussian.train.loop import train

    common = dict(source=InMemorySource(scenes), model_config=tiny_model_config(12), text_embeddings=text_stub())
    digests = {}
    for workers in (0, 1, 2):
        out = tmp_path / f"w{workers}"
        result = train(tiny_config(out, 2, loader_workers=workers), **common)
        assert result.steps == 4 and result.phases["steps"] == 4
        digests[workers] = _run_digest(result, out)
    part = tmp_path / "part"
    train(tiny_config(part, 2, loader_workers=2, stop_after_epochs=1), **common)
    resumed = train(tiny_config(part, 2, loader_workers=1, resume=True), **common)
    assert resumed.steps == 4 and resumed.phases["steps"] == 2
    digests["resumed"] = _run_digest(resumed, part)
    assert len(set(digests.values())) == 1, digests
    assert _no_children_left()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (no GPU on this machine)")
def test_cuda_training_with_a_loader_worker_follows_the_one_without(scenes, tmp_path):
    """On the GPU (pinned samples, copies without blocking) one loader worker gives the per-step losses of none, within
    the GPU's float tolerance (its scatter-adds need not be bitwise repeatable), and the copies are timed."""
    from ovgaussian.run.folder import read_metrics
    from ovgaussian.train.loop import train

    runs = {}
    for workers in (0, 1):
        out = tmp_path / f"w{workers}"
        result = train(tiny_config(out, 2, device="cuda", loader_workers=workers), source=InMemorySource(scenes),
                       model_config=tiny_model_config(12), text_embeddings=text_stub())
        assert result.phases["loader_workers"] == workers and result.phases["total_s"]["transfer"] > 0
        runs[workers] = read_metrics(out)
    assert len(runs[0]) == len(runs[1]) == 4
    for a, b in zip(runs[0], runs[1]):
        assert a["scenes"] == b["scenes"]
        for key in ("loss", "text_3d", "text_2d"):
            assert b[key] == pytest.approx(a[key], rel=1e-4, abs=1e-5), (key, a, b)
    assert _no_children_left()


def test_phase_times_add_up_to_the_step(scenes, tmp_path):
    from ovgaussian.train.loop import train

    result = train(tiny_config(tmp_path, 1), source=InMemorySource(scenes), model_config=tiny_model_config(12),
                   text_embeddings=text_stub())
    total = result.phases["total_s"]
    assert result.phases["loader_workers"] == 0  # the default: samples drawn in the training process
    assert result.phases["steps"] == 2 and all(v > 0 for k, v in total.items() if k != "transfer")
    assert total["wait"] == total["sample"]  # without workers the step waits for all of its sampling
    assert total["wait"] + total["transfer"] + total["compute"] <= total["step"]
    assert result.phases["device_busy"] == pytest.approx(total["compute"] / total["step"])
    assert 0 < result.phases["device_busy"] < 1


@pytest.mark.parametrize("workers", [0, 1])
def test_a_scene_that_fails_to_load_ends_the_run_with_one_line_naming_it(scenes, tmp_path, workers):
    from ovgaussian.train.loop import train

    with pytest.raises(LoaderError) as error:
        train(tiny_config(tmp_path, 2, loader_workers=workers), source=BrokenAfterScan(scenes, "scene02"),
              model_config=tiny_model_config(12), text_embeddings=text_stub())
    message = str(error.value)
    assert message.startswith("scene scene02 (epoch ") and "OSError: scene02/gaussians.parquet: truncated" in message
    assert "\n" not in message
    assert _no_children_left()


def test_a_hung_worker_is_reported_within_the_timeout(scenes, tmp_path):
    from ovgaussian.train.loop import train

    with pytest.raises(LoaderError, match=r"^scene scene0\d \(epoch 0 step 0\): no sample from the loader workers "
                                          r"after 4 s \(a worker hung\)$"):
        train(tiny_config(tmp_path, 1, loader_workers=1, loader_timeout_s=4.0), source=InMemorySource(scenes),
              model_config=tiny_model_config(12), text_embeddings=text_stub(), pixel_blend_function=hanging_blend)
    assert _no_children_left()  # the sleeping worker was terminated, not waited for


def test_cli_reports_a_worker_error_in_one_line_without_a_traceback(scenes, tmp_path):
    """A scene whose label maps do not fit its camera passes the scan and fails when a worker samples it: the
    command exits 1 with one line naming the scene."""
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main

    bad = scenes[1]
    bad = bad._replace(views=[v._replace(semantic=v.semantic[:-1]) for v in bad.views])
    dataset = tmp_path / "dataset"
    _write_shards(dataset, [scenes[0], bad, scenes[2], scenes[3]])
    result = CliRunner().invoke(main, ["train", "--data", str(dataset), "--out", str(tmp_path / "run"),
                                       "--epochs", "1", "--model-preset", "slim", "--pixels-per-view", "64",
                                       "--batch-scenes", "4", "--loader-workers", "1", "--no-progress"])
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: scene scene01 (epoch 0 step 0): ValueError: scene scene01 "
                                                   "view frame00"), result.output
    assert "Traceback" not in result.output
    assert _no_children_left()


def test_the_json_summary_reports_the_device_busy_share(scenes, tmp_path):
    from click.testing import CliRunner

    from cli.ovgaussian_cli import main

    dataset = tmp_path / "dataset"
    _write_shards(dataset, scenes)
    result = CliRunner().invoke(main, ["train", "--data", str(dataset), "--out", str(tmp_path / "run"),
                                       "--epochs", "1", "--model-preset", "slim", "--pixels-per-view", "64",
                                       "--batch-scenes", "2", "--no-progress", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output[result.output.index("{"):])
    assert payload["phases"]["steps"] == 2 and 0 < payload["phases"]["device_busy"] < 1
    assert "device busy" in payload["summary"] and "0 loader workers" in payload["summary"]


def test_training_data_that_cannot_reach_a_worker_is_refused_in_one_line(scenes):
    """A blend function defined in a function cannot be pickled for a spawned worker: one line saying so, no worker
    left behind."""
    data = TrainingData(InMemorySource(scenes), DataConfig(blend_top_k=8, pixels_per_view=50), training_vocabulary(20),
                        pixel_blend_function=lambda *args, **kwargs: None)
    with pytest.raises(LoaderError, match=r"^loader workers: the training data cannot be sent to a worker process "
                                          r"\(.*\); use 0 loader workers$"):
        WorkerLoader(data, _tasks(["scene00"], 1), 0, workers=1, threads=1, timeout_s=60)
    assert _no_children_left()


def test_negative_loader_workers_are_refused():
    from ovgaussian.run.config import TrainConfig

    with pytest.raises(ValueError, match="loader_workers"):
        TrainConfig(loader_workers=-1)
    with pytest.raises(ValueError, match="loader_timeout_s"):
        TrainConfig(loader_timeout_s=0)
