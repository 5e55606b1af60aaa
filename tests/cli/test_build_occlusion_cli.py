"""``seggaussian build --occlusion-tolerance`` / ``--keep-occluded`` reach ``TransferConfig.occlusion_tolerance``."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from cli.seggaussian_cli import main as seg_main
from seggaussian.pipeline import dataset as build_dataset_module
from seggaussian.labels.config import TransferConfig


def _config_of(args, tmp_path, monkeypatch):
    seen = []

    def capture(config):
        seen.append(config)
        raise ValueError("captured")  # stop before any work; the CLI reports it as one line

    monkeypatch.setattr(build_dataset_module, "build_dataset", capture)
    result = CliRunner().invoke(seg_main, ["build", "--root", str(tmp_path), "--out", str(tmp_path / "out"), *args])
    assert result.exit_code == 1 and "captured" in result.output, result.output
    return seen[0]


@pytest.mark.parametrize("args, tolerance", [([], TransferConfig().occlusion_tolerance),
                                             (["--occlusion-tolerance", "0.02"], 0.02),
                                             (["--keep-occluded"], None)])
def test_options_set_the_tolerance(args, tolerance, tmp_path, monkeypatch):
    assert _config_of(args, tmp_path, monkeypatch).transfer.occlusion_tolerance == tolerance


def test_both_options_are_refused(tmp_path):
    result = CliRunner().invoke(seg_main, ["build", "--root", str(tmp_path), "--out", str(tmp_path / "out"),
                                           "--keep-occluded", "--occlusion-tolerance", "0.02"])
    assert result.exit_code == 2 and "exclude each other" in result.output
    result = CliRunner().invoke(seg_main, ["build", "--root", str(tmp_path), "--out", str(tmp_path / "out"),
                                           "--occlusion-tolerance", "-1"])
    assert result.exit_code == 2
