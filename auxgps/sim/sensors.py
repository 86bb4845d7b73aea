"""A simulated autopilot's telemetry along a flown trajectory, as the estimator's events (truth plus noise).

At each simulation step the autopilot reports what it would at its rates: an attitude and an IMU sample (at
``imu_rate_hz``), its height above home (the barometer, at ``baro_rate_hz``; home is the world's origin, on the
ground), and GPS1 (at ``gps_rate_hz``), which reaches it ``gps1_lag_s`` after its receiver measured it. From
``gps_denied_from_s`` on, GPS1 reports no fix (fix type 1, no satellites, no position), as a jammed receiver does.
With ``heading_error_deg`` set, the attitude's heading also carries a slowly wandering error (first-order
Gauss-Markov, drawn per run from its own generator, so the other streams are those of a run without it); with
``tilt_error_deg``, its roll and pitch too (each its own process, from a generator of their own).
"""

from __future__ import annotations

import numpy as np

from auxgps.core.events import Attitude, Gps1, Imu, Position
from auxgps.core.geometry import LocalFrame, body_rates_from_euler_rates, euler_step_rad
from auxgps.sim.flight import TelemetryNoiseConfig, Trajectory, sense_imu

NO_FIX = 1


class _Wander:
    """A first-order Gauss-Markov error of ``n`` axes: ``sigma_deg`` steady one sigma per axis, correlation time
    ``tau_s``, stepped every ``step_s``; rad. Its generator is seeded from ``rng`` (one draw), and its first value
    drawn from the steady distribution."""

    def __init__(self, rng: np.random.Generator, sigma_deg: float, tau_s: float, step_s: float, n: int) -> None:
        self._rng = np.random.default_rng(rng.integers(2**63))
        self._sigma_rad = np.deg2rad(sigma_deg)
        self._keep = float(np.exp(-step_s / tau_s))
        self._n = n
        self.value_rad = self._rng.standard_normal(n) * self._sigma_rad

    def step(self) -> np.ndarray:
        """Advance one step; the new error, rad (n,)."""
        k = self._keep
        self.value_rad = k * self.value_rad + np.sqrt(1.0 - k * k) * self._sigma_rad * self._rng.standard_normal(self._n)
        return self.value_rad


class Sensors:
    """The events of one trajectory, step by step (:meth:`events_at`), in the order the autopilot sends them."""

    def __init__(self, traj: Trajectory, frame: LocalFrame, noise: TelemetryNoiseConfig, *, rng_tel: np.random.Generator,
                 rng_imu: np.random.Generator, bias_body_m_s2: np.ndarray, gps1_lag_s: float, gps_denied_from_s: float = np.inf) -> None:
        self.traj, self.frame, self.noise = traj, frame, noise
        self.rng_tel, self.rng_imu, self.bias = rng_tel, rng_imu, bias_body_m_s2
        self.gps1_lag_s, self.gps_denied_from_s = gps1_lag_s, gps_denied_from_s
        dt = traj.t_s[1] - traj.t_s[0]
        every = lambda rate_hz: max(1, int(round(1.0 / (rate_hz * dt))))  # noqa: E731
        self.imu_every, self.baro_every, self.gps_every = every(noise.imu_rate_hz), every(noise.baro_rate_hz), every(noise.gps_rate_hz)
        self._gps_pending: list[Gps1] = []  # measured, not yet reached the autopilot
        # The autopilot's attitude errors that wander (heading; roll and pitch), each on its own generator drawn
        # from the IMU's, so that turning one on leaves every other draw as it was.
        step_s = self.imu_every * dt
        self._heading_error = _Wander(rng_imu, noise.heading_error_deg, noise.heading_error_tau_s, step_s, 1) \
            if noise.heading_error_deg > 0 else None
        self._tilt_error = _Wander(rng_imu, noise.tilt_error_deg, noise.tilt_error_tau_s, step_s, 2) \
            if noise.tilt_error_deg > 0 else None

    def _rates_body(self, i: int) -> np.ndarray:
        """The body's true rates (p, q, r) at step ``i``, rad/s, as the autopilot's gyros report them."""
        traj = self.traj
        j = min(i + 1, len(traj.t_s) - 1)
        k = j - 1 if j > 0 else 0
        if j == k:
            return np.zeros(3)
        d_euler = euler_step_rad(traj.euler_rad[k], traj.euler_rad[j])
        return body_rates_from_euler_rates(traj.euler_rad[k], d_euler / (traj.t_s[j] - traj.t_s[k]))

    def events_at(self, i: int) -> list:
        """What the autopilot sends at step ``i``: attitude before the IMU sample it rotates; GPS1 readings whose
        lag has passed."""
        traj, noise, out = self.traj, self.noise, []
        t = float(traj.t_s[i])
        if i % self.imu_every == 0:
            t_imu, f_body, euler = sense_imu(traj, i, noise, self.bias, self.rng_imu)
            if self._heading_error is not None:
                euler = euler + np.array([0.0, 0.0, *self._heading_error.step()])
            if self._tilt_error is not None:
                euler = euler + np.array([*self._tilt_error.step(), 0.0])
            out += [Attitude(t_imu, euler, self._rates_body(i)), Imu(t_imu, f_body)]
        if i % self.baro_every == 0:
            alt = -traj.p_ned_m[i, 2] + noise.altitude_m * self.rng_tel.standard_normal()
            out.append(Position(t, np.nan, np.nan, np.nan, float(alt)))
        if i % self.gps_every == 0:
            self._gps_pending.append(self._gps1(i, t + self.gps1_lag_s))
        while self._gps_pending and self._gps_pending[0].t_s <= t + 1e-9:
            out.append(self._gps_pending.pop(0))
        return out

    def _gps1(self, i: int, t_arrival_s: float) -> Gps1:
        noise = self.noise
        if self.traj.t_s[i] >= self.gps_denied_from_s:
            return Gps1(t_arrival_s, NO_FIX, 0, 0.0, 0.0, 0.0, 99.0)
        sig = np.array([noise.gps_horizontal_m, noise.gps_horizontal_m, noise.gps_vertical_m])
        p = self.traj.p_ned_m[i] + self.rng_tel.standard_normal(3) * sig
        lat, lon, alt = self.frame.to_geodetic(p)
        return Gps1(t_arrival_s, 3, 12, float(lat), float(lon), float(alt), max(noise.gps_horizontal_m, 0.01))
