"""Training across renditions (``DataConfig.renditions`` / ``ovgaussian train --rendition-data``): each sample draws
its splat among the dataset and other datasets of the same rooms, and reads everything of that sample (Gaussians,
labels, view, blend weights) from the splat it drew."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ovgaussian.data.scene_source import InMemorySource, scan_scenes, with_renditions
from ovgaussian.data.training_data import TrainingData
from ovgaussian.run.config import DataConfig
from ovgaussian.text.vocabulary import map_labels, training_vocabulary

from test_train import make_scene


@pytest.fixture(scope="module")
def renditions():
    """The same two rooms as three splats: other Gaussians (and counts) per rendition, same scene ids."""
    return [[make_scene(seed, per_box=per_box) for seed in range(2)] for per_box in (40, 25, 55)]


def _data(records, config=DataConfig(blend_top_k=8, pixels_per_view=100)):
    voc = training_vocabulary(20)
    sources = [InMemorySource(r) for r in records]
    return TrainingData(sources[0], config, voc, renditions=sources[1:]), voc


def test_each_sample_reads_everything_from_the_splat_it_drew(renditions):
    data, voc = _data(renditions)
    counts = {len(r[0].gaussians): i for i, r in enumerate(renditions)}
    assert len(counts) == 3
    seen = set()
    for k in range(30):
        sample = data.sample("scene00", np.random.default_rng(k))
        drawn = counts[len(sample.labels)]
        seen.add(drawn)
        record = renditions[drawn][0]
        expected = map_labels(record.gaussians.extras["semantic"], voc)
        assert torch.equal(sample.labels, torch.from_numpy(expected))
        assert int(sample.pixel_ids.max()) < len(record.gaussians)  # blend weights on that splat's Gaussians
        assert sample.view_name in {v.name for v in record.views if v.role == "train"}
    assert seen == {0, 1, 2}  # every rendition is drawn


def test_the_dataset_itself_is_sampled_as_without_renditions(renditions):
    """A sample that drew rendition 0 is the sample a run without renditions draws from the rest of the stream."""
    alone, _ = _data(renditions[:1])
    several, _ = _data(renditions)
    matched = 0
    for k in range(30):
        rng = np.random.default_rng(k)
        if int(rng.integers(3)) != 0:
            continue
        matched += 1
        a = several.sample("scene01", np.random.default_rng(k))
        b = alone.sample("scene01", rng)  # the same stream after the rendition draw
        for field in ("means", "quats", "log_scales", "labels", "pixels", "pixel_ids", "pixel_weights"):
            assert torch.equal(getattr(a, field), getattr(b, field)), field
        assert a.view_name == b.view_name
    assert matched >= 5


def test_a_rendition_missing_a_trained_scene_is_refused_by_name(renditions):
    voc = training_vocabulary(20)
    scan = scan_scenes(InMemorySource(renditions[0]), voc)
    with pytest.raises(ValueError, match=r"^vertex: rendition has no trainable scene 'scene01'"):
        with_renditions(scan, [InMemorySource(renditions[1][:1])], ["vertex"], voc)
    both = with_renditions(scan, [InMemorySource(renditions[1])], ["vertex"], voc)
    assert both.usable == scan.usable
    assert both.fingerprint != scan.fingerprint  # --resume sees the renditions' data
    other = with_renditions(scan, [InMemorySource(renditions[2])], ["vertex"], voc)
    assert other.fingerprint != both.fingerprint
    assert with_renditions(scan, [], [], voc) == scan


def test_renditions_survive_the_saved_config(tmp_path):
    """What ``--resume`` reads back: the renditions as paths, not as one path made of a list."""
    from pathlib import Path

    from ovgaussian.run.config import TrainConfig, config_from_dict, config_to_dict

    config = TrainConfig(out=tmp_path, data=DataConfig(dataset=Path("a"), renditions=(Path("b"), Path("c d"))))
    assert config_from_dict(TrainConfig, config_to_dict(config)) == config
