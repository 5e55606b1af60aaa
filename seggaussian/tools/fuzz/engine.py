"""Seeded file fuzzing of the splat readers: mutants of seed files, each classified by what the reader did.

A ``FuzzTarget`` is a reader (``path -> Gaussians``, raising on bad input) plus the seed files it reads
and the mutators that make sense for its format. ``make_mutants`` derives ``count`` mutants from the
seeds with one ``numpy`` generator (explicit seed: the same arguments give the same bytes);
``run_fuzz`` writes each mutant to a file, calls the reader under a per-mutant time limit and sorts the
outcome into one of:

* ``accepted``    the reader returned Gaussians whose every array is finite;
* ``clean_error`` it raised one of the target's error types, from our own code, naming the file;
* ``nonfinite``   it returned Gaussians holding NaN or Inf (a silent wrong value);
* ``crash``       any other exception, or a clean type raised inside a dependency or not naming the file;
* ``hang``        it ran past the time limit (``SIGALRM`` in the main thread; a loop inside one C call
                  is only stopped when that call returns, so a hang is reported late, never missed).

A format plugs in by building a ``FuzzTarget`` with its reader, seeds and mutators (``BYTE_MUTATORS`` apply
to any format): the PLY target and its header mutators are in ``fuzz_ply.py``, the other splat formats' in
``fuzz_splat.py``.
"""

from __future__ import annotations

import math
import re
import signal
import time
from collections import Counter
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.core.gaussians import Gaussians
from seggaussian.tools.own_code import raised_by_own_code

VERDICTS = ("accepted", "clean_error", "nonfinite", "crash", "hang")
#: Default per-mutant time limit in seconds (the largest seed reads in well under 0.1 s).
DEFAULT_TIMEOUT_S = 5.0

Mutator = Callable[[bytes, np.random.Generator], bytes]
#: The end of a PLY-style header (``end_header`` and its line break).
END_HEADER = re.compile(rb"end_header[ \t]*\r?\n")


class Mutant(NamedTuple):
    """One mutated file."""

    #: ``<seed name>/<mutator>/<index>``: unique within a run, stable for a given generator seed.
    name: str
    mutator: str
    data: bytes


class Outcome(NamedTuple):
    """What the reader did with one mutant."""

    name: str
    mutator: str
    verdict: str
    #: The error message, or for ``accepted`` the number of Gaussians read.
    detail: str
    seconds: float


class FuzzTarget(NamedTuple):
    """A reader to fuzz, its seed files and its mutators."""

    name: str
    #: Reads one file; returns Gaussians or raises.
    read: Callable[[Path], Gaussians]
    #: ``(name, bytes)`` of valid files the mutants start from.
    seeds: Sequence[tuple[str, bytes]]
    #: ``(name, function)`` pairs; each function returns a mutated copy of its input.
    mutators: Sequence[tuple[str, Mutator]]
    #: Exception types that count as a clean refusal (when raised by our code and naming the file).
    clean_errors: tuple[type, ...] = (ValueError,)
    #: File name suffix of the mutants (readers that sniff the content must not rely on it).
    suffix: str = ".ply"


class FuzzReport(NamedTuple):
    target: str
    outcomes: list

    @property
    def counts(self) -> dict[str, int]:
        c = Counter(o.verdict for o in self.outcomes)
        return {v: c.get(v, 0) for v in VERDICTS}

    def failures(self) -> list[Outcome]:
        """Outcomes that are bugs: a crash, a hang or a non-finite value accepted silently."""
        return [o for o in self.outcomes if o.verdict in ("crash", "hang", "nonfinite")]

    def by_mutator(self) -> dict[str, dict[str, int]]:
        table: dict[str, Counter] = {}
        for o in self.outcomes:
            table.setdefault(o.mutator, Counter())[o.verdict] += 1
        return {m: {v: c.get(v, 0) for v in VERDICTS} for m, c in sorted(table.items())}


# --- byte-level mutators (any format) -------------------------------------------------------------
def body_start(data: bytes) -> int:
    """Offset of the body after a PLY-style header in the first MiB, or 0 (a headerless file)."""
    match = END_HEADER.search(data[: 1 << 20])
    return match.end() if match else 0


def flip_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """1 to 8 random bytes replaced by random values."""
    if not data:
        return data
    out = bytearray(data)
    for i in rng.integers(0, len(out), size=int(rng.integers(1, 9))):
        out[i] = int(rng.integers(0, 256))
    return bytes(out)


def flip_bits(data: bytes, rng: np.random.Generator) -> bytes:
    """One random bit flipped."""
    if not data:
        return data
    out = bytearray(data)
    i = int(rng.integers(0, len(out)))
    out[i] ^= 1 << int(rng.integers(0, 8))
    return bytes(out)


def truncate(data: bytes, rng: np.random.Generator) -> bytes:
    """Cut at a random length (0 to len - 1)."""
    return data[: int(rng.integers(0, max(1, len(data))))]


def append_garbage(data: bytes, rng: np.random.Generator) -> bytes:
    """1 to 64 random bytes, a newline or a copy of the last bytes appended."""
    kind = int(rng.integers(0, 3))
    if kind == 0:
        return data + rng.bytes(int(rng.integers(1, 65)))
    if kind == 1:
        return data + b"\n"
    return data + data[-int(rng.integers(1, 257)):]


def delete_span(data: bytes, rng: np.random.Generator) -> bytes:
    """A random span of 1 to 64 bytes removed."""
    if len(data) < 2:
        return data
    i = int(rng.integers(0, len(data) - 1))
    return data[:i] + data[i + int(rng.integers(1, 65)):]


