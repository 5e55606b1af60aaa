"""Build cache keys cover the code: a stage's key hashes the source of every module its entry module imports.

The rebuild test edits one module in a copy of the package source (the hashed text; the running code is
unchanged) and checks that exactly that stage and those downstream of it run again, the others come from the cache.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from seggaussian.pipeline import cache as build_cache
from seggaussian.pipeline.dataset import build_dataset
from seggaussian.pipeline.config import BuildConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.pipeline.scene import GAUSSIANS_MODES, STAGE_MODULES
from seggaussian.util.module_closure import module_file

synthetic = pytest.importorskip("seggaussian.sources.synthetic.generate")


def _short(closure) -> set[str]:
    return {m.removeprefix("seggaussian.") for m in closure}


def test_closures_hold_what_each_stage_runs_and_nothing_else():
    views = _short(build_cache.module_closure(STAGE_MODULES["views"]))
    transfer = _short(build_cache.module_closure(STAGE_MODULES["transfer"]))
    oracle = _short(build_cache.module_closure(GAUSSIANS_MODES["oracle"].__name__))
    assert {"pipeline.stages.views", "render", "render.labelmaps", "render.blend", "shards", "shards.schema"} <= views
    assert {"pipeline.stages.transfer", "labels.transfer", "shards", "shards.schema"} <= transfer
    assert {"pipeline.stages.gaussians_oracle", "labels.oracle", "pipeline.stages.gaussians", "util.seeds"} <= oracle
    assert "labels.transfer" not in views and "labels.oracle" not in views
    assert not any(m.startswith("render") for m in transfer | oracle)
    # the fitting code is not the oracle mode's (its configuration is: BuildConfig holds a FitConfig)
    assert {m for m in oracle if m.startswith("fit.")} == {"fit.config"}
    # a lazy import inside a function is code the stage runs: replica's raycast renders views into the cache
    assert "sources.raycast" in _short(build_cache.module_closure("seggaussian.sources.replica"))
    for entry in ("seggaussian.pipeline.stages.views", "seggaussian.pipeline.stages.gaussians_fit"):
        assert all(module_file(m, build_cache.PACKAGE_DIR.parent) is not None for m in build_cache.module_closure(entry))
    with pytest.raises(ModuleNotFoundError, match="no module"):
        build_cache.module_closure("seggaussian.sources.replica_classes")


def test_relative_imports_and_submodules(tmp_path):
    pkg = tmp_path / "seggaussian"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import leaf\n")
    (pkg / "sub" / "leaf.py").write_text("def f():\n    from ..other import g\n")
    (pkg / "other.py").write_text("import os\nfrom seggaussian import sub\n")
    (pkg / "alone.py").write_text("x = 1\n")
    assert build_cache.module_closure("seggaussian.other", pkg) == (
        "seggaussian", "seggaussian.other", "seggaussian.sub", "seggaussian.sub.leaf")


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("raw")
    synthetic.synthesize(root / "scannetpp", 1, 0, "scannetpp", synthetic.SynthConfig(width=40, num_views=3))
    return root


def test_changing_one_stage_module_reruns_exactly_that_stage_and_downstream(raw, tmp_path, monkeypatch):
    source = tmp_path / "src" / "seggaussian"
    shutil.copytree(build_cache.PACKAGE_DIR, source, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(build_cache, "PACKAGE_DIR", source)
    config = BuildConfig(source="synthetic", root=raw, out=tmp_path / "ds", gaussians="oracle", progress=False,
                         oracle=OracleConfig(num_gaussians=400))

    def rebuild_after_editing(module: str | None) -> set[tuple]:
        if module is not None:
            path = source / module
            path.write_text(path.read_text() + "\n# edited\n")
        report = build_dataset(config)
        assert report.counts["failed"] == 0
        return {o.stages_run for o in report.outcomes}

    assert rebuild_after_editing(None) == {("gaussians", "transfer", "views")}
    assert rebuild_after_editing(None) == {()}
    assert rebuild_after_editing("pipeline/stages/views.py") == {("views",)}
    assert rebuild_after_editing("render/labelmaps.py") == {("views",)}
    assert rebuild_after_editing("pipeline/stages/transfer.py") == {("transfer", "views")}
    assert rebuild_after_editing("labels/oracle.py") == {("gaussians", "transfer", "views")}
    assert rebuild_after_editing("pipeline/split.py") == {()}  # not code of any stage
    assert rebuild_after_editing("fit/optimize.py") == {()}  # the fitting mode's code, not the oracle mode's
    assert rebuild_after_editing("core/constants.py") == {("gaussians", "transfer", "views")}
