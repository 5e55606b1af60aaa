"""Scenes of ``seggaussian build --executor ray`` as Ray tasks on a cluster of one or more nodes.

* Connecting is bounded: ``BuildConfig.ray_timeout`` seconds for the cluster's GCS to accept a TCP connection
  and for ``ray.init`` to return in a child process (killed when it does not), else a one-line error. Ray
  rewrites a loopback address (``127.0.0.1:PORT``, the ``--node-ip-address 127.0.0.1`` of ``ray start``) to the
  machine's outward address; a cluster whose nodes were started bound to 127.0.0.1 is then never reached and
  ``ray.init`` retries forever. For a loopback address (and for a Ray started here) the driver therefore takes
  127.0.0.1 as its own address, through Ray's ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` (its node address becomes
  the loopback one), set before Ray is imported.
* Every alive node that can hold a scene task checks, before any scene is built, that it sees the raw root(s)
  and the output folder the driver sees: a task pinned to the node (``NodeAffinitySchedulingStrategy``, hard)
  lists the raw roots, reads a probe file the driver wrote into the output, and writes and removes its own. A
  node that fails stops the build with one line naming the node and the path.
* Each scene task asks for ``ray_cpus`` CPUs and ``ray_memory_gb`` of memory, spread over the nodes
  (``SPREAD``); a request no alive node can hold is refused at the start (Ray would wait for such a node
  forever). Ray reruns a task whose worker process or node was lost up to ``ray_retries`` times
  (``max_retries``); an error raised inside a scene is already a failed scene (``scene.build_scene`` never
  raises), so application errors are never retried (``retry_exceptions=False``).
* A task that still fails (retries used up, the object lost) fails its scene only, with the same reason the
  local process pool gives a crashed worker (``records.crashed_outcome``); the other scenes go on.
"""

from __future__ import annotations

import contextlib
import math
import os
import secrets
import socket
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

from seggaussian.pipeline.config import BuildConfig
from seggaussian.pipeline.records import SceneOutcome, SceneTask, crashed_outcome, failed_outcome
from seggaussian.util.atomic import write_text_atomic

#: Ray's switch for the address a process takes as its own: ``0`` makes it the loopback address.
LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
#: Prefix of the probe files the storage check writes into the output folder (removed when it ends).
PROBE_PREFIX = ".ray-probe-"


class NodeCheck(NamedTuple):
    """One Ray node that passed the storage check: its node id and the address Ray knows it by."""

    node_id: str
    address: str


def _host_port(address: str | None) -> tuple[str, int] | None:
    """(host, port) of a ``HOST:PORT`` address; None for no address, ``auto``, ``ray://...`` or a bare host."""
    if not address or "://" in address or ":" not in address:
        return None
    host, _, port = address.rpartition(":")
    host = host.strip("[]")
    return (host, int(port)) if port.isdigit() and host else None


def import_ray(address: str | None):
    """``import ray``, after making 127.0.0.1 this process's Ray address when ``address`` is loopback or None."""
    hp = _host_port(address)
    if address is None or (hp is not None and hp[0] in LOOPBACK_HOSTS):
        os.environ.setdefault(LOOPBACK_ENV, "0")
    try:
        import ray
    except ImportError:
        raise RuntimeError("--executor ray needs Ray: pip install 'seggaussian[ray]' (or ray>=2.9)") from None
    return ray


def connect(config: BuildConfig):
    """The ``ray`` module, connected to ``config.address`` (or a local Ray) within ``config.ray_timeout`` seconds.
    Returns (ray, whether this call connected it)."""
    ray = import_ray(config.address)
    if ray.is_initialized():
        return ray, False
    timeout = float(config.ray_timeout)
    hp = _host_port(config.address)
    if hp is not None:
        try:
            socket.create_connection(hp, timeout=timeout).close()
        except OSError as exc:
            raise ConnectionError(f"build: no Ray cluster answers at {config.address} "
                                  f"({exc.strerror or type(exc).__name__})") from None
        _check_connects(config.address, timeout)
    ray.init(address=config.address, include_dashboard=False, log_to_driver=False)
    return ray, True


