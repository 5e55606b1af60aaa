"""``--device``: a clear one-line refusal where CUDA is asked for and absent, on every command that takes it."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

from cli.ovgaussian_cli import main
from ovgaussian.run.devices import resolve_device


def test_cpu_resolves_and_unknown_names_are_refused():
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="expected one of cpu, cuda"):
        resolve_device("tpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_cuda_without_a_gpu_is_refused_in_one_line():
    with pytest.raises(ValueError, match="--device cuda: no usable CUDA device"):
        resolve_device("cuda")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("argv", [
    ["train", "--data", "{data}", "--out", "{tmp}/run", "--device", "cuda"],
    ["bench", "--data", "{data}", "--run", "{tmp}/run", "--device", "cuda"],
    ["predict", "{tmp}/scene.ply", "--run", "{tmp}/run", "--vocab", "chair", "--out", "{tmp}/o.ply", "--device", "cuda"],
])
def test_every_command_refuses_cuda_without_a_gpu_with_a_json_error(argv, tmp_path):
    # the check comes before any input is read: empty folders and a missing scene do not matter
    for folder in ("data", "run"):
        (tmp_path / folder).mkdir()
    (tmp_path / "scene.ply").write_bytes(b"")
    args = [a.format(data=tmp_path / "data", tmp=tmp_path) for a in argv] + ["--json"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 1, result.output
    payload = json.loads(result.output)
    assert "--device cuda: no usable CUDA device" in payload["error"]
