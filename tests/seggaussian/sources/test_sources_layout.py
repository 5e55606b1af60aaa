"""The raw-tree layout dispatch (``seggaussian.sources.layout``) on hand-made folder trees."""

from __future__ import annotations

import pytest

from seggaussian.sources import replica, scannetpp
from seggaussian.sources.layout import detect_layout, find_scene_layout, layout_roots, reader, source_of_tree


@pytest.fixture()
def synthetic_root(tmp_path):
    (tmp_path / "scannetpp" / "data" / "s0").mkdir(parents=True)
    (tmp_path / "replica" / "room0").mkdir(parents=True)
    return tmp_path


def test_detect_layout_and_reader(tmp_path, synthetic_root):
    assert detect_layout(synthetic_root / "scannetpp") == "scannetpp"
    assert detect_layout(synthetic_root / "replica") == "replica"
    assert reader("scannetpp") is scannetpp and reader("replica") is replica
    with pytest.raises(ValueError, match="unknown source domain 'ply'"):
        reader("ply")
    with pytest.raises(FileNotFoundError, match="raw tree does not exist"):
        detect_layout(tmp_path / "missing")


def test_layout_roots(synthetic_root):
    root = synthetic_root
    assert layout_roots("synthetic", root) == [("scannetpp", root / "scannetpp"), ("replica", root / "replica")]
    assert layout_roots("synthetic", root / "replica") == [("replica", root / "replica")]
    assert layout_roots("scannetpp", root / "x") == [("scannetpp", root / "x")]  # an explicit layout is trusted
    assert layout_roots("ply", root / "scannetpp") == [("scannetpp", root / "scannetpp")]
    with pytest.raises(ValueError, match="--source must be one of"):
        layout_roots("nope", root)


def test_source_of_tree_and_find_scene(synthetic_root):
    root = synthetic_root
    assert source_of_tree(root) == "synthetic"
    assert source_of_tree(root / "scannetpp") == "scannetpp" and source_of_tree(root / "replica") == "replica"
    assert find_scene_layout(root, "s0") == ("scannetpp", root / "scannetpp")
    assert find_scene_layout(root, "room0") == ("replica", root / "replica")
    assert find_scene_layout(root / "scannetpp", "s0") == ("scannetpp", root / "scannetpp")
    with pytest.raises(FileNotFoundError, match="no scene 'nope'"):
        find_scene_layout(root, "nope")
