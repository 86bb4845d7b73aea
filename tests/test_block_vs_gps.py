"""tools/block_vs_gps.py: the similarity and the GPS time offset, on tracks whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import load_tool

bg = load_tool("block_vs_gps")


def _serpentine(n_lines=4, per_line=12, step_s=4.0, speed_m_s=10.0, spacing_m=40.0):
    """Capture times and true positions (north, east) of a lawnmower flown both ways, turns included."""
    t, p = [], []
    for k in range(n_lines):
        east = k * spacing_m
        norths = np.arange(per_line) * step_s * speed_m_s
        for j, n in enumerate(norths if k % 2 == 0 else norths[::-1]):
            t.append(len(t) * step_s)
            p.append((n, east))
    return np.array(t, float), np.array(p, float)


def test_a_late_gps_is_found_as_its_time_offset():
    t, truth = _serpentine()
    v = np.gradient(truth, t, axis=0)
    lag_s = 0.3
    gps = truth + v * lag_s + np.array([0.4, -0.2])  # taken 0.3 s after the exposure, and a constant offset
    dt, c, left = bg.gps_lag(truth - gps, gps, t)
    assert dt == pytest.approx(lag_s, abs=0.02)
    np.testing.assert_allclose(c, [-0.4, 0.2], atol=0.05)
    assert np.sqrt(np.mean(left**2)) < 0.1


def test_the_similarity_gives_the_blocks_scale_and_turn():
    _, truth = _serpentine()
    turn = np.deg2rad(0.5)
    R = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    moved = 0.984 * truth @ R.T + [3.0, -1.0]
    scale, got_turn, res = bg.similarity(truth, moved)
    assert scale == pytest.approx(-0.016, abs=1e-9)
    assert got_turn == pytest.approx(turn, abs=1e-9)
    assert np.max(np.abs(res)) < 1e-9
