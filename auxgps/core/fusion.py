"""Fusion of visual fixes with the autopilot's IMU and attitude: an extended Kalman filter on filterpy.

State (15): position NED (m), velocity NED (m/s), accelerometer bias in the body frame (m/s^2), the north/east
error that visual fixes share (m), the north/east offset of a prior map (m), and the north/east acceleration the
autopilot's tilt error leaves out (m/s^2). Between fixes the
filter is driven by the IMU: specific force minus the bias, rotated by the attitude, plus gravity. The bias is
estimated because a tenth of a m/s^2 left in the specific force, integrated over a few seconds without a fix,
is metres; it is observable from the fixes as soon as the vehicle turns. The autopilot's attitude is off by a
tilt that wanders (ArduCopter SITL's EKF: 0.1 to 0.4 degrees, changing leg by leg), and the specific force
rotated by it leaves g times that tilt of horizontal acceleration (0.01 to 0.04 m/s^2 over 10 s) in the NED frame:
a body-frame bias cannot hold it through a turn (learnt on one leg, it is twice wrong after a U-turn), so it is
its own first-order Gauss-Markov state (``tilt_error_deg``, ``tilt_error_tau_s``). Without it a filter dead
reckoning ten seconds of a survey's turns drifted metres while reporting a few decimetres. GPS1 readings do not
teach it (a "consider" update: they are widened by it, but their gain on it is zero), or a slowly dragged GPS1
would be followed as an acceleration; visual fixes do. The shared fix error is what does not
average out over frames: an error in the autopilot's attitude that lasts seconds (0.3 degrees is 8 cm at 15 m)
and the map's own errors. Fusing twenty fixes a second as if their errors were independent would make the filter
believe itself to a centimetre, gate out good fixes and report an accuracy that the truth does not bear out; as a
first-order Gauss-Markov state it keeps the reported accuracy honest. GPS1 readings do not share it.

A prior map (an orthophoto's) is placed on Earth only as well as the orthophoto is: an offset shared by its
landmarks near each other, which changes across the map (a mosaic's scale and turn are off as well as its
place). It is a state of the map's stated placement error (``map_offset_sigma_m``), correlated over
``prior_map_offset_length_m`` of distance flown (first-order Gauss-Markov in distance), seen by a fix in the
share of its inliers that are the prior map's: the filter learns it from the first prior-map fixes after GPS1 is
lost (while the IMU still holds the position GPS1 gave), forgets it as the vehicle flies on, and never makes
the fixes surer than it.

Every input is stamped with the time it describes, and any may arrive late (a visual fix a frame's processing
after its capture, GPS1 its receiver's lag after its measurement). The filter keeps a short history of every step
it took (IMU propagations, accepted updates, re-initialisations) with the state after each; a late measurement
rolls the state back to its time, is applied there, and every later step is taken again in time order, so the
result is the one the inputs would have given in time order, whatever their arrival order (PX4's EKF2 fuses at a
delayed horizon for the same reason). A replayed update keeps the gate decision it had. A measurement between two
IMU samples is compared with the state at the earlier one carried forward by its velocity. Each fix is
gated on its innovation (squared Mahalanobis distance against a chi-square threshold); when the gate keeps
rejecting a run of fixes that agree with each other, the filter itself has drifted and is re-initialised on them.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from auxgps.core.localise import PositionPrior

log = logging.getLogger(__name__)

GRAVITY_NED_M_S2 = np.array([0.0, 0.0, 9.80665])
_N = 15
_I3 = np.arange(3)  # diagonal indices of a 3 x 3 block
_I2 = np.arange(2)
_EYE3 = np.eye(3)


def _H_ne(dt_s: float, visual: bool, prior_share: float = 0.0) -> np.ndarray:
    """(2, 13) horizontal position ``dt_s`` after the state's time (carried by its velocity); a visual fix also
    sees the shared fix error, and the prior map's offset in the share of its inliers from it."""
    H = np.zeros((2, _N))
    H[_I2, _I2] = 1.0
    H[_I2, _I2 + 3] = dt_s
    if visual:
        H[_I2, _I2 + 9] = 1.0
        H[_I2, _I2 + 11] = prior_share
    return H


