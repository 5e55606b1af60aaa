import json
import math

import pytest

from seggaussian.atomic import atomic_path, write_bytes_atomic, write_json_atomic


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
    from ovgaussian import checkpoint
    from seggaussian import shards
    from seggaussian.jsonsafe import NAN_IS_ERROR

    target = tmp_path / "state.json"
    with pytest.raises(ValueError, match=r"payload\['groups'\]\[1\] holds nan"):
        write_json_atomic(target, {"groups": [1.0, math.nan]}, nan=NAN_IS_ERROR)
    with pytest.raises(ValueError, match="holds inf"):
        checkpoint.write_json_atomic(target, {"lr": math.inf})
    with pytest.raises(ValueError, match="NaN policy"):
        write_json_atomic(target, {}, nan="drop")
    assert list(tmp_path.iterdir()) == []  # nothing written, no temp file left
    checkpoint.write_json_atomic(target, {"lr": 0.5})
    assert json.loads(target.read_text()) == {"lr": 0.5}
    shards.write_json_atomic(tmp_path / "m.json", {"b": math.nan, "a": 1})
    assert (tmp_path / "m.json").read_text() == '{\n  "a": 1,\n  "b": null\n}\n'
