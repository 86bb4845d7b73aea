"""The companion process: MAVLink in and out, camera frames through the pipeline, GPS_INPUT at a steady rate.

Threads: the link's reader feeds IMU, attitude, altitude and GPS1 into the filter and the supervisor; a timer
sends GPS_INPUT every 1/rate seconds from whatever the filter holds, never waiting on frame processing; the main
loop turns camera frames into landmarks (while GPS1 is trusted) and visual fixes. One lock guards the filter
and the supervisor, held only for their quick updates. Every time is on this process's monotonic clock.
"""

from __future__ import annotations

import csv
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from auxgps.config import PipelineConfig
from auxgps.core.camera import camera_from_config
from auxgps.core.features import FeatureDetector
from auxgps.core.fusion import ImuSample, NavFilter
from auxgps.core.geometry import LocalFrame, R_body_cam_from_mount, R_ned_body_from_euler
from auxgps.core.gps_output import FIX_3D, gps_output
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix, Localiser
from auxgps.core.mapping import Mapper
from auxgps.core.nav import NavSample
from auxgps.core.supervisor import Gps1Sample, Mode, Supervisor
from auxgps.io.camera import open_camera
from auxgps.io.link import Attitude, Gps1, Imu, MavLink, Position, Truth
from auxgps.io.map_file import load_map, save_map

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunOptions:
    connect: str
    camera: str
    map_in: str | None = None
    map_out: str | None = None
    log_dir: str = "out/run"
    duration_s: float | None = None
    gps_input_rate_hz: float = 10.0
    gps_delay_s: float = 0.1  # GPS_INPUT describes the vehicle this long ago: the autopilot's GPS2_DELAY_MS
    gps1_lag_s: float = 0.1  # a GPS1 reading describes the vehicle this long before its fix time (SITL: SIM_GPS1_LAG_MS)


class CsvLog:
    """Append-only CSV files in one folder, flushed per row (a crash loses nothing written)."""

    def __init__(self, folder: str) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._files: dict[str, tuple] = {}
        self._lock = threading.Lock()

    def row(self, name: str, **fields) -> None:
        with self._lock:
            if name not in self._files:
                f = open(self.folder / f"{name}.csv", "w", newline="")
                w = csv.DictWriter(f, fieldnames=list(fields))
                w.writeheader()
                self._files[name] = (f, w)
            f, w = self._files[name]
            w.writerow(fields)
            f.flush()

    def close(self) -> None:
        with self._lock:
            for f, _ in self._files.values():
                f.close()


