"""CPU seconds of the named parts of a piece of work (every thread of this process: ``time.process_time``).

Parts nest: a part measured inside another is counted in its own name and left out of the enclosing one, so the
parts add up to the CPU time spent inside the outermost ones.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator


class CpuClock:
    """CPU seconds per named part (``seconds``); ``measure(name)`` times one part, nested parts excluded."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._inner: list[float] = []  # per open part: CPU seconds of the parts nested in it

    @contextmanager
    def measure(self, name: str) -> Iterator[None]:
        start = time.process_time()
        self._inner.append(0.0)
        try:
            yield
        finally:
            spent = time.process_time() - start
            nested = self._inner.pop()
            self.seconds[name] = self.seconds.get(name, 0.0) + spent - nested
            if self._inner:
                self._inner[-1] += spent

    def rounded(self, digits: int = 3) -> dict[str, float]:
        """``seconds`` rounded (for records and JSON)."""
        return {name: round(value, digits) for name, value in self.seconds.items()}


@contextmanager
def measured(clock: CpuClock | None, name: str) -> Iterator[None]:
    """``clock.measure(name)``, or nothing when ``clock`` is None."""
    if clock is None:
        yield
    else:
        with clock.measure(name):
            yield
