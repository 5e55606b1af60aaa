import json
import math

import pytest

from seggaussian.util.atomic import atomic_path, write_bytes_atomic, write_json_atomic


def test_failed_write_leaves_old_file_and_no_temp(tmp_path):
    target = tmp_path / "a.bin"
    write_bytes_atomic(target, b"old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_json_nan_becomes_null_and_png_suffix_kept(tmp_path):
    write_json_atomic(tmp_path / "r.json", {"x": math.nan, "y": 1.5})
    assert json.loads((tmp_path / "r.json").read_text()) == {"x": None, "y": 1.5}
    with atomic_path(tmp_path / "img.png", suffix=".png") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path
        tmp.write_bytes(b"png")
    assert (tmp_path / "img.png").read_bytes() == b"png"


def test_json_nan_policy_error_refuses_before_writing(tmp_path):
    import torch

    from ovgaussian.run.checkpoint import CHECKPOINTS_DIR, save_checkpoint
    from seggaussian.util.jsonsafe import NAN_AS_NULL, NAN_IS_ERROR

    target = tmp_path / "state.json"
    with pytest.raises(ValueError, match=r"payload\['groups'\]\[1\] holds nan"):
        write_json_atomic(target, {"groups": [1.0, math.nan]}, nan=NAN_IS_ERROR)
    with pytest.raises(ValueError, match="NaN policy"):
        write_json_atomic(target, {}, nan="drop")
    assert list(tmp_path.iterdir()) == []  # nothing written, no temp file left
    # the run's JSON files refuse NaN/Inf: a checkpoint whose state holds inf is not written at all
    net = torch.nn.Linear(2, 2)
    optimizer = torch.optim.SGD(net.parameters(), lr=0.1)
    run = tmp_path / "run"
    with pytest.raises(ValueError, match="holds inf"):
        save_checkpoint(run, 1, net, optimizer, {"lr": math.inf})
    assert not [p for p in run.rglob("*") if p.is_file()]
    save_checkpoint(run, 1, net, optimizer, {"lr": 0.5})
    assert json.loads((run / CHECKPOINTS_DIR / "epoch-0001" / "state.json").read_text())["lr"] == 0.5
    # the dataset's JSON files (manifest, splits): NaN as null, keys sorted
    write_json_atomic(tmp_path / "m.json", {"b": math.nan, "a": 1}, nan=NAN_AS_NULL, sort_keys=True,
                      only_if_changed=True)
    assert (tmp_path / "m.json").read_text() == '{\n  "a": 1,\n  "b": null\n}\n'
