"""What auxgps is doing, and whether GPS1 can be trusted: the companion's decisions, free of I/O.

Modes
-----
- ``MAPPING``: GPS1 is trusted. Landmarks are geotagged from it, GPS1 corrects the filter, and frames are also
  located against the map as a running self-check.
- ``POSITIONING``: GPS1 is lost, degraded, or disagrees with auxgps (a jump: jamming or spoofing). Mapping stops
  at once; the filter runs on visual fixes alone.
- ``NO_FIX``: auxgps does not believe its own estimate (no recent correction, or too uncertain); it keeps
  sending at rate, without a fix.

GPS1 becomes trusted again only after it has agreed with auxgps's estimate for ``rejoin_s`` without a break, or at
once when auxgps has no estimate of its own worth comparing with (looser than ``max_sigma_h_m``).

GPS1 is not trusted either while its reported accuracy is over ``max_gps1_h_acc_m``, or over ``h_acc_inflation``
times the median of its recent trusted reports (a receiver that keeps its 3D fix under jamming reports it so); nor
when the filter's gate has rejected it ``reinit_count`` times in a row on one track (:meth:`Supervisor.gps1_rejected`:
a jump the filter, not this comparison, saw first, as when GPS1 is dragged faster than the self-check can follow).

A GPS1 dragged away slowly (spoofing, a failing receiver) is followed by the filter it corrects, so comparing the
two cannot see it. The map can: while mapping, every frame is also located against the map (the self-check), and
:meth:`Supervisor.visual_check` takes each self-check's difference from the filter. When the mean of the last
``drag_fixes`` within ``drag_window_s`` is over ``drag_m`` and over ``agree_chi2`` in its own covariance, GPS1 is
distrusted (mapping stops; GPS_INPUT comes from the visual estimate) and it may rejoin only by agreeing with
auxgps within its covariance alone, without the ``min_jump_m`` allowance, for ``rejoin_s``.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass

import numpy as np


class Mode(enum.Enum):
    MAPPING = "mapping"
    POSITIONING = "positioning"
    NO_FIX = "no fix"


@dataclass(frozen=True)
class Gps1Sample:
    """GPS1 as the autopilot reports it (GPS_RAW_INT): time s, fix type, satellites, NED position m, accuracy m."""

    t_s: float
    fix_type: int
    satellites: int
    p_ned_m: np.ndarray
    h_acc_m: float


@dataclass(frozen=True)
class SupervisorConfig:
    min_fix_type: int = 3
    min_satellites: int = 6
    stale_s: float = 1.0
    agree_chi2: float = 13.8  # 99.9% for 2 degrees of freedom
    min_jump_m: float = 2.0  # and at least this far apart: a receiver's jump, not latency or noise
    rejoin_s: float = 10.0
    max_sigma_h_m: float = 2.0
    # A standalone receiver reports 1 to 2.5 m, RTK centimetres, SITL 0.3 m: over this, or this many times the median
    # of its last trusted reports, GPS1 is degraded (geotagging from it would blur the map).
    max_gps1_h_acc_m: float = 3.0
    h_acc_inflation: float = 4.0
    h_acc_history: int = 50
    # Between visual fixes the filter carries on the IMU and its covariance grows honestly (the camera-blackout
    # test checks it); a landing's last metres see nothing mapped. This is a backstop against an IMU error the
    # filter does not model, however small its covariance says the error is.
    max_fix_age_s: float = 15.0
    status_interval_s: float = 1.0
    # GPS1 dragged away from the map (see the module's docstring). The self-check's mean difference stays under
    # 0.15 m over 3 fixes on the simulated surveys (p95 of single fixes 0.15 to 0.17 m).
    drag_m: float = 0.5
    drag_fixes: int = 3
    drag_window_s: float = 2.0
    # The self-check uses only landmarks first geotagged this long before the frame: over ground first seen during a
    # drag, the landmarks of moments before carry the same drag and would agree with it.
    self_check_age_s: float = 10.0
    # How far back the map's changes are kept, so that a drag found late can be undone back to the last agreeing
    # self-check (which judged the map self_check_age_s older than itself): a few MB at 20 mapped frames a second.
    undo_span_s: float = 40.0


@dataclass(frozen=True)
class Decision:
    """The mode now, whether GPS1 is trusted, and a status line to send (None: nothing new to say)."""

    mode: Mode
    gps1_trusted: bool
    status: str | None


class Supervisor:
    """Decides the mode from GPS1 and the filter; rate-limits the status lines that announce changes."""

    def __init__(self, cfg: SupervisorConfig | None = None) -> None:
        self.cfg = cfg or SupervisorConfig()
        self.mode: Mode = Mode.NO_FIX
        self.gps1_trusted = False
        self._gps1: Gps1Sample | None = None
        self._agree_since: float | None = None
        self._ever_trusted = False
        self._last_status_t = -np.inf
        self._pending_status: deque[str] = deque(maxlen=4)  # lines to announce, oldest first
        self.disagreement: str | None = None
        self._checks: list[tuple[float, np.ndarray, np.ndarray]] = []  # recent self-checks (t, fix - filter, cov)
        self.dragged_at_s: float | None = None  # when GPS1 was found dragged away from the map
        self._h_acc_trusted: list[float] = []  # GPS1's reported accuracy while trusted, m (the latest h_acc_history)
        self.trusted_since_s: float | None = None  # when GPS1 last became trusted
        self.last_agreement_t_s: float | None = None  # the last self-check run whose mean was within drag_m / 2
        # The mean self-check (the map's fix less the filter) when GPS1 was found dragged, m: what the filter had
        # followed of the drag (None: no run of self-checks within drag_window_s said)
        self.drag_seen_ne_m: np.ndarray | None = None
        self._last_run: tuple[float, np.ndarray] | None = None  # the latest run of self-checks: its time and mean, m

    def _degraded(self, sample: Gps1Sample) -> str | None:
        """Why GPS1's report is not good enough to trust (None: it is)."""
        cfg = self.cfg
        if sample.fix_type < cfg.min_fix_type or sample.satellites < cfg.min_satellites or not np.all(np.isfinite(sample.p_ned_m)):
            return f"GPS1 lost (fix {sample.fix_type}, {sample.satellites} sats): positioning visually"
        usual_m = float(np.median(self._h_acc_trusted)) if len(self._h_acc_trusted) >= 10 else None
        if sample.h_acc_m > cfg.max_gps1_h_acc_m or (usual_m is not None and sample.h_acc_m > cfg.h_acc_inflation * max(usual_m, 0.05)):
            usual = f"usually {usual_m:.2f} m" if usual_m is not None else f"over {cfg.max_gps1_h_acc_m:g} m"
            return f"GPS1 accuracy {sample.h_acc_m:.1f} m: distrusted, positioning ({usual})"
        return None

    def gps1(self, sample: Gps1Sample, p_est_ned_m: np.ndarray | None, cov_est_ne_m2: np.ndarray | None) -> None:
        """Take a GPS1 report; ``p_est``/``cov_est`` are auxgps's own estimate at the same time (None if none)."""
        cfg = self.cfg
        if self._gps1 is not None and sample.t_s - self._gps1.t_s > cfg.stale_s:
            self._agree_since = None  # a silence breaks an agreement (a GPS1 that keeps dropping out never rejoins)
        self._gps1 = sample
        degraded = self._degraded(sample)
        good = degraded is None
        agrees = True
        self.disagreement = None
        if good and p_est_ned_m is not None and cov_est_ne_m2 is not None:
            d = sample.p_ned_m[:2] - p_est_ned_m[:2]
            S = cov_est_ne_m2 + np.eye(2) * max(sample.h_acc_m, 0.05) ** 2
            m2 = float(d @ np.linalg.solve(S, d))
            strict = self.dragged_at_s is not None and not self.gps1_trusted
            agrees = m2 <= cfg.agree_chi2 or (not strict and float(np.linalg.norm(d)) < cfg.min_jump_m)
            if not agrees:
                self.disagreement = f"GPS1 disagrees with auxgps by {np.linalg.norm(d):.1f} m"
        if not (good and agrees):
            if self.gps1_trusted:
                self._say(self.disagreement or degraded, sample.t_s)
            self.gps1_trusted = False
            self._agree_since = None
            return
        if self.gps1_trusted:
            self._h_acc_trusted = (self._h_acc_trusted + [float(sample.h_acc_m)])[-cfg.h_acc_history:]
            return
        self.trusted_since_s = sample.t_s  # (kept only if trusted below)
        if not self._ever_trusted:
            self.gps1_trusted = self._ever_trusted = True  # first lock: nothing of ours to compare with yet
            return
        own_sigma_m = float(np.sqrt(np.linalg.eigvalsh(cov_est_ne_m2)[-1])) if cov_est_ne_m2 is not None else np.inf
        if self.dragged_at_s is not None:
            # Found dragged: GPS1 rejoins only by agreeing for rejoin_s with a position of auxgps's own that is tight
            # enough to tell a drag (however lost auxgps may be meanwhile: a loose estimate agrees with anything).
            if own_sigma_m > cfg.drag_m:
                self._agree_since = None
                return
        elif own_sigma_m > cfg.max_sigma_h_m:
            # auxgps has no position of its own worth comparing (after a link outage without IMU, or a long run
            # without fixes): waiting rejoin_s would leave the vehicle with nothing, and GPS1 would agree with any
            # estimate that loose anyway.
            self.gps1_trusted = True
            self._say("GPS1 trusted again: auxgps had no position of its own", sample.t_s)
            return
        self._agree_since = sample.t_s if self._agree_since is None else self._agree_since
        if sample.t_s - self._agree_since >= cfg.rejoin_s:
            self.gps1_trusted = True
            self.dragged_at_s = None
            self._checks.clear()
            self._say(f"GPS1 agrees with auxgps for {cfg.rejoin_s:.0f} s: mapping again", sample.t_s)

    def gps1_rejected(self, t_s: float, distance_m: float) -> str | None:
        """The filter's gate rejected GPS1 on a run of consistent reports ``distance_m`` from its track: GPS1
        jumped, or is dragged faster than the filter follows. Distrusted as when found dragged. Returns the line
        to log (None when GPS1 was not trusted anyway)."""
        if not self.gps1_trusted:
            return None
        # What the filter followed of it is what the map says now: the latest run of self-checks, if recent
        recent = self._last_run is not None and abs(t_s - self._last_run[0]) <= self.cfg.drag_window_s
        self.drag_seen_ne_m = self._last_run[1] if recent else None
        return self._distrust_as_dragged(t_s, f"GPS1 off track {distance_m:.1f} m: distrusted, no mapping (a run of its "
                                              "reports off the filter's track, rejected by its gate)")

    def unverified_since_s(self) -> float:
        """Landmarks first geotagged after this time were never checked against older ones before GPS1 was found
        dragged: the last agreeing self-check judged those older than ``self_check_age_s`` then (-inf: none did)."""
        return -np.inf if self.last_agreement_t_s is None else self.last_agreement_t_s - self.cfg.self_check_age_s

    def _distrust_as_dragged(self, t_s: float, line: str) -> str:
        """Stop trusting GPS1 until it agrees strictly (see the module's docstring); announce ``line``."""
        self.gps1_trusted = False
        self._agree_since = None
        self.dragged_at_s = t_s
        self._checks.clear()
        self._say(line, t_s)
        return line

    def visual_check(self, t_s: float, d_ne_m: np.ndarray, cov_ne_m2: np.ndarray, shared_ne_m2: np.ndarray | None = None) -> str | None:
        """Take a self-check while mapping: a fix located on the map minus the filter (which follows GPS1), with
        their combined covariance, and the covariance of the error visual fixes share (the map's, the attitude's:
        it does not average out over a run of checks). Returns a line when GPS1 is found dragged away from the map
        (then distrusted)."""
        cfg = self.cfg
        if not self.gps1_trusted:
            return None
        self._checks = [c for c in self._checks if t_s - c[0] <= cfg.drag_window_s] + [(t_s, np.asarray(d_ne_m, float), np.asarray(cov_ne_m2, float))]
        run = self._checks[-cfg.drag_fixes:]
        if len(run) < cfg.drag_fixes:
            return None
        n = len(run)
        mean = sum(c[1] for c in run) / n
        self._last_run = (t_s, mean)
        cov = sum(c[2] for c in run) / (n * n) + (shared_ne_m2 if shared_ne_m2 is not None else 0.0)
        m2 = float(mean @ np.linalg.solve(cov, mean))
        if float(np.linalg.norm(mean)) <= cfg.drag_m / 2:
            self.last_agreement_t_s = t_s
        if float(np.linalg.norm(mean)) <= cfg.drag_m or m2 <= cfg.agree_chi2:
            return None
        self.drag_seen_ne_m = mean
        return self._distrust_as_dragged(t_s, f"GPS1 drifts {np.linalg.norm(mean):.1f} m from map: distrusted, no mapping "
                                              f"(mean of the last {n} self-checks; spoofing or a failing receiver?)")

    def believes(self, t_s: float, *, sigma_h_worst_m: float | None, last_correction_t_s: float | None) -> bool:
        """Whether auxgps believes its estimate at ``t_s`` (else GPS_INPUT says no fix): corrected within
        ``max_fix_age_s`` and its horizontal sigma at most ``max_sigma_h_m``."""
        cfg = self.cfg
        return (
            sigma_h_worst_m is not None
            and bool(np.isfinite(sigma_h_worst_m))
            and sigma_h_worst_m <= cfg.max_sigma_h_m
            and last_correction_t_s is not None
            and t_s - last_correction_t_s <= cfg.max_fix_age_s
        )

    def decide(self, t_s: float, *, sigma_h_worst_m: float | None, last_correction_t_s: float | None) -> Decision:
        """The mode at ``t_s`` given the filter's horizontal sigma and the time of its last correction."""
        cfg = self.cfg
        if self._gps1 is not None and t_s - self._gps1.t_s > cfg.stale_s and self.gps1_trusted:
            self.gps1_trusted = False
            self._agree_since = None
            self._say("GPS1 silent: positioning visually", t_s)
        believed = self.believes(t_s, sigma_h_worst_m=sigma_h_worst_m, last_correction_t_s=last_correction_t_s)
        mode = Mode.MAPPING if (self.gps1_trusted and believed) else Mode.POSITIONING if believed else Mode.NO_FIX
        if mode != self.mode:
            self._say(f"auxgps: {mode.value}", t_s)
            self.mode = mode
        status = None
        if self._pending_status and t_s - self._last_status_t >= cfg.status_interval_s:
            status = self._pending_status.popleft()
            self._last_status_t = t_s
        return Decision(mode, self.gps1_trusted, status)

    def _say(self, text: str, t_s: float) -> None:
        # One line per status interval, in order; a burst beyond the queue loses its oldest lines. A STATUSTEXT
        # carries 50 characters: each line says what matters in its first 50.
        self._pending_status.append(text)
