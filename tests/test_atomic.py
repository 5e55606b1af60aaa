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
