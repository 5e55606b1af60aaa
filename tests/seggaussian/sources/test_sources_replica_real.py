"""The three real Replica info_semantic.json files parse and their classes map as specified."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from seggaussian.core.constants import IGNORE_LABEL, read_class_names
from seggaussian.sources.replica import ReplicaInfo
from shared_data import REALDATA

REAL = REALDATA / "replica_info_semantic"

# Classes used by each room's objects (id_to_label), split by whether they map onto top-100.
EXPECTED = {
    "room0": (
        ["basket", "blanket", "blinds", "book", "cabinet", "ceiling", "chair", "cushion", "door", "floor", "indoor-plant",
         "picture", "pot", "sofa", "switch", "table", "vent", "wall", "wall-plug", "window"],
        ["candle", "lamp", "pillar", "plant-stand", "plate", "rug", "stool", "vase"],
    ),
    "room1": (
        ["basket", "bed", "blanket", "blinds", "book", "cabinet", "ceiling", "comforter", "door", "floor", "indoor-plant",
         "picture", "pillow", "switch", "vent", "wall", "wall-plug", "window"],
        ["lamp", "nightstand", "panel", "plate", "rug", "vase"],
    ),
    "office4": (
        ["bin", "ceiling", "chair", "clock", "door", "floor", "table", "tv-screen", "vent", "wall", "wall-plug", "window"],
        ["bench", "camera", "lamp", "panel"],
    ),
}
# A few mappings spelled out (synonyms included).
SPOT_CHECKS = {"sofa": "sofa", "bin": "trash can", "tv-screen": "tv", "indoor-plant": "plant", "comforter": "blanket",
               "wall-plug": "socket", "switch": "light switch", "vent": "air vent", "wall": "wall"}


def _info(room: str) -> ReplicaInfo:
    path = REAL / f"info_semantic_{room}.json"
    if not path.is_file():
        pytest.skip(f"real Replica metadata not available at {path}")
    return ReplicaInfo(path)


@pytest.mark.parametrize("room", sorted(EXPECTED))
def test_real_info_parses_and_maps(room):
    info = _info(room)
    assert len(info.class_names) == 101
    mapped, ignored = info.mapped_classes()
    assert len(mapped) + len(ignored) == 101
    used = sorted({info.class_names[c] for c in info.id_to_label.tolist() if c >= 0})
    assert [u for u in used if u in mapped] == EXPECTED[room][0]
    assert [u for u in used if u in ignored] == EXPECTED[room][1]
    names = read_class_names()
    by_name = {n: c for c, n in info.class_names.items()}
    table = info.class_to_top100()
    for replica_name, top in SPOT_CHECKS.items():
        assert table[by_name[replica_name]] == names.index(top), replica_name
    assert table[by_name["base-cabinet"]] == IGNORE_LABEL


@pytest.mark.parametrize("room", sorted(EXPECTED))
def test_real_object_labels_void_and_ranges(room, tmp_path):
    info = _info(room)
    ids = np.arange(len(info.id_to_label))
    semantic, instance = info.object_labels(ids, tmp_path / "mesh_semantic.ply")
    void = info.id_to_label < 0
    assert void.any()  # the real files use -1 and -2 for void ids
    assert (semantic[void] == IGNORE_LABEL).all() and (instance[void] == IGNORE_LABEL).all()
    assert (instance[~void] == ids[~void]).all()
    with pytest.raises(ValueError, match="object_id"):
        info.object_labels(np.array([len(info.id_to_label)]), tmp_path / "mesh_semantic.ply")