def _check_connects(address: str, timeout: float) -> None:
    """Connect to ``address`` from a child process first: a ``ray.init`` that hangs there is killed after
    ``timeout`` seconds and reported in one line (a hung ``ray.init`` cannot be left behind in this process)."""
    code = ("import sys, ray; ray.init(address=sys.argv[1], include_dashboard=False, log_to_driver=False); "
            "ray.shutdown()")
    try:
        proc = subprocess.run([sys.executable, "-c", code, address], capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise TimeoutError(f"build: Ray did not connect to {address} within {timeout:g} s (--ray-timeout)") from None
    if proc.returncode != 0:
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        said = next((line for line in reversed(lines) if "Error" in line), lines[-1] if lines else "")
        raise RuntimeError(f"build: Ray could not connect to {address}: {said.strip()[:300]}")


def _probe(roots: list[str], out: str, token: str, node_id: str) -> tuple[str, str] | None:
    """On one node: None when it sees every raw root and the driver's output folder (and can write there),
    else (path, what is wrong)."""
    for root in roots:
        if not os.path.isdir(root):
            return root, "no such folder on that node"
        try:
            os.listdir(root)
        except OSError as exc:
            return root, exc.strerror or type(exc).__name__
    probe = Path(out) / f"{PROBE_PREFIX}{token}"
    try:
        if probe.read_text() != token:
            return out, "not the driver's folder (its probe file holds other text)"
    except OSError:
        return out, "not the driver's folder (the probe file it wrote there is missing: not shared storage?)"
    mine = Path(out) / f"{PROBE_PREFIX}{token}-{node_id[:12]}"
    try:
        write_text_atomic(mine, node_id)
        mine.unlink()
    except OSError as exc:
        return out, f"not writable ({exc.strerror or type(exc).__name__})"
    return None


def _node_label(node: dict) -> str:
    return f"Ray node {node['NodeID'][:12]} ({node.get('NodeManagerAddress', '?')})"


def scene_nodes(ray, cpus: float, memory: int) -> list[dict]:
    """The alive nodes that can hold one scene task; refuses a request no node can hold."""
    alive = [n for n in ray.nodes() if n.get("Alive")]
    fit = [n for n in alive if n.get("Resources", {}).get("CPU", 0) >= cpus
           and n.get("Resources", {}).get("memory", 0) >= memory]
    if not fit:
        raise RuntimeError(f"build: no alive Ray node offers {cpus:g} CPUs and {memory / 2**30:.2f} GiB of memory "
                           f"for a scene (--ray-cpus, --ray-memory-gb); {len(alive)} nodes alive")
    return fit


def check_nodes(ray, nodes: list[dict], roots: list[Path], out: Path, timeout: float) -> list[NodeCheck]:
    """Every node in ``nodes`` sees each of ``roots`` and ``out`` (see the module docstring), or a one-line error."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    token = secrets.token_hex(8)
    probe = Path(out) / f"{PROBE_PREFIX}{token}"
    write_text_atomic(probe, token)
    try:
        remote = ray.remote(_probe)
        refs = {remote.options(num_cpus=0, max_retries=0, scheduling_strategy=NodeAffinitySchedulingStrategy(
            n["NodeID"], soft=False)).remote([str(r) for r in roots], str(out), token, n["NodeID"]): n for n in nodes}
        ready, late = ray.wait(list(refs), num_returns=len(refs), timeout=timeout)
        for ref in late:
            ray.cancel(ref, force=True)
        if late:
            raise TimeoutError(f"build: {_node_label(refs[late[0]])} did not check the raw root and the output "
                               f"within {timeout:g} s (--ray-timeout)")
        for ref in ready:
            try:
                problem = ray.get(ref)
            except Exception as exc:  # noqa: BLE001 -- the node died or the task could not run there
                raise RuntimeError(f"build: {_node_label(refs[ref])} could not check the raw root and the output: "
                                   f"{type(exc).__name__}") from None
            if problem is not None:
                raise FileNotFoundError(f"build: {_node_label(refs[ref])} cannot see {problem[0]}: {problem[1]}")
    finally:
        probe.unlink(missing_ok=True)
    return [NodeCheck(n["NodeID"], n.get("NodeManagerAddress", "")) for n in nodes]


def collect(ray, refs: dict, scene_timeout: float, on_done) -> list[SceneOutcome]:
    """The outcome of every scene task in ``refs`` ({object ref: task}) as it finishes (``on_done`` called each
    time). A task that raises (its retries used up, its object lost) fails its scene only; when no task finishes
    within ``scene_timeout`` seconds (0 = no limit), the tasks still out are cancelled and their scenes fail."""
    pending = list(refs)
    outcomes: list[SceneOutcome] = []
    wait = scene_timeout or None
    while pending:
        done, pending = ray.wait(pending, num_returns=1, timeout=wait)
        if not done:
            for ref in pending:
                ray.cancel(ref, force=True)
                outcome = failed_outcome(refs[ref], f"no scene finished on Ray within {wait:g} s (--ray-scene-timeout)",
                                         wait)
                outcomes.append(outcome)
                on_done(outcome)
            break
        try:
            outcome = ray.get(done[0])
        except Exception as exc:  # noqa: BLE001 -- retries used up: that scene fails, the others go on
            outcome = crashed_outcome(refs[done[0]], exc)
        outcomes.append(outcome)
        on_done(outcome)
    return outcomes


def run_ray(tasks: list[SceneTask], config: BuildConfig, cache_root: Path, on_done,
            worker) -> tuple[list[SceneOutcome], list[NodeCheck]]:
    """Build every task as a Ray task running ``worker(task, config, cache_root, threads)``; see the module
    docstring. Returns the outcomes and the nodes that passed the storage check.

    Ray prints the cluster's messages (a task retried, a node lost) to standard output from a thread of its own;
    they go to standard error while this runs, so that standard output keeps the command's own output."""
    with contextlib.redirect_stdout(sys.stderr):
        return _run_ray(tasks, config, cache_root, on_done, worker)


def _run_ray(tasks, config, cache_root, on_done, worker):
    ray, connected = connect(config)
    try:
        cpus = float(config.ray_cpus)
        memory = int(float(config.ray_memory_gb) * 2**30)
        if cpus <= 0 or memory < 0 or config.ray_retries < 0:
            raise ValueError("build: --ray-cpus must be positive, --ray-memory-gb and --ray-retries not negative")
        nodes = scene_nodes(ray, cpus, memory)
        roots = sorted({Path(config.root), *(t.root for t in tasks),
                        *([Path(config.ply_dir)] if config.ply_dir is not None else [])})
        checked = check_nodes(ray, nodes, roots, Path(config.out), float(config.ray_timeout))
        remote = ray.remote(worker).options(num_cpus=cpus, memory=memory, max_retries=int(config.ray_retries),
                                            retry_exceptions=False, scheduling_strategy="SPREAD")
        threads = max(1, math.ceil(cpus))
        refs = {remote.remote(t, config, cache_root, threads): t for t in tasks}
        outcomes = collect(ray, refs, float(config.ray_scene_timeout), on_done)
        return outcomes, checked
    finally:
        if connected:
            ray.shutdown()
