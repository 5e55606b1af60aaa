"""seggaussian.util.allocator: freed memory is reused without page faults once the package is imported, and
SEGGAUSSIAN_MALLOC=system keeps glibc's own behaviour (each run in a fresh interpreter)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                                reason="the allocator settings are glibc's (mallopt); other C libraries are left alone")

# Allocates and fills a 64 MB array, frees it, allocates the same size again while another array lives (as a
# training step keeps the previous view's outputs), and counts the minor page faults of the second fill.
_PROBE = """
import json, resource, sys
import seggaussian
from seggaussian.util import allocator
import numpy as np
size = 64 << 20
keep = np.ones(1 << 20)
a = np.empty(size, np.uint8); a.fill(1); del a
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
b = np.empty(size, np.uint8); b.fill(2)
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
print(json.dumps({"faults": faults, **allocator.settings()}))
"""


def _probe(**env) -> dict:
    res = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120,
                         env={**os.environ, **env})
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout)


def test_freed_memory_is_reused_without_page_faults():
    applied = _probe(SEGGAUSSIAN_MALLOC="")
    system = _probe(SEGGAUSSIAN_MALLOC="system")
    assert applied["keep_freed_memory"] and not system["keep_freed_memory"]
    # glibc's default maps the second 64 MB afresh (16,384 faults of 4 KB pages, fewer with huge pages)
    assert system["faults"] >= 16
    assert applied["faults"] < 8 <= system["faults"] // 2
