"""Every process pool of the toolkit and its benchmarks starts its workers with ``seggaussian.util.workers``'
``pool_options``, so that a killed command leaves no worker running (tested by killing one: test_bench_suite.py,
test_build.py). A pool made without it is found here, in the source, before anyone has to kill it."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("seggaussian", "ovgaussian", "cli", "benchmarks", "scripts")


def pools(tree: ast.AST):
    """The calls of ``ProcessPoolExecutor`` (by that name or as an attribute) in a module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", None)
            if name == "ProcessPoolExecutor":
                yield node


def with_pool_options(call: ast.Call) -> bool:
    """The call unpacks ``pool_options(...)`` into its keywords."""
    return any(k.arg is None and isinstance(k.value, ast.Call) and getattr(k.value.func, "id", None) == "pool_options"
               for k in call.keywords)


def test_every_process_pool_ends_its_workers_with_their_parent():
    found, bare = 0, []
    for folder in FOLDERS:
        for path in sorted((REPO / folder).rglob("*.py")):
            for call in pools(ast.parse(path.read_text(), str(path))):
                found += 1
                if not with_pool_options(call):
                    bare.append(f"{path.relative_to(REPO)}:{call.lineno}")
    assert found >= 4  # the build's, synth's, the profile's and the fit benchmark's pools
    assert not bare, f"process pools without **pool_options(...): {bare}"


def test_the_check_tells_a_bare_pool_from_one_with_pool_options():
    bare = ast.parse("ProcessPoolExecutor(max_workers=2)")
    good = ast.parse("futures.ProcessPoolExecutor(max_workers=2, **pool_options(ctx))")
    assert [with_pool_options(c) for c in pools(bare)] == [False]
    assert [with_pool_options(c) for c in pools(good)] == [True]
