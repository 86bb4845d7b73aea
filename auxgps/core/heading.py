"""The autopilot's heading error, followed from what the images show.

``b`` is how far the autopilot's heading is turned from the true one, rad, positive clockwise seen from above (a
heading read as 91 deg for a true 90 is ``b = +1 deg``). Everything auxgps does with an attitude uses the
heading less the estimate, so that the map and the fixes are geotagged with the true heading as well as it is
known. A compass-fed EKF's heading is off by a degree or two and wanders over minutes; from 40 m a degree moves
the image's edge 0.7 m, and a map geotagged with it is turned about where it was seen from, so that fixes from
elsewhere (a return leg beside the way out) are off by the turn times the distance.

Two kinds of evidence, one per phase:

- **While mapping** (GPS1 trusted): the same landmark seen from two cameras ``B`` apart (GPS1's positions, a second
  or two apart), each ray put on the ground with the telemetry's own heading, lands at two points ``b * B^perp``
  apart (``(n, e)^perp = (-e, n)``, a quarter turn clockwise seen from above): the images and GPS1 disagree on
  which way the vehicle moved. An error in the landmark's height moves the two points along ``B`` (parallax), not
  across it, so only the across part is used (:func:`heading_from_motion`). This uses neither the map's positions
  nor the estimate, so it cannot follow its own corrections around (a map made with an error and checked against
  itself shows none). Hovering, there is no baseline and no evidence.
- **While positioning** the map is not changed, and the turn the localiser fits between the frame's rays and the
  landmarks is the heading error left (:attr:`auxgps.core.localise.Fix.heading_turn_rad`).

Pure: arrays and times in, estimates out; no clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class HeadingEstimate:
    """The autopilot's heading error at ``t_s``: ``offset_rad`` (subtract it from the heading) and its one sigma.
    ``memory``: the tracker's memory clock then (:meth:`HeadingTracker.at`); ``p_off``: the probability that the
    heading is off at all (the estimate is the mixture's: see :class:`HeadingTracker`)."""

    t_s: float
    offset_rad: float
    sigma_rad: float
    memory: float = 0.0
    p_off: float = 1.0


@dataclass(frozen=True)
class MotionView:
    """One mapping frame as the heading is solved from: its camera's north/east (GPS1, m), and the landmarks it saw
    with their rays put on the ground with the telemetry's heading (``ground_ne_m`` (K, 2), m), ids sorted."""

    t_s: float
    camera_ne_m: np.ndarray
    landmark_ids: np.ndarray
    ground_ne_m: np.ndarray


@dataclass(frozen=True)
class HeadingMeasurement:
    """The heading error one pair of views says, rad, with its variance, over ``n`` landmarks and a baseline."""

    t_s: float
    offset_rad: float
    var_rad2: float
    n: int
    baseline_m: float


def perp(v_ne: np.ndarray) -> np.ndarray:
    """North/east vectors (..., 2) turned a quarter clockwise seen from above (what a small turn adds per radian)."""
    v = np.asarray(v_ne, float)
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def ground_points_ne(camera_ned_m: np.ndarray, rays_ned: np.ndarray, down_m: np.ndarray) -> np.ndarray:
    """(K, 2) north/east where rays from ``camera_ned_m`` (3,) along ``rays_ned`` (K, 3) cross the horizontal planes
    ``down = down_m`` (K,); NaN where a ray does not go down to its plane."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.asarray(down_m, float) - camera_ned_m[2]) / rays_ned[:, 2]
    t = np.where(np.isfinite(t) & (t > 0), t, np.nan)
    return camera_ned_m[:2] + t[:, None] * rays_ned[:, :2]


def heading_from_motion(now: MotionView, before: MotionView, shift_sigma_m: float, min_shared: int) -> HeadingMeasurement | None:
    """The heading error from the landmarks two views share: the across-baseline offset of their ground points over
    the baseline, the median of them (a wrong match cannot move it), its variance from their spread and from what
    moves all of them alike (``shift_sigma_m``, one sigma across: GPS1's error over the interval, the two
    attitudes' tilt errors). None: too few landmarks shared."""
    _, i_now, i_before = np.intersect1d(now.landmark_ids, before.landmark_ids, assume_unique=True, return_indices=True)
    d_ground = now.ground_ne_m[i_now] - before.ground_ne_m[i_before]
    d_ground = d_ground[np.all(np.isfinite(d_ground), axis=1)]
    if len(d_ground) < min_shared:
        return None
    B = before.camera_ne_m - now.camera_ne_m
    B2 = float(B @ B)
    z = d_ground @ perp(B) / B2  # rad, per landmark
    med = float(np.median(z))
    spread = 1.4826 * float(np.median(np.abs(z - med)))
    var = (1.2533 * spread) ** 2 / len(z) + shift_sigma_m**2 / B2  # the median's variance: (pi/2) sigma^2 / n
    return HeadingMeasurement(now.t_s, med, var, len(z), float(np.sqrt(B2)))


# The odds are kept within e^-9 to e^9 (p_off 1e-4 to 0.9999), so that a few seconds of evidence turn them.
_MAX_LOG_ODDS = 9.0
_P_OFF_MAX = float(1.0 / (1.0 + np.exp(-_MAX_LOG_ODDS)))


class HeadingTracker:
    """A scalar Kalman filter on the heading error (first-order Gauss-Markov: ``sigma_deg``, ``tau_s``), with the
    views of the last few mapping frames to pair each new one with.

    Two hypotheses are weighed: the heading is off, and wanders as that process (a compass-fed EKF), or it is right
    within the telemetry's own noise (a heading from two GPS antennas, a well-aligned EKF, the simulator). Each
    measurement moves their odds by its likelihood under each (the filter's prediction against zero); between
    measurements the odds relax toward ``off_prior`` over ``tau_s`` (a right heading may start to wander). What is
    taken out of the heading is the mixture's mean, ``p_off`` times the filter's estimate, with the mixture's
    variance: where the evidence cannot tell a small wandering error from none, a correction that follows the
    measurements' noise is not worth its cost (the map geotagged with it carries that noise, shared by all the views
    of a landmark, where a right heading's noise averages out over them). The filter itself runs as before.

    A measurement older than the newest is applied at the newest time (the error changes over minutes; frames come
    within a second). Each is gated on its innovation; a run of ``reset_after`` refused in a row (the error has
    jumped: a magnetometer re-learnt, a compass switched) opens the estimate to its prior again. Evidence of one kind
    is weighed by how many of its kind came in the last ``decorrelation_s`` (consecutive frames share their errors)."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self._sigma2 = np.deg2rad(cfg.sigma_deg) ** 2
        self._b = 0.0
        self._var = self._sigma2
        self._t: float | None = None
        self._views: deque[MotionView] = deque()
        self._refused_in_row = 0
        self._recent: dict[str, deque[float]] = {"view": deque(), "turn": deque()}
        self.n_used = 0
        self.n_refused = 0
        self._memory = 0.0  # the memory clock at self._t
        self._p_off = cfg.off_prior  # at self._t

    def restore(self, offset_rad: float, sigma_rad: float, elapsed_s: float) -> None:
        """Start from an estimate saved ``elapsed_s`` ago (a map checkpoint, read again after a crash), decayed
        toward the prior as the Gauss-Markov process decays: seconds after, nearly as it was; after many
        ``tau_s``, the prior again. A non-finite or negative part leaves the prior."""
        if not (np.isfinite(offset_rad) and np.isfinite(sigma_rad) and sigma_rad >= 0 and np.isfinite(elapsed_s) and elapsed_s >= 0):
            return
        phi = float(np.exp(-elapsed_s / self.cfg.tau_s))
        self._b = offset_rad * phi
        self._var = min(sigma_rad**2 * phi**2 + self._sigma2 * (1.0 - phi**2), self._sigma2)
        # The saved estimate was taken out as it is: "off", as far as the odds' bound allows, aged like the rest.
        self._p_off = self.cfg.off_prior + (_P_OFF_MAX - self.cfg.off_prior) * phi
        self._t = None

    def _decayed(self, t_s: float) -> tuple[float, float]:
        if self._t is None or t_s <= self._t:
            return self._b, self._var
        phi = float(np.exp(-(t_s - self._t) / self.cfg.tau_s))
        return self._b * phi, self._var * phi**2 + self._sigma2 * (1.0 - phi**2)

    def _p_off_at(self, t_s: float) -> float:
        if self._t is None or t_s <= self._t:
            return self._p_off
        return self.cfg.off_prior + (self._p_off - self.cfg.off_prior) * float(np.exp(-(t_s - self._t) / self.cfg.tau_s))

    def _memory_at(self, t_s: float, var: float) -> float:
        """The memory clock at ``t_s``: the integral of ``q / var`` (``q = 2 sigma^2 / tau_s``, the process's
        variance rate). A smoother would correct the estimate at an earlier time by what a measurement now says
        times about ``exp(-(memory now - memory then))``: while the tracker knows little (``var`` near its prior)
        the clock runs slowly and later evidence still tells about then; once it knows the error well the clock
        runs fast (about 0.25 a second at 0.3 deg), as the error may since have moved by as much as it is known."""
        if self._t is None or t_s <= self._t:
            return self._memory
        return self._memory + (t_s - self._t) * 2.0 * self._sigma2 / self.cfg.tau_s / max(var, 1e-12)

    def at(self, t_s: float) -> HeadingEstimate:
        """The estimate at ``t_s`` (at the newest measurement's, for an earlier time): the mixture of "off" and
        "right" (see the class)."""
        off = self.if_off(t_s)
        p = self._p_off_at(t_s)
        b = off.offset_rad
        return replace(off, offset_rad=p * b, sigma_rad=float(np.sqrt(p * off.sigma_rad**2 + p * (1.0 - p) * b * b)), p_off=p)

    def if_off(self, t_s: float) -> HeadingEstimate:
        """The filter's estimate at ``t_s`` alone, as if the heading were known to be off (``p_off`` 1)."""
        b, var = self._decayed(t_s)
        return HeadingEstimate(max(t_s, self._t if self._t is not None else t_s), b, float(np.sqrt(var)), self._memory_at(t_s, var))

    def observe(self, t_s: float, offset_rad: float, var_rad2: float) -> bool:
        """A direct measurement of the heading error; False when the gate refused it."""
        b, var = self._decayed(t_s)
        t_new = max(t_s, self._t if self._t is not None else t_s)
        self._memory = self._memory_at(t_new, var)
        innovation = offset_rad - b
        S = var + var_rad2
        if not (np.isfinite(innovation) and np.isfinite(S) and S > 0):
            return False
        if innovation**2 > self.cfg.gate_chi2 * S:
            self.n_refused += 1
            self._refused_in_row += 1
            self._p_off = self._p_off_at(t_s)
            self._b, self._var, self._t = b, var, t_new
            if self._refused_in_row >= self.cfg.reset_after:
                self._var, self._refused_in_row = self._sigma2, 0
            return False
        # The odds of "off" against "right": this measurement's likelihood under each (N(b, S) against N(0, R)).
        p = self._p_off_at(t_s)
        log_lr = 0.5 * (np.log(var_rad2 / S) + offset_rad**2 / var_rad2 - innovation**2 / S)
        p = min(max(p, 1.0 - _P_OFF_MAX), _P_OFF_MAX)
        log_odds = np.clip(np.log(p / (1.0 - p)) + log_lr, -_MAX_LOG_ODDS, _MAX_LOG_ODDS)
        self._p_off = float(1.0 / (1.0 + np.exp(-log_odds)))
        K = var / S
        self._b, self._var, self._t = b + K * innovation, max(var * (1.0 - K), 1e-12), t_new
        self._refused_in_row = 0
        self.n_used += 1
        return True

    def _share(self, kind: str, t_s: float) -> float:
        """How many measurements of ``kind`` (this one included) fall within ``decorrelation_s``: the factor their
        variance is weighed by, so that a burst of correlated frames tells what one of them does."""
        recent = self._recent[kind]
        while recent and recent[0] < t_s - self.cfg.decorrelation_s:
            recent.popleft()
        recent.append(t_s)
        return float(len(recent))

    def observe_view(self, view: MotionView, shift_sigma_m: float, jitter_var_rad2: float = 0.0) -> HeadingMeasurement | None:
        """A mapping frame's view: paired with the oldest kept view at least ``min_baseline_m`` away and at most
        ``max_pair_gap_s`` earlier that shares enough landmarks, and kept for the frames after it. The
        measurement it gave (None: none, or the gate refused it). ``shift_sigma_m``: see :func:`heading_from_motion`;
        ``jitter_var_rad2``: the heading's own frame-to-frame noise, what it adds to a pair's measurement."""
        cfg = self.cfg
        while self._views and self._views[0].t_s < view.t_s - cfg.max_pair_gap_s:
            self._views.popleft()
        found = None
        for before in self._views:
            if before.t_s >= view.t_s or np.hypot(*(before.camera_ne_m - view.camera_ne_m)) < cfg.min_baseline_m:
                continue
            found = heading_from_motion(view, before, shift_sigma_m, cfg.min_shared)
            if found is not None:
                break
        self._views.append(view)
        if found is None or not self.observe(found.t_s, found.offset_rad, (found.var_rad2 + jitter_var_rad2) * self._share("view", found.t_s)):
            return None
        return found

    def observe_turn(self, t_s: float, turn_rad: float, var_rad2: float, used_rad: float) -> bool:
        """A positioning frame whose rays had to be turned by ``turn_rad`` (``var_rad2``) to fit the map, located
        with the heading less ``used_rad``: the heading error is ``used_rad - turn_rad``."""
        var = (var_rad2 + np.deg2rad(self.cfg.rotation_floor_deg) ** 2) * self._share("turn", t_s)
        return self.observe(t_s, used_rad - turn_rad, var)
