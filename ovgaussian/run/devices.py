"""The compute device a training, benchmark or prediction runs on, checked before any work starts."""

from __future__ import annotations

import torch

DEVICES = ("cpu", "cuda")


def resolve_device(name: str) -> torch.device:
    """``torch.device(name)`` for ``cpu`` or ``cuda``; a one-line ``ValueError`` when CUDA is asked for but this
    torch build or machine has none (instead of torch's error deep inside the first ``.to``)."""
    if name not in DEVICES:
        raise ValueError(f"--device {name!r}: expected one of {', '.join(DEVICES)}")
    if name == "cuda" and not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
        raise ValueError(f"--device cuda: no usable CUDA device (torch {torch.__version__}, {build}); "
                         "use --device cpu or install a CUDA build of torch on a GPU machine")
    return torch.device(name)
