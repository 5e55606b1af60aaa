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

Other splat formats plug in by building a ``FuzzTarget`` with their reader, seeds and mutators
(``BYTE_MUTATORS`` apply to any format; ``PLY_MUTATORS`` edit a PLY header).
"""

from __future__ import annotations

import math
import re
import signal
import time
import traceback
from collections import Counter
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.gaussians import Gaussians
from seggaussian.io.ply import PlyFormatError, read_gaussians_ply, read_ply_header, write_gaussians_ply

VERDICTS = ("accepted", "clean_error", "nonfinite", "crash", "hang")
#: Packages whose frames count as "our code" when deciding whether an error was raised cleanly.
OWN_PACKAGES = ("seggaussian", "ovgaussian")
#: Default per-mutant time limit in seconds (the largest seed reads in well under 0.1 s).
DEFAULT_TIMEOUT_S = 5.0

Mutator = Callable[[bytes, np.random.Generator], bytes]


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
    body = _body_start(data)
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


# --- PLY header mutators --------------------------------------------------------------------------
_END_HEADER = re.compile(rb"end_header[ \t]*\r?\n")


def _body_start(data: bytes) -> int:
    match = _END_HEADER.search(data[: 1 << 20])
    return match.end() if match else 0


def _split(data: bytes) -> tuple[list[bytes], bytes] | None:
    """Header lines (without ``end_header``) and the body, or None when there is no header."""
    match = _END_HEADER.search(data[: 1 << 20])
    if match is None:
        return None
    head = data[: match.start()]
    lines = head.split(b"\n")
    if head.endswith(b"\n"):
        lines = lines[:-1]
    return lines, data[match.end():]


def _join(lines: list[bytes], body: bytes) -> bytes:
    return b"\n".join(lines) + b"\nend_header\n" + body


def _header_lines(kind: bytes):
    def indices(lines: list[bytes]) -> list[int]:
        return [i for i, line in enumerate(lines) if line.startswith(kind)]
    return indices


_properties = _header_lines(b"property ")
_elements = _header_lines(b"element ")


def ply_count(data: bytes, rng: np.random.Generator) -> bytes:
    """An element count set to 0, n - 1, n + 1, 2n, a huge number, a negative or a non-number."""
    parts = _split(data)
    if parts is None or not _elements(parts[0]):
        return data
    lines, body = parts
    i = _elements(lines)[int(rng.integers(0, len(_elements(lines))))]
    words = lines[i].split()
    n = int(words[2]) if len(words) == 3 and words[2].isdigit() else 1
    new = [b"0", str(max(0, n - 1)).encode(), str(n + 1).encode(), str(2 * n).encode(), b"4294967295",
           b"-1", b"1e3", b"99999999999999999999"][int(rng.integers(0, 8))]
    lines[i] = b" ".join(words[:2] + [new])
    return _join(lines, body)


def ply_rename(data: bytes, rng: np.random.Generator) -> bytes:
    """A property renamed: zero-padded index (``f_rest_05``), another property's name, upper case or
    a suffix."""
    parts = _split(data)
    if parts is None or not _properties(parts[0]):
        return data
    lines, body = parts
    props = _properties(lines)
    i = props[int(rng.integers(0, len(props)))]
    words = lines[i].split()
    name = words[-1]
    kind = int(rng.integers(0, 4))
    if kind == 0:
        match = re.match(rb"(.*_)(\d+)$", name)
        name = match.group(1) + b"0" + match.group(2) if match else name + b"_0"
    elif kind == 1:
        name = lines[props[int(rng.integers(0, len(props)))]].split()[-1]
    elif kind == 2:
        name = name.upper()
    else:
        name = name + b"x"
    lines[i] = b" ".join(words[:-1] + [name])
    return _join(lines, body)


def ply_retype(data: bytes, rng: np.random.Generator) -> bytes:
    """A property's type changed (``float`` -> ``double``, ``uchar``, ``int``, ...) or made a list."""
    parts = _split(data)
    if parts is None or not _properties(parts[0]):
        return data
    lines, body = parts
    i = _properties(lines)[int(rng.integers(0, len(_properties(lines))))]
    words = lines[i].split()
    types = [b"double", b"uchar", b"int", b"short", b"float", b"char", b"uint", b"float128", b"list uchar int"]
    new = types[int(rng.integers(0, len(types)))]
    lines[i] = b"property " + new + b" " + words[-1]
    return _join(lines, body)


def ply_drop_line(data: bytes, rng: np.random.Generator) -> bytes:
    """A property, element, format or comment line removed or duplicated."""
    parts = _split(data)
    if parts is None or len(parts[0]) < 2:
        return data
    lines, body = parts
    i = int(rng.integers(1, len(lines)))
    if rng.random() < 0.5:
        del lines[i]
    else:
        lines.insert(i, lines[i])
    return _join(lines, body)


def ply_format(data: bytes, rng: np.random.Generator) -> bytes:
    """The ``format`` line changed to another format (binary body under an ASCII header and back)."""
    parts = _split(data)
    if parts is None:
        return data
    lines, body = parts
    formats = [b"ascii", b"binary_little_endian", b"binary_big_endian", b"binary", b"ascii 2.0"]
    for i, line in enumerate(lines):
        if line.startswith(b"format"):
            lines[i] = b"format " + formats[int(rng.integers(0, len(formats)))] + b" 1.0"
    return _join(lines, body)


