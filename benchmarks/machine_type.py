"""Which CPU type a benchmark runs on, so that a wall-time budget can match it.

A wall-time figure measured on one CPU type does not hold on another: the paper-scale training step takes
18.6-19.4 s on the 2-core AMD EPYC Zen 4 machines and 22.6-25.7 s on the 2-core Zen 3 ones (BENCHMARKS.md,
"Training"). A budget script looks its machine up here and takes the budget of that type; a type it has no figure
for gets the slowest known budget and is reported, never failed, on wall time. Budgets that are ratios or memory
do not depend on the type and stay as they are.

The type is read from ``/proc/cpuinfo`` (vendor, family, model and model name of the first CPU): AMD family 25
(0x19) is Zen 3 for models 0x00-0x0f and 0x20-0x5f, Zen 4 for 0x10-0x1f, 0x60-0x7f and 0xa0-0xaf; AMD family 23
(0x17) is Zen or Zen+ for models 0x00-0x2f and Zen 2 from 0x30 (BENCHMARKS.md's "EPYC family 23" type, model 1,
is Zen: slower than Zen 3, and no budget here is its own, so its wall times are reported, not enforced).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

ZEN1 = "zen1"  # Zen and Zen+ (AMD family 23 before model 0x30)
ZEN2 = "zen2"
ZEN3 = "zen3"
ZEN4 = "zen4"
UNKNOWN = "unknown"


@dataclass(frozen=True)
class MachineType:
    """A CPU type: ``kind`` is ``zen1``, ``zen2``, ``zen3``, ``zen4`` or ``unknown``; ``label`` names the CPU and its
    cores."""

    kind: str
    model_name: str
    vendor: str
    family: int | None
    model: int | None
    cores: int

    @property
    def known(self) -> bool:
        return self.kind != UNKNOWN

    @property
    def label(self) -> str:
        names = {ZEN1: "AMD EPYC Zen (family 23)", ZEN2: "AMD EPYC Zen 2", ZEN3: "AMD EPYC Zen 3",
                 ZEN4: "AMD EPYC Zen 4"}
        name = names.get(self.kind, self.model_name or "unknown CPU")
        return f"{name}, {self.cores} cores"


def _first_cpu(text: str) -> dict[str, str]:
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            if fields:
                break
            continue
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return fields


def _int(value: str | None) -> int | None:
    try:
        return int(value, 0) if value is not None else None
    except ValueError:
        return None


def classify(vendor: str, family: int | None, model: int | None) -> str:
    """The kind of a CPU from its vendor id and its family and model numbers."""
    if vendor == "AuthenticAMD" and family == 25 and model is not None:
        if model <= 0x0F or 0x20 <= model <= 0x5F:
            return ZEN3
        if 0x10 <= model <= 0x1F or 0x60 <= model <= 0x7F or 0xA0 <= model <= 0xAF:
            return ZEN4
    if vendor == "AuthenticAMD" and family == 23 and model is not None:
        return ZEN1 if model < 0x30 else ZEN2
    return UNKNOWN


def parse_cpuinfo(text: str, cores: int | None = None) -> MachineType:
    """The machine type described by the text of ``/proc/cpuinfo``."""
    cpu = _first_cpu(text)
    vendor = cpu.get("vendor_id", "")
    family, model = _int(cpu.get("cpu family")), _int(cpu.get("model"))
    count = cores if cores is not None else sum(1 for line in text.splitlines() if line.startswith("processor"))
    return MachineType(classify(vendor, family, model), cpu.get("model name", ""), vendor, family, model,
                       count or (os.cpu_count() or 0))


def detect(cpuinfo: Path = Path("/proc/cpuinfo")) -> MachineType:
    """This machine's type; ``unknown`` where ``/proc/cpuinfo`` cannot be read."""
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:
        return MachineType(UNKNOWN, "", "", None, None, os.cpu_count() or 0)
    return parse_cpuinfo(text, os.cpu_count())


def budget_for(machine: MachineType, budgets: dict[str, float]) -> tuple[float, bool]:
    """The budget of ``machine``'s type out of ``budgets`` (kind -> value), and whether it is enforced.

    A known type gets its own budget, enforced. Any other type gets the largest (slowest) budget, not enforced:
    the figure is reported against it and does not fail the run."""
    if machine.kind in budgets:
        return budgets[machine.kind], True
    return max(budgets.values()), False
