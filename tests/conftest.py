"""Fixtures shared by several test files, and the test folders on ``sys.path``.

The tests mirror the packages (``tests/seggaussian/...``, ``tests/ovgaussian/...``, ``tests/cli/``; repository-wide
rules at the top). A few test modules share helpers by module name across folders (``from test_bench import
_write_tiny_dataset`` in the shards and CLI tests): every test folder is put on ``sys.path`` here, before any test
module is collected, as pytest does for the folder of each file it collects. Test module names are therefore
unique across the folders (pytest refuses two with one name).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
for _folder in sorted({path.parent for path in TESTS.rglob("*.py")} - {TESTS}, reverse=True):
    if str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))
# pytest puts tests/ (this file's folder) on sys.path, where tests/seggaussian and tests/ovgaussian would be
# namespace packages shadowing the real ones when the repository root is not on sys.path (``python -m pytest``
# from the root adds it, a bare ``pytest`` does not): the root goes first, so the packages are always ours.
sys.path.insert(0, str(TESTS.parent))


def pytest_collection_modifyitems(config, items):
    """Files holding a ``slow`` test run first, each file's tests in their own order: ``make test`` hands whole files
    to two workers in collection order (``--dist loadfile --no-loadscope-reorder``), so the long files start at once
    and the many short ones fill in behind them and both workers end together. (xdist's own reorder, by number of
    tests, put the one-test files that take minutes last, and one worker ran them alone.)"""
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)


@pytest.fixture
def one_torch_thread():
    """Tiny tensors: one torch thread is faster and immune to the shared machine's load (restored after)."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
