"""A build split over processes and machines gives the bytes of a build in one process.

* Two slices (``--num-shards 2``) run at the same time as two processes into one output, then a plain build
  assembles them.
* A build on a Ray cluster of three nodes on this machine, every node and the driver bound to 127.0.0.1, loses a
  worker node (its process group killed) while that node runs a scene; the scene is rerun elsewhere.

Both are compared file by file (every byte, the build cache included) with a build in this process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from seggaussian.pipeline import dataset as build_mod
from seggaussian.pipeline.config import BuildConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.pipeline.slicing import slice_ids
from seggaussian.shards.layout import MANIFEST_NAME, SPLITS_NAME

pytest.importorskip("seggaussian.sources.synthetic.generate")

REPO = Path(__file__).resolve().parents[2]
#: Bounded waits (seconds) for the processes these tests start.
BUILD_TIMEOUT = 300
START_TIMEOUT = 120


OPTIONS = ["--gaussians", "oracle", "--oracle-gaussians", "1500", "--no-progress"]


def _config(raw: Path, out: Path) -> BuildConfig:
    return BuildConfig(source="synthetic", root=raw, out=out, gaussians="oracle", progress=False,
                       oracle=OracleConfig(num_gaussians=1500))


@pytest.fixture(scope="module")
def one_process(raw, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("one") / "dataset"
    report = build_mod.build_dataset(_config(raw, out))
    assert report.counts == {"built": 3, "skipped": 0, "failed": 0}
    return out


def _files(ds: Path) -> dict[str, bytes]:
    """Every file below ``ds`` (the build cache included) by relative path."""
    return {str(p.relative_to(ds)): p.read_bytes() for p in sorted(ds.rglob("*")) if p.is_file()}


def _build(raw: Path, out: Path, *extra: str, env=None, stdout=subprocess.PIPE) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli.seggaussian_cli", "build", "--root", str(raw), "--out",
                             str(out), *OPTIONS, "--json", *extra], cwd=REPO, env=env, stdout=stdout,
                            stderr=subprocess.PIPE, text=True)


def test_slice_ids_are_stable_disjoint_and_cover_every_scene():
    ids = [f"scene{i:02d}" for i in range(11)]
    slices = [slice_ids(ids, 3, k) for k in range(3)]
    assert sorted(s for part in slices for s in part) == ids
    assert [len(part) for part in slices] == [4, 4, 3]
    assert slices[1] == ["scene01", "scene04", "scene07", "scene10"]
    assert slice_ids(list(reversed(ids)) + ids[:2], 3, 1) == slices[1]  # listing order and repeats do not matter
    assert slice_ids(ids, 1, 0) == ids


def test_shard_index_out_of_range_is_a_one_line_error(raw, tmp_path):
    from cli.seggaussian_cli import main

    result = CliRunner().invoke(main, ["build", "--root", str(raw), "--out", str(tmp_path / "o"), *OPTIONS,
                                       "--num-shards", "2", "--shard-index", "2"])
    assert result.exit_code == 1
    assert result.output.strip().splitlines() == ["Error: build: --shard-index must be in 0..1 for --num-shards 2, "
                                                  "got 2"]


def test_slices_built_at_once_then_assembled_equal_a_one_process_build(raw, one_process, tmp_path):
    out = tmp_path / "dataset"
    slices = [_build(raw, out, "--num-shards", "2", "--shard-index", str(k)) for k in range(2)]
    reports = []
    for proc in slices:
        stdout, stderr = proc.communicate(timeout=BUILD_TIMEOUT)
        assert proc.returncode == 0, stderr[-2000:]
        reports.append(json.loads(stdout))
    built = [sorted(s["scene"] for s in r["scenes"]) for r in reports]
    assert [r["shard"] for r in reports] == [{"index": 0, "count": 2}, {"index": 1, "count": 2}]
    assert sorted(built[0] + built[1]) == sorted(p.name for p in (one_process / ".build" / "scenes").iterdir())
    assert not set(built[0]) & set(built[1]) and all(r["counts"]["failed"] == 0 for r in reports)
    # a slice writes its scenes only: no dataset-level file yet
    assert not (out / MANIFEST_NAME).exists() and not (out / SPLITS_NAME).exists()
    assert not (out / ".build" / "build.json").exists()
    report = build_mod.build_dataset(_config(raw, out))
    assert report.counts == {"built": 0, "skipped": 3, "failed": 0} and report.assembled
    assert _files(out) == _files(one_process)


def _first_task_started(cluster, node: str) -> bool:
    """True once a worker process of ``node`` runs a scene task (Ray titles it after the task's function)."""
    return any(cmd.startswith("ray::_worker") for _, cmd in cluster.processes(node))


@pytest.mark.slow
def test_ray_multi_node_build_loses_a_node_and_equals_the_local_build(raw, one_process, tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'seggaussian[ray]')")
    from seggaussian.tools.ray_cluster import LoopbackRayCluster

    out = tmp_path / "dataset"
    with LoopbackRayCluster(tmp_path / "c", nodes=3, cpus=1, start_timeout=START_TIMEOUT) as cluster:
        assert cluster.listening() == {"127.0.0.1"}, {n.name: n.log.read_text()[-2000:] for n in cluster.nodes}
        log = (tmp_path / "build.json").open("w")
        build = _build(raw, out, "--executor", "ray", "--address", cluster.address, "--ray-memory-gb", "0.25",
                       "--ray-timeout", "60", env=cluster.driver_env(), stdout=log)
        deadline = time.monotonic() + START_TIMEOUT
        while not _first_task_started(cluster, "node1"):
            if build.poll() is not None or time.monotonic() > deadline:
                build.kill()
                pytest.fail(f"node1 ran no scene (build exit {build.wait()}): {build.stderr.read()[-3000:]}")
            time.sleep(0.05)
        cluster.kill_node("node1")
        try:
            _, stderr = build.communicate(timeout=BUILD_TIMEOUT)
        finally:
            if build.poll() is None:
                build.kill()
            log.close()
        assert not cluster.processes("node1")
    assert build.returncode == 0, stderr[-3000:]
    report = json.loads((tmp_path / "build.json").read_text())
    assert report["counts"] == {"built": 3, "skipped": 0, "failed": 0}
    assert len(report["ray_nodes"]) == 3 and {n["address"] for n in report["ray_nodes"]} == {"127.0.0.1"}
    assert _files(out) == _files(one_process)
    assert not any(name.startswith(".ray-probe-") for name in os.listdir(out))


def test_a_node_that_does_not_see_the_paths_names_them(tmp_path):
    from seggaussian.pipeline.ray_tasks import PROBE_PREFIX, _probe

    out, raw = tmp_path / "out", tmp_path / "raw"
    out.mkdir()
    raw.mkdir()
    (out / f"{PROBE_PREFIX}abc").write_text("abc")
    assert _probe([str(raw)], str(out), "abc", "n" * 56) is None
    assert sorted(os.listdir(out)) == [f"{PROBE_PREFIX}abc"]  # its own probe file written and removed
    assert _probe([str(raw / "missing")], str(out), "abc", "n" * 56) == (str(raw / "missing"),
                                                                         "no such folder on that node")
    other = tmp_path / "other"  # same name on the node, another folder: the driver's probe file is not there
    other.mkdir()
    path, why = _probe([str(raw)], str(other), "abc", "n" * 56)
    assert path == str(other) and "not the driver's folder" in why


def test_ray_connect_to_an_address_that_never_answers_is_a_bounded_one_line_error(raw, tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'seggaussian[ray]')")
    import socket

    with socket.socket() as silent:  # accepts connections (the kernel does) and never speaks
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        address = f"127.0.0.1:{silent.getsockname()[1]}"
        build = _build(raw, tmp_path / "o", "--executor", "ray", "--address", address, "--ray-timeout", "3")
        stdout, _ = build.communicate(timeout=BUILD_TIMEOUT)
    assert build.returncode == 1
    assert json.loads(stdout)["error"] == f"build: Ray did not connect to {address} within 3 s (--ray-timeout)"


class _Scheduler:
    """Ray's ``wait`` / ``get`` / ``cancel`` over fixed results: a value, an exception raised by ``get``, or None
    for a task that never finishes."""

    def __init__(self, results: dict):
        self.results, self.cancelled = results, []

    def wait(self, pending, num_returns, timeout):
        ready = [r for r in pending if self.results[r] is not None][:num_returns]
        if not ready:
            time.sleep(timeout)
        return ready, [r for r in pending if r not in ready]

    def get(self, ref):
        if isinstance(self.results[ref], BaseException):
            raise self.results[ref]
        return self.results[ref]

    def cancel(self, ref, force):
        self.cancelled.append(ref)


def test_a_lost_scene_task_fails_that_scene_only_as_in_the_local_pool():
    from seggaussian.pipeline.ray_tasks import collect
    from seggaussian.pipeline.records import SceneOutcome, SceneTask

    tasks = {name: SceneTask(name, "scannetpp", Path("raw"), "f", None, None) for name in ("a", "b", "c")}
    built = SceneOutcome("a", "scannetpp", None, "built", ("views",), None, {}, {}, {}, 1.0)
    lost = RuntimeError("The worker died unexpectedly while executing this task.\nmore lines")
    ray = _Scheduler({"ref-a": built, "ref-b": lost, "ref-c": None})
    seen = []
    outcomes = collect(ray, {"ref-a": tasks["a"], "ref-b": tasks["b"], "ref-c": tasks["c"]}, 0.1, seen.append)
    assert seen == outcomes and [o.scene_id for o in outcomes] == ["a", "b", "c"]
    assert outcomes[0] is built
    assert outcomes[1].status == "failed" and outcomes[1].reason == (
        "worker crashed: RuntimeError: The worker died unexpectedly while executing this task.")
    assert outcomes[2].status == "failed" and "--ray-scene-timeout" in outcomes[2].reason
    assert ray.cancelled == ["ref-c"]
