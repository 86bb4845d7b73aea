"""The flight's CSV logs: fixes and gate decisions, every GPS_INPUT sent, and events. One writer for a flight and
for its replay, so that the two can be compared line by line.

Files in the log folder, flushed per row (a crash loses nothing written):

- ``fixes.csv``: per frame that reached positioning: time, kind ("none", "self-check", "visual"), the reason or
  gate decision, inliers, squared Mahalanobis distance, accepted, latitude and longitude (deg), one-sigma (m), the
  sigma it was offered to the filter with (``offered_sigma_m``, widened after an ambiguous frame) and the filter's
  own sigma of it before (``filter_sigma_m``), m, and the map the fix used (``flight``, or a prior map's file name: the source most of its inliers come from);
- ``gps_input.csv``: per GPS_INPUT: time, fix type, latitude, longitude (deg), altitude AMSL and horizontal
  accuracy (m), satellites, auxgps's mode;
- ``events.csv``: time, text and the autopilot's boot time of each status line, fault and GPS1 disagreement (the
  boot time is what the autopilot's own log stamps, to find the moment there; empty in a replay);
- ``stalls.txt`` (written by ``auxgps run``, not by this class): every thread's stack at each moment the GPS_INPUT
  timer was held up (``--stall-report``); empty when nothing stalled.
"""

from __future__ import annotations

import csv
import threading
from pathlib import Path

import numpy as np

from auxgps.core.estimator import FrameResult, Output
from auxgps.core.geometry import LocalFrame


class CsvLog:
    """Append-only CSV files in one folder, flushed per row."""

    def __init__(self, folder: str | Path) -> None:
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
            self._files.clear()


def _rounded(x: float) -> str:
    return "" if not np.isfinite(x) else f"{x:.3f}"


class FlightLog(CsvLog):
    """The three logs of a flight (see the module's docstring)."""

    def frame(self, res: FrameResult, frame: LocalFrame | None) -> None:
        if res.kind == "skipped":
            return
        loc = res.located
        n = loc.n_inliers if loc is not None else ""
        if res.kind == "none" or frame is None:
            self.row("fixes", t_s=res.t_s, kind="none", reason=res.reason, n=f"{n}", m2="", accepted="", lat_deg="", lon_deg="", sigma_m="",
                     offered_sigma_m="", filter_sigma_m="", map="")
            return
        lat_deg, lon_deg, _ = frame.to_geodetic(loc.p_ned_m)
        d = res.decision
        self.row("fixes", t_s=res.t_s, kind=res.kind, reason=res.reason, n=n, m2=f"{d.mahalanobis2:.2f}" if d else "",
                 accepted=d.accepted if d else "", lat_deg=float(lat_deg), lon_deg=float(lon_deg), sigma_m=round(loc.sigma_h_rms_m, 3),
                 offered_sigma_m=_rounded(d.fix_sigma_m if d else np.nan), filter_sigma_m=_rounded(d.filter_sigma_m if d else np.nan),
                 map=loc.map_source)

    def output(self, out: Output) -> None:
        g = out.gps
        if g is None:
            return
        self.row("gps_input", t_s=round(out.t_s, 4), fix_type=g.fix_type, lat_deg=g.lat_deg, lon_deg=g.lon_deg,
                 alt_amsl_m=round(g.alt_amsl_m, 3), horiz_accuracy_m=round(g.horiz_accuracy_m, 3), satellites=g.satellites,
                 mode=out.decision.mode.value)

    def event(self, t_s: float, text: str, autopilot_boot_s: float | None = None) -> None:
        self.row("events", t_s=t_s, text=text, autopilot_boot_s="" if autopilot_boot_s is None else f"{autopilot_boot_s:.3f}")