def insert_span(data: bytes, rng: np.random.Generator) -> bytes:
    """1 to 64 random bytes inserted at a random position."""
    i = int(rng.integers(0, len(data) + 1))
    return data[:i] + rng.bytes(int(rng.integers(1, 65))) + data[i:]


def special_floats(data: bytes, rng: np.random.Generator) -> bytes:
    """1 to 4 aligned 4-byte words of the body set to a float32 NaN, +-Inf, huge or denormal value."""
    body = body_start(data)
    words = (len(data) - body) // 4
    if words <= 0:
        return data
    out = bytearray(data)
    values = np.array([np.nan, np.inf, -np.inf, 3.0e38, 1.0e-45, -0.0], dtype="<f4")
    for _ in range(int(rng.integers(1, 5))):
        i = body + 4 * int(rng.integers(0, words))
        out[i: i + 4] = values[int(rng.integers(0, len(values)))].tobytes()
    return bytes(out)


def random_file(data: bytes, rng: np.random.Generator) -> bytes:
    """Random bytes of a random length, or an empty file."""
    if rng.random() < 0.1:
        return b""
    return rng.bytes(int(rng.integers(1, 4096)))


BYTE_MUTATORS: tuple[tuple[str, Mutator], ...] = (
    ("flip_bytes", flip_bytes), ("flip_bits", flip_bits), ("truncate", truncate),
    ("append_garbage", append_garbage), ("delete_span", delete_span), ("insert_span", insert_span),
    ("special_floats", special_floats), ("random_file", random_file),
)


# --- generating and running ----------------------------------------------------------------------
def make_mutants(target: FuzzTarget, count: int, seed: int) -> list[Mutant]:
    """``count`` mutants, round-robin over seeds and mutators, 1 to 3 stacked mutations each (seeded)."""
    if not target.seeds:
        raise ValueError(f"fuzz target {target.name!r} has no seed files")
    rng = np.random.default_rng(seed)
    out = []
    for index in range(count):
        seed_name, data = target.seeds[index % len(target.seeds)]
        names = []
        steps = 1 if rng.random() < 0.7 else int(rng.integers(2, 4))
        for step in range(steps):
            # the first mutation cycles through the mutators, so every one is used equally often
            pick = (index // len(target.seeds)) % len(target.mutators) if step == 0 \
                else int(rng.integers(0, len(target.mutators)))
            name, mutate = target.mutators[pick]
            data = mutate(data, rng)
            names.append(name)
        out.append(Mutant(f"{seed_name}/{'+'.join(names)}/{index}", names[0], data))
    return out


class _Timeout(Exception):
    pass


def _on_alarm(signum, frame):
    raise _Timeout()


def _finite(g: Gaussians) -> bool:
    return all(np.isfinite(a).all() for a in (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh))


def classify(target: FuzzTarget, path: Path, timeout_s: float) -> tuple[str, str]:
    """``(verdict, detail)`` of reading ``path`` with ``target.read``."""
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        g = target.read(path)
    except _Timeout:
        return "hang", f"no answer within {timeout_s:g} s"
    except target.clean_errors as exc:
        message = str(exc)
        if not raised_by_own_code(exc):
            return "crash", f"{type(exc).__name__} from a dependency: {message}"
        if str(path) not in message:
            return "crash", f"error does not name the file: {message}"
        if "\n" in message.strip():
            return "crash", f"error is not one line: {message!r}"
        return "clean_error", message
    except Exception as exc:  # noqa: BLE001 -- everything else is what the fuzz exists to find
        return "crash", f"{type(exc).__name__}: {exc}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    if not isinstance(g, Gaussians):
        return "crash", f"reader returned {type(g).__name__}, not Gaussians"
    if not _finite(g):
        return "nonfinite", f"{len(g)} Gaussians with NaN or Inf"
    return "accepted", f"{len(g)} Gaussians"


def run_fuzz(target: FuzzTarget, count: int, seed: int, workdir: Path, *, timeout_s: float = DEFAULT_TIMEOUT_S,
             progress: Callable[[Outcome], None] | None = None) -> FuzzReport:
    """Generate ``count`` mutants, read each from ``workdir/<index><suffix>``, classify; files removed."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    outcomes = []
    for index, mutant in enumerate(make_mutants(target, count, seed)):
        path = workdir / f"mutant-{index:05d}{target.suffix}"
        path.write_bytes(mutant.data)
        start = time.perf_counter()
        verdict, detail = classify(target, path, timeout_s)
        outcome = Outcome(mutant.name, mutant.mutator, verdict, detail, time.perf_counter() - start)
        path.unlink()
        outcomes.append(outcome)
        if progress is not None:
            progress(outcome)
    return FuzzReport(target.name, outcomes)


def format_report(report: FuzzReport) -> str:
    """Markdown: counts per mutator and in total."""
    lines = [f"| mutator | {' | '.join(VERDICTS)} |", "|---|" + "---:|" * len(VERDICTS)]
    for mutator, counts in report.by_mutator().items():
        lines.append(f"| {mutator} | " + " | ".join(str(counts[v]) for v in VERDICTS) + " |")
    total = report.counts
    lines.append("| **total** | " + " | ".join(f"**{total[v]}**" for v in VERDICTS) + " |")
    return "\n".join(lines)


def seconds_summary(report: FuzzReport) -> str:
    times = [o.seconds for o in report.outcomes]
    if not times:
        return "no mutants"
    return (f"{len(times)} mutants, median {1e3 * float(np.median(times)):.2f} ms, "
            f"max {1e3 * max(times):.1f} ms, total {math.fsum(times):.1f} s")
