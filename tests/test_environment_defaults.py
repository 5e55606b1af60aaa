"""Process-wide threading defaults set by importing the packages (seggaussian/__init__.py).

Both take effect only when set before torch / numba start their thread pools, so they are checked in a fresh
interpreter: importing ``ovgaussian`` (what every ``ovgaussian`` command does first) sets them, and a value the
user exported is left alone.
"""

from __future__ import annotations

import os
import subprocess
import sys

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
