"""The simulated autopilot's telemetry: the heading and tilt errors that wander (a compass-aided EKF's), when asked
for."""

from __future__ import annotations

import numpy as np

from auxgps.config import parse_as
from auxgps.core.events import Attitude
from auxgps.core.geometry import LocalFrame
from auxgps.sim.flight import TelemetryNoiseConfig, Trajectory
from auxgps.sim.sensors import Sensors


def _hover(duration_s: float = 300.0, dt_s: float = 0.01) -> Trajectory:
    t = np.arange(0.0, duration_s, dt_s)
    z = np.zeros((len(t), 3))
    p = z.copy()
    p[:, 2] = -30.0
    return Trajectory(t, p, z, z, z.copy())


def _headings(noise: TelemetryNoiseConfig, seed: int, axis: int = 2) -> np.ndarray:
    traj = _hover()
    rng = np.random.default_rng(seed)
    s = Sensors(traj, LocalFrame(47.0, 8.0, 400.0), noise, rng_tel=np.random.default_rng(rng.integers(2**63)),
                rng_imu=np.random.default_rng(rng.integers(2**63)), bias_body_m_s2=np.zeros(3), gps1_lag_s=0.1)
    out = [e.euler_rad[axis] for i in range(len(traj.t_s)) for e in s.events_at(i) if isinstance(e, Attitude)]
    return np.degrees(np.array(out))


def test_the_heading_error_wanders_with_its_sigma_and_correlation_time_and_is_off_by_default():
    white = parse_as(TelemetryNoiseConfig, {"heading_deg": 0.0}, "test")
    assert np.all(_headings(white, 1) == 0.0)  # no heading error asked for: none
    drift = parse_as(TelemetryNoiseConfig, {"heading_deg": 0.0, "heading_error_deg": 1.5, "heading_error_tau_s": 10.0}, "test")
    runs = np.array([_headings(drift, seed) for seed in range(8)])  # (runs, samples at 100 Hz over 300 s)
    assert 1.2 < np.std(runs) < 1.8  # its stationary sigma
    lag = 1000  # 10 s: one correlation time
    c = np.mean(runs[:, :-lag] * runs[:, lag:]) / np.mean(runs**2)
    assert 0.2 < c < 0.55, c  # exp(-1) = 0.37
    step = np.abs(np.diff(runs, axis=1)).max()
    assert step < 0.4  # it wanders (white noise of 1.5 deg would jump 5 deg from sample to sample)


def test_the_tilt_error_wanders_per_axis_with_its_sigma_and_correlation_time_and_is_off_by_default():
    white = parse_as(TelemetryNoiseConfig, {"attitude_deg": 0.0}, "test")
    assert np.all(_headings(white, 1, axis=0) == 0.0) and np.all(_headings(white, 1, axis=1) == 0.0)
    drift = parse_as(TelemetryNoiseConfig, {"attitude_deg": 0.0, "tilt_error_deg": 0.09, "tilt_error_tau_s": 7.0}, "test")
    for axis in (0, 1):
        runs = np.array([_headings(drift, seed, axis) for seed in range(8)])
        assert 0.07 < np.std(runs) < 0.11  # its stationary sigma
        lag = 700  # 7 s: one correlation time
        c = np.mean(runs[:, :-lag] * runs[:, lag:]) / np.mean(runs**2)
        assert 0.2 < c < 0.55, c
        assert np.abs(np.diff(runs, axis=1)).max() < 0.03  # it wanders, it does not jump
    roll, pitch = _headings(drift, 3, 0), _headings(drift, 3, 1)
    assert abs(np.corrcoef(roll, pitch)[0, 1]) < 0.5  # each axis its own process
