"""A Ray cluster of several nodes on this machine, every node bound to 127.0.0.1: for tests and benchmarks of
``seggaussian build --executor ray``.

Each node is its own ``ray start`` (the head with ``--head``, the others with ``--address``), started in a new
process group, so that one node can be killed alone (``kill_node``: SIGKILL to its group and to the workers its
raylet started, each in a group of its own) and ``stop`` ends the processes of these nodes by their ids, never by
``ray stop`` (that ends every Ray of the user on the machine). Each node has a private ``--temp-dir`` (removed by
``stop``), random ports, a small object store, no dashboard and no usage statistics; the nodes use token
authentication with a token of their own (``RAY_AUTH_MODE=token``, ``RAY_AUTH_TOKEN``; ``driver_env`` gives a
driver the same).

``ray start --node-ip-address 127.0.0.1`` is rewritten by Ray to the machine's outward address (its
``resolve_ip_for_localhost``), and so is ``--address 127.0.0.1:PORT``; run as ``python -m
seggaussian.tools.ray_cluster <ray start options>``, this module runs Ray's own ``ray`` command with that
rewrite turned off, so the node's processes bind to and advertise 127.0.0.1 only.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

from seggaussian.pipeline.ray_tasks import LOOPBACK_ENV

#: Ray's health checks made fast, so a killed node is declared dead within seconds (defaults: about 30 s).
FAST_HEALTH_CHECKS = {"RAY_health_check_initial_delay_ms": "1000", "RAY_health_check_period_ms": "1000",
                      "RAY_health_check_timeout_ms": "1000", "RAY_health_check_failure_threshold": "3"}


class RayNode(NamedTuple):
    """One started node: its ``ray start`` process (the leader of the node's process group) and its log."""

    name: str
    process: subprocess.Popen
    log: Path


def free_port() -> int:
    """A TCP port of 127.0.0.1 nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LoopbackRayCluster:
    """``nodes`` Ray nodes of ``cpus`` CPUs each on 127.0.0.1, started by ``start`` and ended by ``stop``
    (a context manager does both)."""

    def __init__(self, folder: Path, nodes: int = 2, cpus: int = 1, object_store_mb: int = 80, memory_gb: float = 2.0,
                 start_timeout: float = 90.0):
        self.folder = Path(folder)
        self.count = int(nodes)
        self.cpus = int(cpus)
        self.object_store = int(object_store_mb) * 2**20
        self.memory = int(memory_gb * 2**30)
        self.start_timeout = float(start_timeout)
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.token = secrets.token_hex(16)
        self.nodes: list[RayNode] = []
        self.temp: Path | None = None

    def __enter__(self) -> "LoopbackRayCluster":
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def driver_env(self) -> dict:
        """The environment of a driver of this cluster (the token; the build takes 127.0.0.1 as its address)."""
        env = dict(os.environ, RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=self.token, RAY_USAGE_STATS_ENABLED="0")
        env.pop("RAY_ADDRESS", None)
        return env

    def _start_node(self, name: str, head: bool) -> RayNode:
        # one temp dir per node, as on separate machines (nodes starting at once in one temp folder race for the
        # same socket names), in a short folder of the system's temp dir: Ray's socket paths must stay
        # under the AF_UNIX limit of 107 bytes
        if self.temp is None:
            self.temp = Path(tempfile.mkdtemp(prefix="sgray-"))
        temp = self.temp / name
        temp.mkdir()
        args = [sys.executable, "-m", "seggaussian.tools.ray_cluster", "start", "--node-ip-address", "127.0.0.1",
                "--num-cpus", str(self.cpus), "--memory", str(self.memory), "--object-store-memory",
                str(self.object_store), "--temp-dir", str(temp), "--disable-usage-stats"]  # other ports: random
        if head:
            args += ["--head", "--port", str(self.port), "--include-dashboard", "false",
                     "--dashboard-port", str(free_port())]
        else:
            args += ["--address", self.address]
        log = self.folder / f"{name}.log"
        env = dict(self.driver_env(), **FAST_HEALTH_CHECKS)
        # a driver here may have made 127.0.0.1 its own Ray address through Ray's switch (ray_tasks.import_ray);
        # `ray start` of a worker node refuses to run under it, and this module keeps loopback itself
        env.pop(LOOPBACK_ENV, None)
        with open(log, "wb") as f:
            process = subprocess.Popen(args, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                       start_new_session=True)
        return RayNode(name, process, log)

    def _wait(self, node: RayNode) -> None:
        try:
            rc = node.process.wait(timeout=self.start_timeout)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"ray start of {node.name} did not return within {self.start_timeout:g} s "
                               f"(log: {node.log})") from None
        if rc != 0:
            tail = node.log.read_text(errors="replace").strip().splitlines()[-1:] or [""]
            raise RuntimeError(f"ray start of {node.name} failed ({rc}): {tail[0]} (log: {node.log})")

    def start(self) -> None:
        """Start the head, then the other nodes side by side; wait (bounded) until every ``ray start`` returned."""
        self.folder.mkdir(parents=True, exist_ok=True)
        head = self._start_node("head", True)
        self.nodes.append(head)
        self._wait(head)
        for i in range(1, self.count):
            self.nodes.append(self._start_node(f"node{i}", False))
        for node in self.nodes[1:]:
            self._wait(node)

    def group(self, name: str) -> int:
        """The process group id of node ``name`` (its ``ray start`` process was the group's leader)."""
        return next(n.process.pid for n in self.nodes if n.name == name)

    def processes(self, name: str) -> list[tuple[int, str]]:
        """(pid, command line) of every live process of node ``name``: its process group and their descendants
        (the raylet starts each worker in a process group of its own)."""
        table = {}
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                stat = Path(entry.path, "stat").read_text()
                cmd = Path(entry.path, "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()  # state, ppid, pgrp, ...
            if fields[0] != "Z":
                table[int(entry.name)] = (int(fields[1]), int(fields[2]), cmd)
        pgid = self.group(name)
        mine = {pid for pid, (_, group, _) in table.items() if group == pgid}
        grown = True
        while grown:
            children = {pid for pid, (ppid, _, _) in table.items() if ppid in mine} - mine
            mine |= children
            grown = bool(children)
        return sorted((pid, table[pid][2]) for pid in mine)

    def kill_node(self, name: str) -> None:
        """SIGKILL node ``name``: its process group (raylet, object store and the rest) and its workers, as when
        the machine is lost."""
        victims = self.processes(name)
        try:
            os.killpg(self.group(name), signal.SIGKILL)
        except ProcessLookupError:
            pass
        for pid, _ in victims:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def listening(self) -> set[str]:
        """The local addresses of every TCP socket a process of the cluster listens on (IPv4-mapped IPv6
        addresses read as IPv4)."""
        inodes = set()
        for node in self.nodes:
            for pid, _ in self.processes(node.name):
                try:
                    fds = os.listdir(f"/proc/{pid}/fd")
                except OSError:
                    continue
                for fd in fds:
                    try:
                        link = os.readlink(f"/proc/{pid}/fd/{fd}")
                    except OSError:
                        continue
                    if link.startswith("socket:["):
                        inodes.add(link[8:-1])
        found = set()
        for table in ("/proc/net/tcp", "/proc/net/tcp6"):
            try:
                rows = Path(table).read_text().splitlines()[1:]
            except OSError:
                continue
            for row in rows:
                cols = row.split()
                if cols[3] == "0A" and cols[9] in inodes:  # 0A: LISTEN
                    found.add(_proc_net_address(cols[1].split(":")[0]))
        return found

    def stop(self, timeout: float = 2.0) -> None:
        """End every node: SIGTERM to its processes, SIGKILL to those left after ``timeout`` s (the processes are
        listed first: a worker whose raylet ended is no longer found as its child)."""
        victims = [pid for node in self.nodes for pid, _ in self.processes(node.name)]
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid in victims:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + timeout
            while sig == signal.SIGTERM and time.monotonic() < deadline and any(_alive(pid) for pid in victims):
                time.sleep(0.1)
        for node in self.nodes:
            node.process.wait(timeout=timeout)
        if self.temp is not None:
            shutil.rmtree(self.temp, ignore_errors=True)
            self.temp = None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _proc_net_address(hex_address: str) -> str:
    """The IP of a ``/proc/net/tcp{,6}`` local-address field (host byte order per 32-bit word)."""
    words = [bytes.fromhex(hex_address[i:i + 8])[::-1] for i in range(0, len(hex_address), 8)]
    raw = b"".join(words)
    if len(raw) == 16 and raw[:12] == b"\0" * 10 + b"\xff\xff":
        raw = raw[12:]
    return socket.inet_ntop(socket.AF_INET if len(raw) == 4 else socket.AF_INET6, raw)


def _ray_cli_keeping_loopback() -> int:
    """Ray's ``ray`` command with ``sys.argv[1:]``, a loopback ``--node-ip-address`` / ``--address`` kept as given."""
    import ray._private.services as services

    services.resolve_ip_for_localhost = lambda host: host
    from ray.scripts.scripts import main

    sys.argv[0] = "ray"
    return main()


if __name__ == "__main__":
    sys.exit(_ray_cli_keeping_loopback())