def _H_down(dt_s: float) -> np.ndarray:
    """(1, 13) down position ``dt_s`` after the state's time."""
    H = np.zeros((1, _N))
    H[0, 2], H[0, 5] = 1.0, dt_s
    return H


@dataclass(frozen=True)
class _Step:
    """One step the filter took, kept for replay after a late measurement.

    ``t_s``: the time the step describes (its order in the history); ``t_state_s``: the state's time after it (the
    last IMU sample's); ``kind``: "imu", "position", "altitude", "reinit", "offset", "gap" or "loosen"; ``data``:
    what re-applies it. ``x``, ``P``: the state after it.
    """

    t_s: float
    t_state_s: float
    kind: str
    data: tuple
    x: np.ndarray
    P: np.ndarray


@dataclass(frozen=True)
class ImuSample:
    """One IMU sample: capture time (s), specific force in the body frame (m/s^2), attitude (body -> NED)."""

    t_s: float
    f_body_m_s2: np.ndarray
    R_ned_body: np.ndarray


@dataclass(frozen=True)
class FusedEstimate:
    """The filter's output at ``t_s``: position (m), velocity (m/s) and their covariances, NED."""

    t_s: float
    p_ned_m: np.ndarray
    v_ned_m_s: np.ndarray
    cov_p_m2: np.ndarray
    cov_v_m2_s2: np.ndarray

    @property
    def sigma_h_worst_m(self) -> float:
        """Horizontal one-sigma along the worst axis, m (what GPS_INPUT's horiz_accuracy says)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.cov_p_m2[:2, :2])[-1]))

    @property
    def sigma_v_m(self) -> float:
        return float(np.sqrt(self.cov_p_m2[2, 2]))

    @property
    def sigma_speed_m_s(self) -> float:
        return float(np.sqrt(np.linalg.eigvalsh(self.cov_v_m2_s2)[-1]))


@dataclass(frozen=True)
class GateDecision:
    """What the filter did with one fix. ``mahalanobis2`` is the squared distance of its innovation;
    ``rejected_run``: the fix ended a run of consistent rejected fixes (the filter re-initialised on it, if allowed)."""

    t_s: float
    accepted: bool
    mahalanobis2: float
    reason: str
    rejected_run: bool = False
    fix_sigma_m: float = np.nan  # the fix's one sigma as offered (RMS per axis), m
    filter_sigma_m: float = np.nan  # the filter's one sigma of what the fix measures, before it (RMS per axis), m


class NavFilter:
    """Position, velocity and accelerometer-bias EKF. ``cfg`` is a :class:`auxgps.config.FusionConfig`."""

    def __init__(self, cfg, t_s: float, p_ned_m: np.ndarray, v_ned_m_s: np.ndarray, sigma_p_m: float, sigma_v_m_s: float,
                 map_offset_sigma_m: float = 0.0) -> None:
        self.cfg = cfg
        self.map_offset_sigma_m = float(map_offset_sigma_m)
        self._map_heading_sigma_m = 0.0  # see set_map_heading_sigma
        self._ekf = ExtendedKalmanFilter(dim_x=_N, dim_z=2)
        self._ekf.x = np.concatenate([p_ned_m, v_ned_m_s, np.zeros(9)]).reshape(_N, 1).astype(float)
        self._ekf.P = np.diag([sigma_p_m**2] * 3 + [sigma_v_m_s**2] * 3 + [cfg.accel_bias_sigma_m_s2**2] * 3
                              + [self.fix_bias_sigma_m**2] * 2 + [self.map_offset_sigma_m**2] * 2
                              + [self.tilt_accel_sigma_m_s2**2] * 2)
        self.t_s = float(t_s)
        # Every step taken, in time order, the state after each; the first is the state it started from.
        self._history: list[_Step] = [_Step(self.t_s, self.t_s, "start", (), self._ekf.x.copy(), self._ekf.P.copy())]
        self._rejected_run: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.n_accepted = 0
        self.n_rejected = 0
        self.n_reinit = 0
        self.n_bad_imu = 0
        self.n_replayed = 0  # steps taken again after a late measurement
        self._last_imu_t = -np.inf

    # -- inputs --------------------------------------------------------------------------------------------

    def propagate(self, imu: ImuSample) -> bool:
        """Advance to ``imu.t_s`` with this sample. A NaN, out-of-range or out-of-order sample is refused."""
        problem = self._check_imu(imu)
        if problem:
            self.n_bad_imu += 1
            log.warning("IMU sample at t=%.3f s rejected: %s", imu.t_s, problem)
            return False
        if imu.t_s - self._last_imu_t > self.cfg.max_imu_gap_s and np.isfinite(self._last_imu_t):
            log.warning("no IMU sample for %.2f s: carried at constant velocity, covariance loosened", imu.t_s - self._last_imu_t)
        self._last_imu_t = imu.t_s
        later = self._rewind(imu.t_s)  # empty unless a measurement stamped after this sample was fused already
        self._take("imu", imu.t_s, (imu,))
        self._retake(later or [])
        return True

    def update_position(self, t_s: float, p_ne_m: np.ndarray, cov_ne_m2: np.ndarray, visual: bool = False,
                        reinit: bool = True, prior_share: float = 0.0) -> GateDecision:
        """Fuse a horizontal position fix captured at ``t_s`` (up to ``history_s`` ago). A ``visual`` fix carries
        the error all visual fixes share (see the module's docstring), and ``prior_share`` (0 to 1) of the prior
        map's offset; a GPS reading neither. Without ``reinit``, a run of consistent rejected fixes is reported
        (``rejected_run``) but the filter stays where it is."""
        prior_share = float(np.clip(prior_share, 0.0, 1.0)) if visual and self.map_offset_sigma_m > 0 else 0.0
        t_s = float(t_s)
        p_ne_m = np.asarray(p_ne_m, float).reshape(2)
        cov_ne_m2 = np.asarray(cov_ne_m2, float).reshape(2, 2)
        if not (np.isfinite(t_s) and np.all(np.isfinite(p_ne_m)) and np.all(np.isfinite(cov_ne_m2))):
            return self._decide(GateDecision(t_s, False, np.nan, "fix is not finite"))
        later = self._rewind(t_s)
        if later is None:
            return self._decide(GateDecision(t_s, False, np.nan, f"fix {self.t_s - t_s:.3f} s old, older than the history"))
        self._carry_to(float(t_s))
        H = _H_ne(t_s - self.t_s, visual, prior_share)
        cov_pred_m2 = H @ self._ekf.P @ H.T
        S = cov_pred_m2 + cov_ne_m2
        y = p_ne_m - (H @ self._ekf.x)[:, 0]
        m2 = float(y @ np.linalg.solve(S, y))
        sigmas = dict(fix_sigma_m=float(np.sqrt(np.trace(cov_ne_m2) / 2.0)), filter_sigma_m=float(np.sqrt(np.trace(cov_pred_m2) / 2.0)))
        ratio = self.cfg.max_fix_sigma_ratio
        if visual and ratio > 0 and sigmas["fix_sigma_m"] > ratio * sigmas["filter_sigma_m"]:
            decision = GateDecision(t_s, False, m2, f"too wide to help: sigma {sigmas['fix_sigma_m']:.3f} m, the filter's "
                                                    f"{sigmas['filter_sigma_m']:.3f} m", **sigmas)
        elif m2 <= self.cfg.gate_chi2:
            self._take("position", t_s, (p_ne_m, cov_ne_m2, visual, prior_share))
            self._rejected_run.clear()
            decision = GateDecision(t_s, True, m2, "accepted", **sigmas)
        else:
            decision = GateDecision(t_s, False, m2, f"innovation {np.sqrt(m2):.1f} sigma", **sigmas)
            self._rejected_run.append((t_s, p_ne_m, cov_ne_m2, prior_share))
            if self._rejected_run_agrees(self.cfg.reinit_min_span_s if visual else 0.0):
                self._rejected_run.clear()
                if reinit:
                    self._take("reinit", t_s, (p_ne_m, cov_ne_m2, prior_share))
                    self.n_reinit += 1
                    log.warning("filter re-initialised at t=%.3f s on %d consistent rejected fixes", t_s, self.cfg.reinit_count)
                    decision = GateDecision(t_s, False, m2, "re-initialised on a run of consistent rejected fixes", True, **sigmas)
                else:
                    decision = GateDecision(t_s, False, m2, "a run of consistent rejected fixes (not re-initialised)", True, **sigmas)
        self._retake(later)
        return self._decide(decision)

    def loosen(self, t_s: float, cov_p_ne_m2: np.ndarray, cov_v_ne_m2_s2: np.ndarray) -> bool:
        """Add these covariances to the horizontal position and velocity at ``t_s``: what the filter has learnt
        from a source found wrong since (GPS1 dragged, by as much as the map says). False if ``t_s`` is older
        than the history."""
        cov_p, cov_v = np.asarray(cov_p_ne_m2, float).reshape(2, 2), np.asarray(cov_v_ne_m2_s2, float).reshape(2, 2)
        if not (np.all(np.isfinite(cov_p)) and np.all(np.isfinite(cov_v))):
            return False
        return self._take_in_order("loosen", float(t_s), (cov_p, cov_v))

    def learn_map_offset(self, t_s: float, p_ne_m: np.ndarray, cov_ne_m2: np.ndarray, prior_share: float) -> bool:
        """While GPS1 holds the position: a visual fix with ``prior_share`` of its inliers from the prior map says
        how far the prior map is off here. Updates the prior-map offset alone (the position stays GPS1's): its
        innovation against the filter's position, the fix's, the position's and the shared fix error's variance."""
        share = float(np.clip(prior_share, 0.0, 1.0))
        if self.map_offset_sigma_m <= 0 or share <= 0 or not (np.all(np.isfinite(p_ne_m)) and np.all(np.isfinite(cov_ne_m2))):
            return False
        return self._take_in_order("offset", float(t_s), (np.asarray(p_ne_m, float).reshape(2), np.asarray(cov_ne_m2, float).reshape(2, 2), share))

    def _learn_offset(self, t_s: float, p_ne_m: np.ndarray, cov_ne_m2: np.ndarray, share: float) -> None:
        x, P = self._ekf.x, self._ekf.P
        dt = t_s - self.t_s
        p_now = x[0:2, 0] + x[3:5, 0] * dt
        y = p_ne_m - p_now - x[9:11, 0] - share * x[11:13, 0]
        Pb = P[11:13, 11:13]
        S = share**2 * Pb + cov_ne_m2 + P[0:2, 0:2] + P[9:11, 9:11]
        if share * np.sqrt(np.trace(Pb) / 2.0) < 0.05 or y @ np.linalg.solve(S, y) > self.cfg.gate_chi2:
            return  # nothing left to learn, or a fix that disagrees (a wrong match, a drag): not taken
        K = share * Pb @ np.linalg.inv(S)
        x[11:13, 0] += K @ y
        P[11:13, 11:13] = Pb - share * K @ Pb
        P[11:13, :11] = P[:11, 11:13].T  # cross terms kept as they were (the position is GPS1's)

    def update_altitude(self, t_s: float, alt_above_origin_m: float, sigma_m: float) -> bool:
        """Fuse a barometric height above the origin (m) measured at ``t_s`` (up to ``history_s`` ago)."""
        t_s = float(t_s)
        if not (np.isfinite(t_s) and np.isfinite(alt_above_origin_m) and np.isfinite(sigma_m) and sigma_m > 0):
            log.warning("altitude sample at t=%.3f s rejected: not finite", t_s)
            return False
        if not self._take_in_order("altitude", t_s, (float(alt_above_origin_m), float(sigma_m))):
            log.warning("altitude sample at t=%.3f s rejected: older than the history", t_s)
            return False
        return True

    # -- outputs -------------------------------------------------------------------------------------------

    def map_offset(self) -> tuple[np.ndarray, np.ndarray]:
        """The prior map's offset as the filter holds it: north/east (2,) m and covariance (2, 2) m^2."""
        return self._ekf.x[11:13, 0].copy(), self._ekf.P[11:13, 11:13].copy()

    def estimate(self) -> FusedEstimate:
        x, P = self._ekf.x[:, 0], self._ekf.P
        return FusedEstimate(self.t_s, x[:3].copy(), x[3:6].copy(), P[:3, :3].copy(), P[3:6, 3:6].copy())

    def estimate_at(self, t_s: float) -> FusedEstimate:
        """The estimate at ``t_s`` (s), at most ``history_s`` back: the state after the last step not later
        than ``t_s``, carried to ``t_s`` by its velocity. What GPS_INPUT sends when the autopilot is told its GPS
        lags by a fixed delay (``GPS2_DELAY_MS``): the vehicle at that moment, not at the last IMU sample."""
        t_s = float(t_s)
        k = self._last_not_after(t_s)
        step = self._history[max(k, 0)]
        t_k, x, P = step.t_state_s, step.x[:, 0], step.P
        dt = t_s - t_k
        P_pv = P[:3, 3:6]
        P_p, P_v = P[:3, :3] + (P_pv + P_pv.T) * dt + P[3:6, 3:6] * dt * dt, P[3:6, 3:6].copy()
        if dt > self.cfg.max_imu_gap_s:  # no IMU this long (a link outage, no attitude): an unknown acceleration too
            q_pp, _, q_vv = self._gap_noise(dt)
            P_p, P_v = P_p + _EYE3 * q_pp, P_v + _EYE3 * q_vv
        return FusedEstimate(t_s, x[:3] + x[3:6] * dt, x[3:6].copy(), P_p, P_v)

    def prior(self, t_s: float | None = None) -> PositionPrior:
        """Where the vehicle is at ``t_s`` (default: the state's time), for the localiser's search."""
        est = self.estimate() if t_s is None else self.estimate_at(t_s)
        return PositionPrior(est.p_ned_m, est.sigma_h_worst_m)

    @property
    def accel_bias_body_m_s2(self) -> np.ndarray:
        return self._ekf.x[6:9, 0].copy()

    # -- internals -----------------------------------------------------------------------------------------

    def _check_imu(self, imu: ImuSample) -> str:
        f = np.asarray(imu.f_body_m_s2, float)
        R = np.asarray(imu.R_ned_body, float)
        if not np.isfinite(imu.t_s) or imu.t_s <= self._last_imu_t:
            return f"time {imu.t_s} is not after the previous sample's {self._last_imu_t}"
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            return "specific force is not 3 finite numbers"
        if np.linalg.norm(f) > self.cfg.max_specific_force_m_s2:
            return f"specific force {np.linalg.norm(f):.1f} m/s^2 is out of range"
        # np.allclose(R @ R.T, I, atol=1e-3), written out: this runs at the IMU rate.
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.all(np.abs(R @ R.T - _EYE3) <= 1e-3 + 1e-5 * _EYE3):
            return "attitude is not a finite rotation"
        return ""

    def _predict(self, imu: ImuSample) -> None:
        dt = imu.t_s - self.t_s
        if dt <= 0:
            return
        cfg = self.cfg
        if dt > cfg.max_imu_gap_s:
            self._carry_across_gap(imu.t_s)
            return
        R = imu.R_ned_body
        # F, B and Q are written entry by entry into zeros and an identity (the same numbers as sums of scaled
        # identity blocks, a few times faster: this runs at the IMU rate, and again for every sample replayed
        # after a late fix).
        F = np.eye(_N)
        F[_I3, _I3 + 3] = dt
        F[0:3, 6:9] = -0.5 * R * dt * dt
        F[3:6, 6:9] = -R * dt
        B = np.zeros((_N, 3))
        B[_I3, _I3] = 0.5 * dt * dt
        B[_I3 + 3, _I3] = dt
        F[_I2, _I2 + 13] = 0.5 * dt * dt
        F[_I2 + 3, _I2 + 13] = dt
        u = (R @ imu.f_body_m_s2 + GRAVITY_NED_M_S2).reshape(3, 1)
        q = cfg.accel_noise_m_s2_sqrt_hz**2  # white acceleration noise, continuous-time
        Q = np.zeros((_N, _N))
        Q[_I3, _I3] = q * dt**3 / 3.0
        Q[_I3, _I3 + 3] = Q[_I3 + 3, _I3] = q * dt**2 / 2.0
        Q[_I3 + 3, _I3 + 3] = q * dt
        self._slow_states(F, Q, dt)
        self._ekf.F, self._ekf.B, self._ekf.Q = F, B, Q
        self._ekf.predict(u)
        self.t_s = imu.t_s

    def _update_considering_tilt(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        """A GPS reading's update that leaves the tilt's acceleration as it was (a Schmidt, or "consider", update:
        its gain on the state is zero; Joseph form, right for any gain). The tilt still widens the position and
        velocity between readings, as it does, but GPS1 does not teach it: taught, it let the filter follow a
        slowly dragged GPS1 as an acceleration (the emulator's 0.5 m/s drag while mapping was found after 11.7 s
        instead of 2.0 s). Visual fixes, after GPS1 is lost, teach it."""
        x, P = self._ekf.x, self._ekf.P
        PHT = P @ H.T
        K = PHT @ np.linalg.inv(H @ PHT + R)
        K[13:15, :] = 0.0
        x += K @ (z.reshape(2, 1) - H @ x)
        I_KH = np.eye(_N) - K @ H
        self._ekf.P = I_KH @ P @ I_KH.T + K @ R @ K.T

    def _gap_noise(self, dt: float) -> tuple[float, float, float]:
        """Per axis, the position, position-velocity and velocity variance ``dt`` s without IMU add (m^2, m^2/s,
        m^2/s^2): an acceleration of ``imu_gap_accel_sigma_m_s2`` that changes over the gap (white, of density
        a^2 dt), so the velocity may have changed by a dt and the position by a dt^2 / sqrt(3). Not one constant
        acceleration: then the position and velocity added would be fully correlated, and the first fix after
        the gap would tell the velocity as exactly as the position (a vehicle that braked, hovered and set off
        again in the gap would be given a velocity it never had, and a sigma of centimetres a second on it)."""
        q = self.cfg.imu_gap_accel_sigma_m_s2**2 * dt
        return q * dt**3 / 3.0, q * dt**2 / 2.0, q * dt

    def _slow_states(self, F: np.ndarray, Q: np.ndarray, dt: float) -> None:
        """Write into ``F`` and ``Q`` what ``dt`` s do to the slow states, the same with the IMU or across a gap:
        the accelerometer bias walks; the shared fix error, the prior map's offset and the tilt's acceleration
        decay (first-order Gauss-Markov, each keeping its steady sigma)."""
        cfg = self.cfg
        Q[_I3 + 6, _I3 + 6] = cfg.accel_bias_walk_m_s2_sqrt_s**2 * dt
        for i, keep, sigma in ((9, np.exp(-dt / cfg.fix_bias_tau_s), self.fix_bias_sigma_m),
                               (11, self._map_offset_decay(dt), self.map_offset_sigma_m),
                               (13, np.exp(-dt / cfg.tilt_error_tau_s), self.tilt_accel_sigma_m_s2)):
            F[i, i] = F[i + 1, i + 1] = keep
            Q[i, i] = Q[i + 1, i + 1] = sigma**2 * (1.0 - keep**2)

    def _carry_across_gap(self, t_s: float) -> None:
        """No IMU from the state's time to ``t_s`` (a link outage): one sample's specific force says nothing of the
        gap, so the state is carried to ``t_s`` at constant velocity, loosened by an unknown acceleration
        (:meth:`_gap_noise`)."""
        dt = t_s - self.t_s
        F = np.eye(_N)
        F[_I3, _I3 + 3] = dt
        q_pp, q_pv, q_vv = self._gap_noise(dt)
        Q = np.zeros((_N, _N))
        Q[_I3, _I3] = q_pp
        Q[_I3, _I3 + 3] = Q[_I3 + 3, _I3] = q_pv
        Q[_I3 + 3, _I3 + 3] = q_vv
        self._slow_states(F, Q, dt)  # the tilt's acceleration is not carried: it is in the gap's unknown one
        self._ekf.x = F @ self._ekf.x
        self._ekf.P = F @ self._ekf.P @ F.T + Q
        self.t_s = t_s

    def _carry_to(self, t_s: float) -> None:
        """A measurement stamped more than ``max_imu_gap_s`` after the state (the link back before its IMU is):
        the state is first carried across the gap to it, as the next IMU sample would carry it."""
        if t_s - self.t_s > self.cfg.max_imu_gap_s:
            self._take("gap", t_s, ())

    def _last_not_after(self, t_s: float) -> int:
        """Index of the last history step not later than ``t_s`` (-1 when the history starts after it)."""
        return bisect.bisect_right(self._history, t_s, key=lambda s: s.t_s) - 1

    def _take_in_order(self, kind: str, t_s: float, data: tuple) -> bool:
        """Take one step at ``t_s`` in time order: back to the state then, carried to ``t_s``, the step, then the
        later steps again. False (nothing taken) when ``t_s`` is older than the history."""
        later = self._rewind(t_s)
        if later is None:
            return False
        self._carry_to(t_s)
        self._take(kind, t_s, data)
        self._retake(later)
        return True

    def _rewind(self, t_s: float) -> list[_Step] | None:
        """Restore the state after the last step not later than ``t_s``; return the later steps, to be taken
        again after the measurement at ``t_s`` (None: ``t_s`` is older than the history)."""
        hist = self._history
        k = self._last_not_after(t_s)
        if k < 0:
            return None
        later = hist[k + 1 :]
        if later:
            del hist[k + 1 :]
            step = hist[k]
            self._ekf.x, self._ekf.P, self.t_s = step.x.copy(), step.P.copy(), step.t_state_s
        return later

    def _take(self, kind: str, t_s: float, data: tuple) -> None:
        """Take one step (propagate, update or re-initialise) and append it to the history."""
        if kind == "imu":
            self._predict(data[0])
        elif kind == "position":
            p_ne_m, cov_ne_m2, visual, prior_share = data
            H = _H_ne(t_s - self.t_s, visual, prior_share)
            if visual:
                self._ekf.update(p_ne_m.reshape(2, 1), lambda x: H, lambda x: H @ x, R=cov_ne_m2)
            else:
                self._update_considering_tilt(p_ne_m, H, cov_ne_m2)
        elif kind == "altitude":
            alt_above_origin_m, sigma_m = data
            H = _H_down(t_s - self.t_s)
            self._ekf.update(np.array([[-alt_above_origin_m]]), lambda x: H, lambda x: H @ x, R=np.array([[sigma_m**2]]))
        elif kind == "reinit":
            self._reinitialise(*data)
        elif kind == "offset":
            self._learn_offset(t_s, *data)
        elif kind == "gap":
            self._carry_across_gap(t_s)
        elif kind == "loosen":
            self._ekf.P[0:2, 0:2] += data[0]
            self._ekf.P[3:5, 3:5] += data[1]
        else:
            raise ValueError(f"unknown filter step {kind!r}")
        self._history.append(_Step(t_s, self.t_s, kind, data, self._ekf.x.copy(), self._ekf.P.copy()))

    def _retake(self, steps: list[_Step]) -> None:
        """Take ``steps`` again, in their order, as they were decided (an update keeps its gate decision); then
        drop the steps older than ``history_s``, keeping one to roll back to."""
        for step in steps:
            self._take(step.kind, step.t_s, step.data)
        self.n_replayed += len(steps)
        hist = self._history
        k = self._last_not_after(self.t_s - self.cfg.history_s)
        if k > 0:
            del hist[:k]

    def _rejected_run_agrees(self, min_span_s: float) -> bool:
        """True when the last ``reinit_count`` rejected fixes or more, within ``reinit_window_s`` and spanning at
        least ``min_span_s`` (visual fixes: ``reinit_min_span_s``; GPS readings, whose run the supervisor reads
        as a jump or a drag, none), agree with each other after the filter's own velocity is taken out: the
        filter, not the fixes, is what is wrong."""
        cfg = self.cfg
        run = [r for r in self._rejected_run if r[0] >= self._rejected_run[-1][0] - cfg.reinit_window_s]
        self._rejected_run[:] = run
        if len(run) < cfg.reinit_count or run[-1][0] - run[0][0] < min_span_s:
            return False
        v = self._ekf.x[3:5, 0]
        t_last, p_last, c_last, _ = run[-1]
        for t, p, c, _ in run[:-1]:
            d = (p + v * (t_last - t)) - p_last
            S = c + c_last + np.eye(2) * (cfg.reinit_speed_sigma_m_s * (t_last - t)) ** 2
            if d @ np.linalg.solve(S, d) > cfg.gate_chi2:
                return False
        return True

    def _map_offset_decay(self, dt: float) -> float:
        """How much of the prior map's offset is still the same after ``dt`` s at the filter's ground speed."""
        if self.map_offset_sigma_m <= 0:
            return 1.0
        return float(np.exp(-np.hypot(self._ekf.x[3, 0], self._ekf.x[4, 0]) * dt / self.cfg.prior_map_offset_length_m))

    @property
    def tilt_accel_sigma_m_s2(self) -> float:
        """One sigma of the horizontal acceleration the autopilot's tilt error leaves out, per axis, m/s^2."""
        return float(GRAVITY_NED_M_S2[2] * np.sin(np.radians(self.cfg.tilt_error_deg)))

    @property
    def fix_bias_sigma_m(self) -> float:
        """One sigma of the error the visual fixes share, m, at the height the filter puts the vehicle at: its
        sources (attitude error, the map's geotagging) are angles, so it grows with the height above the origin's
        ground, from ``fix_bias_sigma_m`` (low flights) by ``fix_bias_per_height``; and what the heading's error
        left in the part of the map in view (:meth:`set_map_heading_sigma`)."""
        own = max(self.cfg.fix_bias_sigma_m, self.cfg.fix_bias_per_height * max(-float(self._ekf.x[2, 0]), 0.0))
        return float(np.hypot(own, self._map_heading_sigma_m))

    def set_map_heading_sigma(self, sigma_m: float) -> None:
        """The part of the map the fixes come from now was geotagged with a heading this uncertain, as metres on
        the ground (one sigma): the fixes share it. Their shared error's variance is raised to it at once where it
        is less (the map in view changed), and its process keeps it there."""
        sigma_m = float(sigma_m) if np.isfinite(sigma_m) and sigma_m > 0 else 0.0
        self._map_heading_sigma_m = sigma_m
        P = self._ekf.P
        floor = self.fix_bias_sigma_m**2
        for i in (9, 10):
            if P[i, i] < floor:
                P[i, i] = floor

    def _reinitialise(self, p_ne_m: np.ndarray, cov_ne_m2: np.ndarray, prior_share: float = 0.0) -> None:
        """Put the position on a fix, forget the shared fix error and the prior map's offset (the fix holds the
        share ``prior_share`` of it: the position is then that uncertain too), loosen the velocity."""
        x, P = self._ekf.x, self._ekf.P
        x[0:2, 0] = p_ne_m
        x[9:13, 0] = 0.0
        for block in (slice(0, 2), slice(9, 13)):
            P[block, :] = 0.0
            P[:, block] = 0.0
        var_map = self.map_offset_sigma_m**2
        P[0:2, 0:2] = cov_ne_m2 + np.eye(2) * prior_share**2 * var_map
        P[9:11, 9:11] = np.eye(2) * self.fix_bias_sigma_m**2
        P[11:13, 11:13] = np.eye(2) * var_map
        P[0:2, 11:13] = P[11:13, 0:2] = -np.eye(2) * prior_share * var_map  # position = fix - share * offset
        P[3:5, 3:5] += np.eye(2) * self.cfg.reinit_speed_sigma_m_s**2

    def _decide(self, d: GateDecision) -> GateDecision:
        if d.accepted:
            self.n_accepted += 1
        else:
            self.n_rejected += 1
            log.info("fix at t=%.3f s rejected: %s (squared Mahalanobis %.1f)", d.t_s, d.reason, d.mahalanobis2)
        return d
