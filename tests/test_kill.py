"""Real SIGKILLs at write points (found by watching for the toolkit's temp files), for ``build`` and for
training during checkpoint saves. After a rerun, the output is byte-identical to an uninterrupted run and
no temporary is left anywhere."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from seggaussian.util.atomic import is_temp_name

REPO = Path(__file__).resolve().parents[1]
#: SIGKILLs per test (the issue asks for at least 10).
MIN_KILLS = 10
#: Give up on one attempt after this long (a job that neither writes nor ends).
ATTEMPT_TIMEOUT_S = 120.0


class Driver:
    """The fork server of tests/kill_driver.py (heavy imports once; each job in a forked child)."""

    def __init__(self):
        env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, str(REPO / "tests" / "kill_driver.py")], cwd=REPO, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def start(self, job: str, **args) -> int:
        self.proc.stdin.write(json.dumps({"job": job, "args": args}) + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())["pid"]

    def status(self) -> int:
        return json.loads(self.proc.stdout.readline())["status"]

    def run(self, job: str, **args) -> int:
        self.start(job, **args)
        return self.status()

    def close(self):
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


@pytest.fixture(scope="module")
def driver():
    d = Driver()
    yield d
    d.close()


def _temps(folder: Path) -> list[str]:
    found = []
    for dirpath, dirnames, filenames in os.walk(folder):
        found += [os.path.join(dirpath, n) for n in dirnames + filenames if is_temp_name(n)]
    return found


def _key(path: str) -> str:
    """A temp file's write point: its path with the pid/token of the writer removed."""
    return re.sub(r"\.tmp-\d+(-[0-9a-f]+)?", ".tmp", path)


def kill_at_new_write_points(driver: Driver, job: str, folder: Path, kills: int, within: str = "",
                             **args) -> list[str]:
    """Run ``job`` again and again; each run is SIGKILLed at the first write point (temp file whose path
    contains ``within``) not killed before. Stops after ``kills`` kills. Returns the write points."""
    killed: list[str] = []
    while len(killed) < kills:
        stale = set(_temps(folder))  # left by the previous kill; the run sweeps them
        pid = driver.start(job, **args)
        deadline = time.monotonic() + ATTEMPT_TIMEOUT_S
        landed = None
        while landed is None and time.monotonic() < deadline:
            for temp in _temps(folder):
                if temp not in stale and within in temp and _key(temp) not in killed:
                    os.kill(pid, signal.SIGKILL)
                    landed = _key(temp)
                    break
            else:
                try:  # the child ended on its own: nothing new to kill in this run
                    done, _ = os.waitpid(pid, os.WNOHANG)
                except ChildProcessError:  # not our child (the driver's): ask the driver
                    done = 0
                if done or not Path(f"/proc/{pid}").exists() or _zombie(pid):
                    break
                time.sleep(0.0005)
        status = driver.status()
        if landed is None:
            assert status == 0, f"{job} failed without a kill (status {status})"
            if not killed or len(killed) < kills:
                pytest.fail(f"{job} finished after {len(killed)} kills; no new write point to kill: {killed}")
        else:
            assert status == -signal.SIGKILL, status
            killed.append(landed)
    return killed


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z"
    except OSError:
        return True


def _files(folder: Path, skip=()) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not set(p.relative_to(folder).parts) & set(skip)}


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    from seggaussian.sources.synthetic.generate import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("raw")
    cfg = SynthConfig(width=32, num_views=3)
    synthesize(root / "scannetpp", 2, 0, "scannetpp", cfg)
    return root


@pytest.mark.slow
def test_build_killed_at_write_points_resumes_byte_identical(driver, raw, tmp_path):
    reference = tmp_path / "reference"
    assert driver.run("build", root=str(raw), out=str(reference)) == 0
    out = tmp_path / "killed"
    killed = kill_at_new_write_points(driver, "build", out, MIN_KILLS, root=str(raw), out=str(out))
    assert len(killed) >= MIN_KILLS and len(set(killed)) == len(killed)
    assert driver.run("build", root=str(raw), out=str(out)) == 0
    assert _temps(out) == []
    # the published dataset (everything outside the build cache) is byte-identical
    assert _files(out, skip={".build"}) == _files(reference, skip={".build"})
    assert sorted(_files(out)) == sorted(_files(reference))


@pytest.mark.slow
def test_training_killed_during_checkpoint_saves_resumes_identically(driver, tmp_path):
    epochs = 4  # spare write points: a save the poll misses under load is never revisited after a resume
    reference = tmp_path / "reference"
    assert driver.run("train", out=str(reference), epochs=epochs) == 0
    out = tmp_path / "killed"
    killed = kill_at_new_write_points(driver, "train", out, MIN_KILLS, within="/checkpoints/", out=str(out),
                                      epochs=epochs)
    assert len(killed) >= MIN_KILLS and all("/checkpoints/" in k for k in killed), killed
    assert driver.run("train", out=str(out), epochs=epochs) == 0
    assert _temps(out) == []
    ref_ckpt = _files(reference / "checkpoints")
    # default retention (TrainConfig.keep_checkpoints = 2): the last 2 epoch folders plus the best, 3 files each,
    # and latest.json + best.json; the killed-and-resumed run holds exactly the same files
    folders = {name.split("/")[0] for name in ref_ckpt if name.startswith("epoch-")}
    assert {"epoch-0003", "epoch-0004"} <= folders and len(folders) <= 3
    assert _files(out / "checkpoints") == ref_ckpt and len(ref_ckpt) == 3 * len(folders) + 2
    assert (out / "metrics.jsonl").read_text() == (reference / "metrics.jsonl").read_text()