class Companion:
    """auxgps as a process beside the autopilot."""

    def __init__(self, cfg: PipelineConfig, opts: RunOptions) -> None:
        self.cfg, self.opts = cfg, opts
        self.camera_model = camera_from_config(cfg.camera)
        m = cfg.mount
        self.R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
        self.frame: LocalFrame | None = None
        self.landmarks = LandmarkMap()
        if opts.map_in:
            self.landmarks, self.frame = load_map(opts.map_in)  # MapError: one clear line from the CLI
        self.detector = FeatureDetector(cfg.detector)
        self.mapper = Mapper(cfg, self.camera_model, self.R_body_cam, self.landmarks)
        self.localiser = Localiser(cfg, self.camera_model, self.R_body_cam, self.landmarks)
        self.supervisor = Supervisor()
        self.filter: NavFilter | None = None
        self.log = CsvLog(opts.log_dir)
        self._lock = threading.Lock()
        self._attitudes: deque[Attitude] = deque(maxlen=200)
        self._truth: Truth | None = None
        self._rel_alt_m: float | None = None
        self._rel_alt_raw_m: float | None = None
        self._home_alt_amsl_m: float | None = None
        self._gps1_sats: int | None = None
        self._last_correction_t: float | None = None
        self._last_disagreement: str | None = None
        self._stop = threading.Event()
        self.link = MavLink(opts.connect, self._on_record, sim=opts.camera.startswith("sim:"))
        self.camera = open_camera(opts.camera, self.camera_model, self.R_body_cam, truth=lambda: self._truth)
        self.sent = 0

    # -- records from the autopilot (reader thread) ----------------------------------------------------------

    def _on_record(self, rec) -> None:
        with self._lock:
            if isinstance(rec, Attitude):
                self._attitudes.append(rec)
            elif isinstance(rec, Imu):
                if self.filter is not None and self._attitudes:
                    R = R_ned_body_from_euler(*self._attitude_at(rec.t_s))
                    self.filter.propagate(ImuSample(rec.t_s, rec.f_body_m_s2, R))
            elif isinstance(rec, Position):
                self._on_position(rec)
            elif isinstance(rec, Gps1):
                self._on_gps1(rec)
            elif isinstance(rec, Truth):
                self._truth = rec

    def _on_position(self, rec: Position) -> None:
        self._rel_alt_raw_m = rec.rel_alt_m
        if self.frame is not None and self._home_alt_amsl_m is None:
            self._home_alt_amsl_m = self.frame.alt_amsl_m  # a loaded map's origin: heights are above it
        if self.frame is not None and self._home_alt_amsl_m is not None:
            self._rel_alt_m = rec.rel_alt_m + (self._home_alt_amsl_m - self.frame.alt_amsl_m)
            if self.filter is not None:
                self.filter.update_altitude(rec.t_s, self._rel_alt_m, self.cfg.noise.altitude_m)

    def _on_gps1(self, rec: Gps1) -> None:
        if self.frame is None:
            # No map: anchor the local frame at the first 3D fix, on the ground below it (the autopilot's height
            # above home says how far up it is). Not at the autopilot's own position: before its EKF has an
            # origin, GLOBAL_POSITION_INT's altitude reads 0.
            if rec.fix_type < 3 or self._rel_alt_raw_m is None:
                return
            self.frame = LocalFrame(rec.lat_deg, rec.lon_deg, rec.alt_amsl_m - self._rel_alt_raw_m)
            self._home_alt_amsl_m = self.frame.alt_amsl_m
            log.info("local frame anchored at %.7f, %.7f, %.1f m AMSL", rec.lat_deg, rec.lon_deg, self.frame.alt_amsl_m)
        p = self.frame.to_ned(lat_deg=rec.lat_deg, lon_deg=rec.lon_deg, alt_amsl_m=rec.alt_amsl_m)
        t_meas = rec.t_s - self.opts.gps1_lag_s  # when the receiver measured it (rec.t_s: the autopilot got it)
        est = self.filter.estimate_at(t_meas) if self.filter is not None else None
        self.supervisor.gps1(
            Gps1Sample(t_meas, rec.fix_type, rec.satellites, p, rec.h_acc_m),
            est.p_ned_m if est is not None else None,
            est.cov_p_m2[:2, :2] if est is not None else None,
        )
        if self.supervisor.disagreement and self.supervisor.disagreement != self._last_disagreement:
            self.log.row("events", t_s=rec.t_s, text=self.supervisor.disagreement)
        self._last_disagreement = self.supervisor.disagreement
        if not self.supervisor.gps1_trusted:
            self._gps1_sats = None
            return
        self._gps1_sats = rec.satellites
        sigma = max(rec.h_acc_m, self.cfg.noise.gps_horizontal_m)
        if self.filter is None:
            self.filter = NavFilter(self.cfg.fusion, t_meas, p, np.zeros(3), sigma, 1.0)
        else:
            self.filter.update_position(t_meas, p[:2], np.eye(2) * sigma**2)
        self._last_correction_t = t_meas

    def _attitude_at(self, t_s: float) -> np.ndarray:
        """The attitude sample nearest to ``t_s`` (called with the lock held)."""
        best = min(self._attitudes, key=lambda a: abs(a.t_s - t_s))
        return best.euler_rad

    # -- GPS_INPUT at a steady rate (timer thread) ----------------------------------------------------------

    def _gps_input_loop(self) -> None:
        period = 1.0 / self.opts.gps_input_rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            next_t += period
            self._send_gps_input()
            delay = next_t - time.monotonic()
            if delay < -period:
                next_t = time.monotonic()  # fell behind (a stalled machine): restart the schedule, do not burst
            elif delay > 0:
                self._stop.wait(delay)

    def _send_gps_input(self) -> None:
        now = time.monotonic()
        t_described = now - self.opts.gps_delay_s  # the autopilot fuses it against its state this long ago
        with self._lock:
            est = self.filter.estimate_at(t_described) if self.filter is not None else None
            decision = self.supervisor.decide(
                now, sigma_h_m=est.sigma_h_m if est is not None else None, last_correction_t_s=self._last_correction_t
            )
            frame = self.frame
            sats = self._gps1_sats if decision.gps1_trusted else None
        if frame is None:
            return
        t_unix = time.time() - self.opts.gps_delay_s
        out = gps_output(est, frame, t_unix, believed=decision.mode != Mode.NO_FIX, gps1_sats=sats, max_sigma_h_m=self.supervisor.cfg.max_sigma_h_m)
        if self.link.send_gps_input(out, int(t_unix * 1e6)):
            self.sent += 1
        self.log.row("gps_input", t_s=round(now, 4), fix_type=out.fix_type, lat_deg=out.lat_deg, lon_deg=out.lon_deg,
                     alt_amsl_m=round(out.alt_amsl_m, 3), horiz_accuracy_m=round(out.horiz_accuracy_m, 3), satellites=out.satellites, mode=decision.mode.value)
        if decision.status:
            self.link.send_statustext(decision.status)
            self.log.row("events", t_s=now, text=decision.status)

    # -- frames (main thread) -------------------------------------------------------------------------------

    def _process(self, frame) -> None:
        with self._lock:
            if not self._attitudes or self._rel_alt_m is None or self.filter is None:
                return
            R = R_ned_body_from_euler(*self._attitude_at(frame.t_s))
            alt = self._rel_alt_m
            prior = self.filter.prior(frame.t_s)
            mapping = self.supervisor.gps1_trusted
            # Where GPS1 puts the camera at the frame's time: the filter, which fuses GPS1 at its measurement
            # time with the IMU, interpolates between GPS1's 5 Hz readings and carries its lag.
            gps1 = self.filter.estimate_at(frame.t_s).p_ned_m if mapping else None
        # Mapping frames keep full resolution; positioning frames from closer than the map are shrunk to its scale.
        # A positioning frame looks its candidate landmarks up once; a mapping frame's self-check after the
        # mapper has changed the map looks them up again.
        cand = None if mapping else self.localiser.candidates(alt, prior)
        scale = 1.0 if mapping else self.localiser.detection_scale(alt, prior, cand)
        feats = self.detector.detect(frame.image_bgr, R @ self.R_body_cam, scale)
        if mapping:
            self.mapper.process(feats, NavSample(frame.t_s, gps1, alt, R))
        res = self.localiser.locate(feats, frame.t_s, R, alt, prior, cand)
        if not isinstance(res, Fix):
            self.log.row("fixes", t_s=frame.t_s, kind="none", reason=res.reason, n=f"{res.n_inliers}", m2="", accepted="",
                         lat_deg="", lon_deg="", sigma_m="")
            return
        with self._lock:
            if mapping:  # a self-check while GPS1 is trusted: how far the visual fix is from the filter, then
                est = self.filter.estimate_at(res.t_s)
                self.log.row("fixes", t_s=frame.t_s, kind="self-check", reason=f"{np.linalg.norm(res.p_ned_m[:2] - est.p_ned_m[:2]):.3f} m",
                             n=res.n_inliers, m2="", accepted="", **self._fix_columns(res))
                return
            d = self.filter.update_position(res.t_s, res.p_ned_m[:2], res.cov_ned_m2[:2, :2], visual=True)
            if d.accepted:
                self._last_correction_t = res.t_s
        self.log.row("fixes", t_s=frame.t_s, kind="visual", reason=d.reason, n=res.n_inliers, m2=f"{d.mahalanobis2:.2f}", accepted=d.accepted,
                     **self._fix_columns(res))

    def _fix_columns(self, res: Fix) -> dict:
        """A fix's latitude and longitude (deg) and its horizontal one-sigma (m), for the log."""
        lat_deg, lon_deg, _ = self.frame.to_geodetic(res.p_ned_m)
        return {"lat_deg": float(lat_deg), "lon_deg": float(lon_deg), "sigma_m": round(res.sigma_h_m, 3)}

    def run(self) -> int:
        self.link.start()
        timer = threading.Thread(target=self._gps_input_loop, daemon=True, name="gps-input")
        timer.start()
        t_end = None if self.opts.duration_s is None else time.monotonic() + self.opts.duration_s
        try:
            while not self._stop.is_set() and (t_end is None or time.monotonic() < t_end):
                frame = self.camera.read()
                if frame is None:
                    time.sleep(0.005)
                    continue
                self._process(frame)
        except KeyboardInterrupt:
            log.info("interrupted")
        finally:
            self._stop.set()
            timer.join(timeout=2.0)
            self.link.stop()
            self.camera.close()
            if self.opts.map_out and self.frame is not None:
                save_map(self.opts.map_out, self.landmarks, self.frame)
                log.info("map of %d landmarks saved to %s", len(self.landmarks), self.opts.map_out)
            self.log.close()
        return 0
