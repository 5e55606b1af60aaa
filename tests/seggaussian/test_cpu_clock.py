"""seggaussian.pipeline.records.CpuClock: nested parts are counted once, in their own name."""

from __future__ import annotations

import time

from seggaussian.pipeline.records import CpuClock


def _spin(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def test_nested_parts_are_left_out_of_the_enclosing_part_and_the_parts_add_up():
    clock = CpuClock()
    start = time.process_time()
    with clock.measure("outer"):
        _spin(0.03)
        with clock.measure("inner"):
            _spin(0.05)
        with clock.measure("inner"):  # a second visit adds to the first
            _spin(0.02)
    total = time.process_time() - start
    assert clock.seconds["inner"] >= 0.07
    assert 0.03 <= clock.seconds["outer"] < 0.07  # its own spin only, not the inner parts'
    assert abs(sum(clock.seconds.values()) - total) < 0.01
    assert set(clock.rounded()) == {"outer", "inner"}
