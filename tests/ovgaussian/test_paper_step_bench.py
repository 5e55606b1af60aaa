"""benchmarks/bench_paper_step.py at a tiny scale: it runs, times every phase and the sparse U-Net on its own, and
it reports the device's busy share and, with ``--compare-workers``, the steps with a loader worker against those
without, and its budget check fails loudly (exit status 1, the missed figure named) when a budget is missed. Its step
budget follows the CPU type (benchmarks/machine_type.py): the slower type gets its own, an unknown type is reported
only.

The bench wraps library functions by name (``net.voxel_stage``, ``net.backbone``, the kernel-map builders, ...);
this keeps a rename from breaking it unnoticed. Timings are not asserted (they belong in BENCHMARKS.md)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "benchmarks" / "bench_paper_step.py"
TINY = ["--gaussians", "3000", "--scenes", "2", "--pixels", "128", "--steps", "1", "--preset", "slim"]


def _run(*budgets: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *TINY, *budgets], capture_output=True, text=True, cwd=REPO,
                          timeout=600)


@pytest.mark.slow
def test_tiny_paper_step_reports_phases_and_the_unet_and_fails_a_missed_budget():
    res = _run("--max-step-s", "1000", "--max-peak-gb", "100", "--max-backward-ratio", "100", "--compare-workers", "1")
    assert res.returncode == 0, res.stderr[-2000:]
    result, _ = json.JSONDecoder().raw_decode(res.stdout)
    assert result["workload"]["gaussians_per_scene"] == 3000 and len(result["steps"]) == 1
    step = result["steps"][0]
    assert step["phases_s"]["network"] > 0 and step["phases_s"]["backward"] > 0
    assert step["phases_s"]["sample"] > 0 and 0 < step["device_busy"] <= 1 and step["compute_s"] <= step["wall_s"]
    # the same steps with one loader worker: it samples (this process does not) and both blocks report their peaks
    compare = result["compare_workers"]
    worker_step = compare["with"]["steps"][0]
    assert compare["without"]["loader_workers"] == 0 and compare["with"]["loader_workers"] == 1
    assert worker_step["phases_s"]["sample"] == 0 and worker_step["worker_sample_s"] > 0
    assert compare["with"]["block_workers_peak_gb"] > 0 and compare["without"]["block_workers_peak_gb"] == 0
    assert compare["step_ratio"] > 0 and compare["peak_ratio"] > 1
    assert "with 1 loader workers / without: step" in res.stdout
    assert 0 < step["unet_forward_s"] and 0 < step["unet_backward_s"] <= step["phases_s"]["backward"] + 1e-6
    assert result["unet_backward_over_forward"] > 0 and result["peak_rss_gb"] > 0
    assert "within budget" in res.stdout.splitlines()[-1]

    missed = _run("--max-step-s", "0.000001", "--max-peak-gb", "100", "--max-backward-ratio", "100")
    assert missed.returncode == 1
    assert "FAILED: step" in missed.stdout.splitlines()[-1] and "Traceback" not in missed.stderr


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # bench_paper_step imports machine_type by this name
    spec.loader.exec_module(module)
    return module


def _cpuinfo(vendor: str, family: int, model: int, name: str, cpus: int = 2) -> str:
    block = (f"vendor_id\t: {vendor}\ncpu family\t: {family}\nmodel\t\t: {model}\nmodel name\t: {name}\n"
             "flags\t\t: fpu sse2 avx2\n")
    return "\n".join(f"processor\t: {i}\n{block}" for i in range(cpus))


@pytest.mark.parametrize("vendor, family, model, kind", [
    ("AuthenticAMD", 25, 1, "zen3"),     # EPYC 7003 (Milan)
    ("AuthenticAMD", 25, 0x21, "zen3"),  # Ryzen 5000 (Vermeer)
    ("AuthenticAMD", 25, 17, "zen4"),    # EPYC 9004 (Genoa)
    ("AuthenticAMD", 25, 0x61, "zen4"),  # Ryzen 7000 (Raphael)
    ("AuthenticAMD", 25, 0xA0, "zen4"),  # EPYC 97x4 (Bergamo)
    ("AuthenticAMD", 23, 49, "zen2"),     # EPYC 7xx2 (Rome)
    ("AuthenticAMD", 23, 1, "zen1"),      # EPYC 7xx1 (Naples): BENCHMARKS.md's "EPYC family 23" type
    ("AuthenticAMD", 26, 2, "unknown"),   # Zen 5
    ("GenuineIntel", 6, 207, "unknown"),  # Xeon
])
def test_the_cpu_type_is_read_from_cpuinfo(vendor, family, model, kind):
    machine_type = _load("machine_type")
    machine = machine_type.parse_cpuinfo(_cpuinfo(vendor, family, model, "Some CPU"))
    assert (machine.kind, machine.family, machine.model, machine.cores) == (kind, family, model, 2)
    assert machine.label.endswith("2 cores")
    assert ("Zen" in machine.label) == machine.known
    assert machine_type.parse_cpuinfo("").kind == "unknown"
    assert machine_type.detect(REPO / "no-such-cpuinfo").kind == "unknown"


def test_the_step_budget_follows_the_cpu_type_and_an_unknown_type_is_never_failed():
    machine_type = _load("machine_type")
    bench = _load("bench_paper_step")
    zen3 = machine_type.parse_cpuinfo(_cpuinfo("AuthenticAMD", 25, 1, "AMD EPYC 7B13"))
    zen4 = machine_type.parse_cpuinfo(_cpuinfo("AuthenticAMD", 25, 17, "AMD EPYC 9B14"))
    xeon = machine_type.parse_cpuinfo(_cpuinfo("GenuineIntel", 6, 207, "Intel(R) Xeon(R) Processor"))
    assert bench.step_budget(None, "cpu", zen4) == (20.0, True)
    # the slower type's budget covers the step measured there (22.6-25.7 s), so such a run does not fail
    zen3_budget, enforced = bench.step_budget(None, "cpu", zen3)
    assert enforced and zen3_budget >= 25.7 and zen3_budget > bench.step_budget(None, "cpu", zen4)[0]
    assert bench.step_budget(None, "cpu", xeon) == (zen3_budget, False)
    zen1 = machine_type.parse_cpuinfo(_cpuinfo("AuthenticAMD", 23, 1, "AMD EPYC"))
    assert zen1.known and bench.step_budget(None, "cpu", zen1) == (zen3_budget, False)  # no budget of its own
    assert bench.step_budget(None, "cuda", xeon) == (20.0, True)
    assert bench.step_budget(5.0, "cpu", xeon) == (5.0, True)