def ply_ascii_body(data: bytes, rng: np.random.Generator) -> bytes:
    """The body replaced by whitespace-separated numbers (an ASCII body under whatever the header says)."""
    parts = _split(data)
    if parts is None:
        return data
    lines, body = parts
    rows = int(rng.integers(1, 300))
    values = rng.normal(size=(rows, int(rng.integers(1, 70))))
    text = b"\n".join(b" ".join(b"%.6g" % v for v in row) for row in values) + b"\n"
    return _join(lines, text)


def ply_extra_element(data: bytes, rng: np.random.Generator) -> bytes:
    """An element declared after the vertices (``face`` with a list, or a scalar element) with no data,
    too little data, or exactly its data."""
    parts = _split(data)
    if parts is None:
        return data
    lines, body = parts
    n = int(rng.integers(1, 20))
    scalar = rng.random() < 0.5
    lines = lines + ([f"element extra {n}".encode(), b"property float w"] if scalar
                     else [f"element face {n}".encode(), b"property list uchar int vertex_indices"])
    record = np.float32(1).tobytes() if scalar else b"\x03" + np.arange(3, dtype="<i4").tobytes()
    have = [0, n // 2, n][int(rng.integers(0, 3))]
    return _join(lines, body + record * have)


def ply_crlf(data: bytes, rng: np.random.Generator) -> bytes:
    """Header lines ended with CRLF (and, half the time, the whole file's newlines)."""
    parts = _split(data)
    if parts is None:
        return data
    lines, body = parts
    head = b"\r\n".join(lines) + b"\r\nend_header\r\n"
    return head + (body.replace(b"\n", b"\r\n") if rng.random() < 0.5 else body)


def ply_header_junk(data: bytes, rng: np.random.Generator) -> bytes:
    """A comment, an unknown keyword, a blank line or non-ASCII bytes inserted in the header."""
    parts = _split(data)
    if parts is None:
        return data
    lines, body = parts
    junk = [b"comment fuzz", b"obj_info x", b"bogus keyword", b"", b"property float late", b"\xff\xfe",
            b"element", b"format binary_little_endian 1.0"][int(rng.integers(0, 8))]
    lines.insert(int(rng.integers(1, len(lines) + 1)), junk)
    return _join(lines, body)


PLY_MUTATORS: tuple[tuple[str, Mutator], ...] = (
    ("ply_count", ply_count), ("ply_rename", ply_rename), ("ply_retype", ply_retype),
    ("ply_drop_line", ply_drop_line), ("ply_format", ply_format), ("ply_ascii_body", ply_ascii_body),
    ("ply_extra_element", ply_extra_element), ("ply_crlf", ply_crlf), ("ply_header_junk", ply_header_junk),
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


def _raised_by_own_code(exc: BaseException) -> bool:
    frames = traceback.extract_tb(exc.__traceback__)
    return bool(frames) and any(f"/{pkg}/" in Path(frames[-1].filename).as_posix() for pkg in OWN_PACKAGES)


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
        if not _raised_by_own_code(exc):
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


# --- the PLY target -------------------------------------------------------------------------------
#: Records kept from a large real seed file (its header count edited to match): mutants stay small.
MAX_SEED_RECORDS = 2000


def real_ply_seed(path: Path, max_records: int = MAX_SEED_RECORDS) -> tuple[str, bytes]:
    """A real binary 3DGS PLY as a seed, cut to its first ``max_records`` vertices (header count edited)."""
    header = read_ply_header(path)
    vertex = header.element("vertex")
    data = Path(path).read_bytes()
    if vertex.count <= max_records or header.format == "ascii" or len(header.elements) != 1:
        return Path(path).name, data
    itemsize = sum(np.dtype(p.dtype).itemsize for p in vertex.properties)
    head = data[: header.body_offset].replace(f"element vertex {vertex.count}".encode(),
                                               f"element vertex {max_records}".encode(), 1)
    body = data[header.body_offset: header.body_offset + max_records * itemsize]
    return f"{Path(path).name}[:{max_records}]", head + body


def written_ply_seeds(seed: int = 0) -> list[tuple[str, bytes]]:
    """Seeds written by our own writer: SH 1 with labels (binary LE), SH 2 big endian, SH 0 ASCII."""
    import tempfile

    rng = np.random.default_rng(seed)
    seeds = []
    cases = (("sh1_labels_le", 40, 1, {"binary": True}), ("sh2_be", 30, 2, {"binary": True, "endian": ">"}),
             ("sh0_ascii", 20, 0, {"binary": False}))
    with tempfile.TemporaryDirectory() as tmp:
        for name, n, degree, options in cases:
            k = (degree + 1) ** 2
            quats = rng.normal(size=(n, 4)).astype(np.float32)
            g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), quats,
                          rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32),
                          rng.normal(size=n).astype(np.float32), rng.normal(size=(n, k, 3)).astype(np.float32))
            if name == "sh1_labels_le":
                g = g.with_extras(semantic=rng.integers(-1, 100, n).astype(np.int32),
                                  instance=rng.integers(0, 9, n).astype(np.int32))
            path = Path(tmp) / f"{name}.ply"
            write_gaussians_ply(path, g, **options)
            seeds.append((f"written:{name}", path.read_bytes()))
    return seeds


def ply_target(real_files: Sequence[Path] = (), seed: int = 0) -> FuzzTarget:
    """The 3DGS PLY reader (``on_invalid='error'``) over the real files given plus our written seeds."""
    seeds = [real_ply_seed(Path(p)) for p in real_files] + written_ply_seeds(seed)
    return FuzzTarget("ply", lambda path: read_gaussians_ply(path)[0], seeds, PLY_MUTATORS + BYTE_MUTATORS,
                      (PlyFormatError,), ".ply")


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
