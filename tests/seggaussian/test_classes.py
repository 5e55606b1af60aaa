"""Class lists, benchmark vocabularies and the Replica mapping (seggaussian.core.classes, data_specs/)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from seggaussian.core.classes import (
    benchmark_vocabulary,
    benchmark_vocabulary_names,
    class_id,
    class_names,
    is_replica_class,
    replica_class_id_to_top100,
    replica_class_names,
    replica_class_to_top100,
    replica_common_class_ids,
    unseen_class_ids,
)
from seggaussian.core.constants import DATA_SPECS_DIR, UNSEEN_CLASSES
from shared_data import SHARED

REPLICA_CLASSES = SHARED / "reference" / "replica_classes_1_to_101.json"
REPLICA_INFO = SHARED / "realdata" / "replica_info_semantic"


def test_class_list():
    names = class_names()
    assert len(names) == 100 and names[0] == "wall" and names[3] == "table"
    assert class_id("trash can") == names.index("trash can")
    with pytest.raises(KeyError, match="banana"):
        class_id("banana")
    assert [names[i] for i in unseen_class_ids()] == sorted(UNSEEN_CLASSES, key=names.index)


@pytest.mark.parametrize("k", [20, 50, 100])
def test_benchmark_vocabulary_follows_the_rule(k):
    names = class_names()
    others = [n for n in names if n not in UNSEEN_CLASSES][: k - 4]  # the rule, re-derived here
    expected = sorted(names.index(n) for n in list(UNSEEN_CLASSES) + others)
    ids = benchmark_vocabulary(k)
    assert ids == expected and len(ids) == k
    assert set(unseen_class_ids()) <= set(ids)
    assert benchmark_vocabulary_names(k) == [names[i] for i in ids]


def test_benchmark_vocabulary_20_content():
    names = [class_names()[i] for i in benchmark_vocabulary(20)]
    # bookshelf (12), sofa (23), bed (25) lie beyond the first 20 lines: the vocabulary reaches further
    assert names[:4] == ["wall", "ceiling", "floor", "table"]
    assert {"curtain", "bookshelf", "sofa", "bed"} <= set(names)
    assert "window" in names and "windowsill" not in names
    assert names[-1] == "bed"
    with pytest.raises(ValueError, match="30"):
        benchmark_vocabulary(30)


def test_broken_vocabulary_file_is_reported(tmp_path):
    (tmp_path / "top100.txt").write_text((DATA_SPECS_DIR / "top100.txt").read_text())
    doc = json.loads((DATA_SPECS_DIR / "vocabularies.json").read_text())
    doc["vocabularies"]["20"] = doc["vocabularies"]["20"][:-1] + ["wall"]  # duplicate
    (tmp_path / "vocabularies.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="vocabulary 20"):
        benchmark_vocabulary(20, data_dir=tmp_path)
    (tmp_path / "vocabularies.json").write_text("{")
    with pytest.raises(ValueError, match="vocabularies.json"):
        benchmark_vocabulary(20, data_dir=tmp_path)


@pytest.mark.skipif(not REPLICA_CLASSES.exists(), reason=f"{REPLICA_CLASSES} not found")
def test_replica_names_are_the_reference_list():
    assert list(replica_class_names()) == json.loads(REPLICA_CLASSES.read_text())


def test_replica_mapping_rules():
    names = class_names()
    mapping = json.loads((DATA_SPECS_DIR / "replica_to_top100.json").read_text())["mapping"]
    for replica, target in mapping.items():
        exact = replica.replace("-", " ")
        if exact in names:  # every exact match is taken, as an exact rule
            assert target == {"top100": exact, "rule": "exact"}, replica
        elif target is not None:
            assert target["rule"] == "synonym" and target["top100"] in names, replica
    synonyms = {"bin": "trash can", "indoor-plant": "plant", "tv-screen": "tv", "desk": "table",
                "comforter": "blanket", "wall-plug": "socket", "vent": "air vent", "tissue-paper": "tissue box"}
    for replica, top in synonyms.items():
        assert replica_class_to_top100(replica) == names.index(top), replica
    assert replica_class_to_top100("paper-towel") == names.index("paper towel")
    assert replica_class_to_top100("paper towel") == names.index("paper towel")  # spaces accepted
    assert replica_class_to_top100("wall") == 0
    assert replica_class_to_top100("base-cabinet") is None and replica_class_to_top100("rug") is None
    assert replica_class_to_top100("hovercraft") is None
    assert not is_replica_class("hovercraft") and is_replica_class("tv screen") and is_replica_class("rug")


def test_replica_ids_and_common_classes():
    names = class_names()
    replica = replica_class_names()
    assert replica_class_id_to_top100(1) == names.index("backpack")  # id 1 = backpack
    assert replica_class_id_to_top100(replica.index("tv-screen") + 1) == names.index("tv")
    assert replica_class_id_to_top100(-1) is None and replica_class_id_to_top100(0) is None
    with pytest.raises(KeyError):
        replica_class_id_to_top100(102)
    common = replica_common_class_ids()
    assert len(common) == 52 and common == sorted(set(common))
    assert names.index("table") in common and names.index("bookshelf") not in common


@pytest.mark.skipif(not REPLICA_INFO.exists(), reason=f"{REPLICA_INFO} not found")
@pytest.mark.parametrize("room", ["room0", "room1", "office4"])
def test_real_replica_info_semantic(room):
    info = json.loads((REPLICA_INFO / f"info_semantic_{room}.json").read_text())
    by_id = {c["id"]: c["name"] for c in info["classes"]}
    for class_id_, name in by_id.items():
        assert replica_class_names()[class_id_ - 1] == name
        assert replica_class_id_to_top100(class_id_) == replica_class_to_top100(name)
    mapped = {replica_class_to_top100(o["class_name"]) for o in info["objects"] if o["class_name"] in by_id.values()}
    assert {0, 2} <= mapped  # wall and floor appear in every room
