"""The GPS_INPUT timer's stall report: every thread's stack, written as the stall happens."""

import time

import pytest

from auxgps.companion import StallWatch

pytestmark = pytest.mark.realtime  # against the wall clock


def _held_up(seconds: float) -> None:
    time.sleep(seconds)


def test_a_timer_held_up_past_its_limit_writes_where_every_thread_was(tmp_path):
    watch = StallWatch(tmp_path / "stalls.txt", timeout_s=0.5)
    try:
        for _ in range(20):  # ticking in time: nothing written
            watch.tick()
            time.sleep(0.02)
        assert not watch.wrote()
        watch.tick()
        _held_up(1.2)
        assert watch.wrote()
        assert not watch.wrote()  # each stall is told once
        text = (tmp_path / "stalls.txt").read_text()
        assert "Timeout" in text and "in _held_up" in text, text
    finally:
        watch.close()
    watch = StallWatch(tmp_path / "stalls.txt", timeout_s=0.3)  # a new watch judges only what it writes itself
    watch.close()
    assert not watch.wrote()

