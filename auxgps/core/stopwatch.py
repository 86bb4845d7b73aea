"""Instrumentation hooks of the core: stages a benchmark may time. The core itself reads no clock.

A stopwatch is called with a stage name and returns a context manager (``with stopwatch("matching"): ...``). The
default times nothing; ``auxgps bench`` passes one that reads a clock (:class:`auxgps.evaluation.bench.StageClock`).
"""

from __future__ import annotations


class _NullStopwatch:
    """Times nothing."""

    def __call__(self, stage: str) -> "_NullStopwatch":
        return self

    def __enter__(self) -> "_NullStopwatch":
        return self

    def __exit__(self, *exc) -> None:
        return None


null_stopwatch = _NullStopwatch()
