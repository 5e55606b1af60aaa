"""Seeded fuzz of every splat reader: truncations, flipped bytes, wrong counts, bad magic, NaN payloads.

Each mutant is generated at test time from a small valid file and read through the public entry point
(``seggaussian.io.formats.read_gaussians``, format detected by content). Every outcome is classified:

* accepted: the Gaussians it returns hold only finite values (validation's default policy);
* clean error: ``PlyFormatError`` (``SplatFormatError`` is one) whose message names the file;
* crash: any other exception, or an accepted file with a non-finite value.

The test asserts zero crashes per format and that the mutants reach both outcomes.
"""

from __future__ import annotations

import gzip
import struct
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians, write_gaussians
from seggaussian.io.ply.header import PlyFormatError
from seggaussian.io.spz import encode_spz

#: Mutants per format.
MUTANTS = 500


def _gaussians(n: int = 40, degree: int = 1, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians.from_arrays(rng.uniform(-2, 2, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-6, 0, (n, 3)),
                                 rng.normal(size=n), rng.uniform(-1, 1, (n, k, 3)))


def _spz_v1(g: Gaussians) -> bytes:
    """A version-1 SPZ payload (float16 positions, 3-byte rotations), unwrapped, from a v2 encoding."""
    payload = gzip.decompress(encode_spz(g, version=2))
    n = len(g)
    head = bytearray(payload[:16])
    head[4:8] = struct.pack("<I", 1)
    return bytes(head) + g.means.astype("<f2").tobytes() + payload[16 + 9 * n:]


def _base_files(tmp: Path) -> dict[str, bytes]:
    g = _gaussians()
    out = {}
    for name, fmt, kwargs in (("splat", "splat", {}), ("compressed_ply", "compressed_ply", {}),
                              ("spz2", "spz", {"spz_version": 2}), ("spz3", "spz", {"spz_version": 3}),
                              ("spz4", "spz", {"spz_version": 4}), ("ply", "ply", {}),
                              ("ksplat0", "ksplat", {"ksplat_level": 0}), ("ksplat1", "ksplat", {"ksplat_level": 1}),
                              ("ksplat2", "ksplat", {"ksplat_level": 2})):
        path = tmp / f"base_{name}"
        write_gaussians(path, g if name != "splat" else _gaussians(degree=0), fmt, **kwargs)
        out[name] = path.read_bytes()
    out["spz3_raw"] = gzip.decompress(out["spz3"])          # a legacy payload without the gzip wrapper
    out["spz1"] = _spz_v1(_gaussians())
    for name, suffix, compression in (("glb", ".glb", "none"), ("gltf", ".gltf", "none"),
                                      ("glb_spz", ".glb", "spz")):
        path = tmp / f"base{suffix}"
        write_gaussians(path, _gaussians(), "gltf", gltf_compression=compression)
        out[name] = path.read_bytes()
    return out


def _nan_payload(name: str, data: bytearray, rng: np.random.Generator) -> bytearray:
    """Write NaN / Inf into a float field of the format (where the format has floats)."""
    bad = struct.pack("<f", [np.nan, np.inf, -np.inf][int(rng.integers(3))])
    if name == "splat":
        record = int(rng.integers(len(data) // 32))
        field = int(rng.integers(6))                    # x, y, z, sx, sy, sz
        data[record * 32 + 4 * field: record * 32 + 4 * field + 4] = bad
    elif name in ("compressed_ply", "ply"):
        start = data.index(b"end_header\n") + len(b"end_header\n")
        offset = start + 4 * int(rng.integers(18 if name == "compressed_ply" else 20))
        data[offset: offset + 4] = bad
    elif name == "spz1":
        offset = 16 + 2 * int(rng.integers(40 * 3))
        data[offset: offset + 2] = np.array([np.nan, np.inf][int(rng.integers(2))], "<f2").tobytes()
    elif name.startswith("ksplat"):                     # block size, SH range, or a record's float (2 bytes)
        offset = [4096 + 16, 36, 40, 5120 + 2 * int(rng.integers((len(data) - 5120) // 2))][int(rng.integers(4))]
        data[offset: offset + (4 if offset < 5120 else 2)] = (bad if offset < 5120 else
                                                              np.array([np.nan], "<f2").tobytes())
    return data


def _mutate(name: str, base: bytes, rng: np.random.Generator) -> bytes:
    kind = int(rng.integers(7))
    data = bytearray(base)
    gz = name in ("spz2", "spz3")
    if gz and kind in (2, 3, 4):                      # mutate the payload, then re-wrap it
        data = bytearray(gzip.decompress(base))
    if kind == 0:                                     # truncation
        data = data[: int(rng.integers(len(data)))]
    elif kind == 1:                                   # flipped bytes anywhere
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(len(data)))
            data[i] ^= int(rng.integers(1, 256))
    elif kind == 2:                                   # wrong counts / header fields
        if name in ("compressed_ply", "ply"):
            text = data[: data.index(b"end_header")].decode()
            words = text.split("\n")
            lines = [i for i, w in enumerate(words) if w.startswith("element")]
            i = lines[int(rng.integers(len(lines)))]
            parts = words[i].split()
            parts[2] = str(int(rng.choice([0, 1, 39, 41, 255, 257, 10**9, int(parts[2]) * 2])))
            words[i] = " ".join(parts)
            data = bytearray("\n".join(words).encode()) + data[data.index(b"end_header"):]
        elif name.startswith("spz"):
            field = int(rng.choice([4, 8, 12, 13, 15, 16] if name == "spz4" else [4, 8, 12, 13]))
            size = 4 if field in (4, 8, 16) else 1
            value = int(rng.choice([0, 1, 2, 5, 39, 41, 255, 2**20, 2**31 - 1])) % (256 ** size)
            data[field: field + size] = value.to_bytes(size, "little")
        elif name.startswith(("glb", "gltf")):        # accessor counts, types, offsets, indices in the JSON
            from seggaussian.tools.fuzz.splat import gltf_json_field

            data = bytearray(gltf_json_field(bytes(data), rng))
        elif name.startswith("ksplat"):               # main and section header counts, level, buckets, degree
            field, size = [(4, 4), (8, 4), (12, 4), (16, 4), (20, 2), (4096, 4), (4100, 4), (4108, 4), (4128, 4),
                           (4132, 4), (4136, 2)][int(rng.integers(11))]
            value = int(rng.choice([0, 1, 2, 3, 4, 39, 41, 255, 2**20, 2**31 - 1])) % (256 ** size)
            data[field: field + size] = value.to_bytes(size, "little")
        else:                                         # .splat has no count: drop or add a partial record
            data = data[:-int(rng.integers(1, 32))] if rng.random() < 0.5 else data + bytes(int(rng.integers(1, 32)))
    elif kind == 3:                                   # bad magic
        data[: 4] = bytes(rng.integers(0, 256, 4, dtype=np.uint8))
    elif kind == 4:                                   # NaN / Inf payload
        data = _nan_payload(name, data, rng)
    elif kind == 5:                                   # junk appended
        data = data + bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8))
    else:                                             # a random block overwritten
        i = int(rng.integers(len(data)))
        data[i: i + 16] = bytes(rng.integers(0, 256, len(data[i: i + 16]), dtype=np.uint8))
    if gz and kind in (2, 3, 4):
        data = bytearray(gzip.compress(bytes(data), mtime=0))
    return bytes(data)


def _classify(path: Path) -> str:
    try:
        g, _report, _fmt = read_gaussians(path)
    except PlyFormatError as exc:
        return "clean_error" if str(path) in str(exc) and "\n" not in str(exc) else f"unclear_error: {exc}"
    except Exception as exc:  # noqa: BLE001 - the point of the test: anything else is a crash
        return f"crash: {type(exc).__name__}: {exc}"
    arrays = [g.means, g.quats, g.log_scales, g.opacity_logits, g.sh]
    return "accepted" if all(np.isfinite(a).all() for a in arrays) else "crash: accepted non-finite values"


@pytest.mark.parametrize("name", ["splat", "compressed_ply", "spz1", "spz2", "spz3", "spz3_raw", "spz4", "ply",
                                  "ksplat0", "ksplat1", "ksplat2", "glb", "gltf", "glb_spz"])
def test_fuzz_gives_clear_errors_only(name, tmp_path):
    base = _base_files(tmp_path)[name]
    rng = np.random.default_rng(sum(map(ord, name)))  # seeded per format
    outcomes: Counter = Counter()
    problems = []
    for i in range(MUTANTS):
        path = tmp_path / f"mutant_{i:04d}.bin"
        path.write_bytes(_mutate(name, base, rng))
        outcome = _classify(path)
        outcomes[outcome.split(":")[0]] += 1
        if not outcome.startswith(("accepted", "clean_error")):
            problems.append(f"mutant {i}: {outcome}")
        path.unlink()
    assert not problems, f"{name}: {outcomes}\n" + "\n".join(problems[:10])
    assert outcomes["clean_error"] >= MUTANTS // 4, outcomes
    # the base file itself is accepted
    (tmp_path / "base.bin").write_bytes(base)
    assert _classify(tmp_path / "base.bin") == "accepted"


# ---------------------------------------------------------------------------------------------
# the same formats through the shared harness (seggaussian.tools.fuzz.engine: own-code, one-line and hang checks)
# ---------------------------------------------------------------------------------------------
#: Mutants per format through the harness.
HARNESS_MUTANTS = 400


@pytest.mark.parametrize("index", range(11))
def test_splat_formats_in_the_shared_fuzz_harness(index, tmp_path):
    from seggaussian.tools.fuzz import engine as fuzz
    from seggaussian.tools.fuzz.splat import splat_targets

    target = splat_targets(seed=0)[index]
    report = fuzz.run_fuzz(target, HARNESS_MUTANTS, seed=15, workdir=tmp_path)
    assert report.failures() == [], [f"{o.name}: {o.verdict}: {o.detail}" for o in report.failures()[:10]]
    counts = report.counts
    assert counts["clean_error"] >= HARNESS_MUTANTS // 4 and counts["accepted"] > 0, (target.name, counts)
    assert set(report.by_mutator()) == {name for name, _ in target.mutators}
    assert not list(tmp_path.iterdir())
