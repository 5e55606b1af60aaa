"""One vocabulary type and one vocabulary rule, shared by the benchmark and the training data."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import numpy as np
import pytest

from ovgaussian.text import vocabulary as V
from seggaussian.core.classes import benchmark_vocabulary as class_ids_for
from seggaussian.core.constants import IGNORE_LABEL, UNSEEN_CLASSES, read_class_names


def test_one_type_everywhere():
    """The vocabulary type and rules are defined, and bound, in ovgaussian.text.vocabulary only: no other module of the
    package defines them or re-exports them under a second import path."""
    names = {"Vocabulary", "make_vocabulary", "benchmark_vocabulary", "training_vocabulary", "map_labels",
             "to_vocabulary_labels"}
    root = Path(V.__file__).parents[1]  # the ovgaussian package (the vocabulary lives in ovgaussian/text/)
    for path in sorted(root.rglob("*.py")):
        if path == Path(V.__file__):
            continue
        tree = ast.parse(path.read_text())
        defined = {n.name for n in ast.walk(tree) if isinstance(n, (ast.ClassDef, ast.FunctionDef))} & names
        assert not defined, (path, defined)
        module = importlib.import_module(".".join(path.relative_to(root.parent).with_suffix("").parts))
        exported = set(getattr(module, "__all__", ())) & names
        assert not exported, (path, exported)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "ovgaussian.text.vocabulary":
                unused = {a.name for a in node.names} - {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
                assert not unused, f"{path.name} imports {sorted(unused)} without using them (a re-export)"


@pytest.mark.parametrize("k", [20, 50, 100])
def test_training_vocabulary_is_the_benchmark_one_minus_the_unseen(k):
    names = read_class_names()
    full, seen = V.benchmark_vocabulary(k), V.training_vocabulary(k)
    assert full.class_ids.tolist() == class_ids_for(k) and full.num_classes == seen.num_classes == k
    assert sorted(full.names[i] for i in full.unseen) == sorted(UNSEEN_CLASSES)
    assert seen.class_ids.tolist() == [i for i in class_ids_for(k) if names[i] not in UNSEEN_CLASSES]
    assert seen.unseen.size == 0 and len(seen.class_ids) == k - len(UNSEEN_CLASSES)


def test_strict_and_lenient_label_maps_agree_on_valid_labels():
    voc = V.training_vocabulary(20)
    rng = np.random.default_rng(0)
    labels = np.concatenate([rng.integers(0, voc.lut.size, 500), [IGNORE_LABEL]])
    np.testing.assert_array_equal(V.map_labels(labels, voc), V.to_vocabulary_labels(labels, voc))
    odd = np.array([-5, voc.lut.size, 70000])
    assert (V.map_labels(odd, voc) == IGNORE_LABEL).all()
    with pytest.raises(ValueError, match="gt: 3 labels are neither"):
        V.to_vocabulary_labels(odd, voc, "gt")
