"""Process-wide threading defaults set by importing the packages (seggaussian/__init__.py).

Both take effect only when set before torch / numba start their thread pools, so they are checked in a fresh
interpreter: importing ``ovgaussian`` (what every ``ovgaussian`` command does first) sets them, and a value the
user exported is left alone.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

PROBE = "import {package}, os; print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('NUMBA_THREADING_LAYER'))"


def _probe(package: str, **overrides: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    env.update(overrides)
    out = subprocess.run([sys.executable, "-c", PROBE.format(package=package)], env=env, check=True,
                         capture_output=True, text=True).stdout
    return out.split()


@pytest.mark.parametrize("package", ["seggaussian", "ovgaussian"])
def test_importing_a_package_sets_passive_openmp_waits_and_the_omp_layer(package):
    assert _probe(package) == ["PASSIVE", "omp"]


@pytest.mark.parametrize("package", ["seggaussian", "ovgaussian"])
def test_a_users_own_settings_win(package):
    assert _probe(package, OMP_WAIT_POLICY="ACTIVE", NUMBA_THREADING_LAYER="workqueue") == ["ACTIVE", "workqueue"]


def test_the_ovgaussian_command_gets_the_defaults_before_torch_loads():
    # The console script imports the group module, which imports ovgaussian before any command module (torch).
    code = ("import sys, os; import cli.ovgaussian_cli; "
            "print('torch' in sys.modules, os.environ.get('OMP_WAIT_POLICY'))")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__)))).stdout.split()
    assert out == ["False", "PASSIVE"]


# --- numba's kernel cache folder (seggaussian/util/numba_cache.py) ------------------------------------------------

HELPER = "import numba\n\n@numba.njit(cache=True)\ndef offset():\n    return {value}\n"
KERNEL = ("import numba\nfrom seggaussian.helper import offset\n\n@numba.njit(cache=True)\n"
          "def kernel(x):\n    return x + offset()\n")
RUN_KERNEL = "import sys; sys.path.insert(0, sys.argv[1]); from seggaussian.kernel import kernel; print(kernel(1))"


def _tree(root, value: int):
    package = root / "seggaussian"
    package.mkdir(parents=True, exist_ok=True)
    (package / "__init__.py").write_text("")
    (package / "helper.py").write_text(HELPER.format(value=value))
    (package / "kernel.py").write_text(KERNEL)
    (package / "plain.py").write_text("X = 1\n")


def _run_kernel(root, cache_dir) -> str:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    return subprocess.run([sys.executable, "-c", RUN_KERNEL, str(root)], env=env, check=True, capture_output=True,
                          text=True).stdout.strip()


def test_the_cache_folder_follows_every_numba_module_and_only_those(tmp_path):
    from seggaussian.util.numba_cache import kernel_source_digest

    _tree(tmp_path, 10)
    before = kernel_source_digest(tmp_path)
    (tmp_path / "seggaussian" / "plain.py").write_text("X = 2\n")          # no numba: same kernels
    assert kernel_source_digest(tmp_path) == before
    (tmp_path / "seggaussian" / "helper.py").write_text(HELPER.format(value=20))
    assert kernel_source_digest(tmp_path) != before


def test_the_default_folder_is_named_by_this_installation_s_kernels():
    """Without a root, the digest covers this installation's kernel modules (it once looked one folder too deep,
    found none, and named every version's kernels by the digest of nothing: stale kernels after an update)."""
    import hashlib

    from seggaussian.util.numba_cache import kernel_modules, kernel_source_digest, numba_cache_dir, source_root

    modules = kernel_modules(source_root())
    assert {"seggaussian.render.binning_numba", "seggaussian.render.projection_lanes"} <= set(modules)
    digest = kernel_source_digest(source_root())
    assert digest != hashlib.sha256().hexdigest()[:len(digest)]
    assert numba_cache_dir().name == digest


def test_an_updated_helper_module_is_never_served_from_a_stale_cache(tmp_path):
    from seggaussian.util.numba_cache import kernel_source_digest

    root, shared_cache = tmp_path / "src", tmp_path / "one-folder"
    _tree(root, 10)
    first = tmp_path / kernel_source_digest(root)
    assert _run_kernel(root, first) == "11" == _run_kernel(root, shared_cache)
    (root / "seggaussian" / "helper.py").write_text(HELPER.format(value=20))
    # numba alone (one cache folder whatever the sources) serves the kernel compiled against the old helper
    assert _run_kernel(root, shared_cache) == "11"
    # a folder named by the digest compiles afresh
    assert _run_kernel(root, tmp_path / kernel_source_digest(root)) == "21"


def test_importing_seggaussian_names_a_cache_folder_under_the_user_cache(tmp_path):
    code = "import seggaussian, os; print(os.environ.get('NUMBA_CACHE_DIR'))"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True).stdout
    folder = Path(out.strip())
    assert folder.parent == tmp_path / "cache" / "seggaussian" / "numba" and folder.is_dir()
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")                         # the user's own setting wins
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True).stdout
    assert out.strip() == str(tmp_path / "mine")
    del env["NUMBA_CACHE_DIR"]
    (tmp_path / "blocked").write_text("a file where the cache folder would go")
    env["XDG_CACHE_HOME"] = str(tmp_path / "blocked")                       # unusable: numba keeps its default
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True).stdout
    assert out.strip() == "None"


def test_the_digest_covers_what_kernels_import_and_not_what_only_names_numba(tmp_path):
    from seggaussian.util.numba_cache import kernel_modules, kernel_source_digest

    _tree(tmp_path, 10)
    package = tmp_path / "seggaussian"
    (package / "constants.py").write_text("LIMIT = 1.0\n")                 # frozen into a kernel at compile time
    (package / "kernel.py").write_text(KERNEL.replace("import numba\n", "import numba\nfrom seggaussian.constants import LIMIT\n"))
    (package / "threads.py").write_text("import numba\n\ndef use(n):\n    numba.set_num_threads(n)\n")
    assert kernel_modules(tmp_path) == ("seggaussian.helper", "seggaussian.kernel")
    before = kernel_source_digest(tmp_path)
    (package / "threads.py").write_text("import numba\n\ndef use(n):\n    numba.set_num_threads(max(n, 1))\n")
    assert kernel_source_digest(tmp_path) == before                        # names numba, defines no kernel
    (package / "constants.py").write_text("LIMIT = 2.0\n")
    assert kernel_source_digest(tmp_path) != before                        # no numba in it, but a kernel reads it

