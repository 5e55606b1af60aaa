"""Processes seen through /proc, for the tests that kill a command and check that its worker processes go with it."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from typing import Callable, Optional

#: Clock ticks per second of /proc/PID/stat's CPU times.
TICKS = os.sysconf("SC_CLK_TCK")


def _stat(pid: int) -> Optional[list[str]]:
    """The fields of /proc/PID/stat after the command name (state first), or None once the process is gone."""
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except OSError:
        return None


def running(pid: int) -> bool:
    """The process exists and is not a zombie."""
    fields = _stat(pid)
    return fields is not None and fields[0] != "Z"


def children(pid: int) -> list[int]:
    """The running (not zombie) processes whose parent is ``pid``."""
    found = {int(e): _stat(int(e)) for e in os.listdir("/proc") if e.isdigit()}
    return [child for child, f in found.items() if f is not None and f[0] != "Z" and int(f[1]) == pid]


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (0 once it is gone)."""
    fields = _stat(pid)
    return 0.0 if fields is None else (int(fields[11]) + int(fields[12])) / TICKS


def assert_workers_end_with_their_parent(parent: subprocess.Popen, ready: Callable[[list[int]], bool],
                                         start_timeout: float = 180.0, end_timeout: float = 20.0) -> None:
    """Wait until ``ready(children of parent)`` (the workers are busy), SIGKILL the parent (no handler of it runs)
    and assert that none of those children is still running ``end_timeout`` seconds later. Whatever is left is
    killed at the end, pass or fail."""
    workers: list[int] = []
    try:
        deadline = time.monotonic() + start_timeout
        while time.monotonic() < deadline and parent.poll() is None:
            workers = children(parent.pid)
            if ready(workers):
                break
            time.sleep(0.2)
        assert parent.poll() is None, f"the command ended (status {parent.returncode}) before its workers were busy"
        assert ready(workers), f"the workers were not busy within {start_timeout:.0f} s: {workers}"
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + end_timeout
        while any(running(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        alive = [w for w in workers if running(w)]
        assert not alive, f"still running {end_timeout:.0f} s after their parent was killed: {alive}"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(timeout=10)
        for w in workers:
            try:
                os.kill(w, signal.SIGKILL)
            except ProcessLookupError:
                pass
