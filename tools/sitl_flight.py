#!/usr/bin/env python3
"""Fly ArduPilot's own copter SITL through a GPS1 failure with auxgps as GPS2, and report the landing.

    ARDUPILOT_SITL=../shared/sitl/arducopter .venv/bin/python tools/sitl_flight.py [--world W] [--out DIR] [--busy N]

Starts SITL in a scratch folder (its defaults file beside the binary, plus config/ardupilot/auxgps-gps2.parm),
connects a ground-station script on SERIAL0 (TCP 5760) and `auxgps run` on SERIAL1 (TCP 5762) with the world
rendered at SIM_STATE's truth. The script arms in GUIDED, takes off to 15 m, flies the thesis' survey over the
world (a 20 m x 20 m lawnmower, north-south legs 2 m apart, at 1 m/s; each leg ends when the autopilot's own
position, GLOBAL_POSITION_INT, is within 0.7 m of its end), disables GPS1 (SIM_GPS1_ENABLE = 0) after
the third leg, finishes the survey on GPS2 (more than 3 minutes), switches to RTL and waits for the landing.
Prints one JSON line: landing_error_m (true distance from home), denied_s, the autopilot's horizontal error after
the failure (rms, max), and whether GPS2 carried a 3D fix; writes result.json, the truth track (truth.csv) and
auxgps's logs (run/) to --out. Exit 0 if it landed within 1 m. ``--busy N`` keeps N processes spinning at normal
priority for the whole flight (a companion computer's other work); ``--run-args="..."`` adds options to
`auxgps run`. The JSON also gives the intervals between the GPS_INPUT messages sent (ArduPilot's rule: a mean under
215 ms, never two in a row over 245 ms), the autopilot's failsafe and EKF STATUSTEXTs, and from SITL's dataflash
log how long after GPS1 was disabled ArduPilot made another GPS primary (``gps_primary_changed_after_s``). ``--faults FILE`` takes
the fault file of `auxgps eval --faults` and applies its GPS1 faults through SITL's own parameters, ``at_s`` after
take-off: a drag by SIM_GPS1_GLTCH_X/Y (set five times a second), an inflated accuracy by SIM_GPS1_ACC (the
reported accuracy only), dropouts by SIM_GPS1_ENABLE. ``--mission FILE --gps-lost-at-waypoint N [--alt-m A]
[--speed-m-s V]`` flies a mission file (as `auxgps eval --mission` reads it) in AUTO instead: uploaded by the
MAVLink mission protocol, taken off in GUIDED, GPS1 disabled when the autopilot reports item N reached, and the
mission's own landing (or an RTL where it ends without one) flown on auxgps.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
import numpy as np  # noqa: E402
import pymap3d  # noqa: E402
from pymavlink import mavutil  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
M = mavutil.mavlink
SPEED_M_S = 1.0
# The thesis' survey: north-south legs from east -10 m to +10 m, 2 m apart, north -10 m to +10 m.
WAYPOINTS_NE_M = [(n, e) for k, e in enumerate(range(-10, 11, 2)) for n in ((-10, 10) if k % 2 == 0 else (10, -10))]
GPS_DELAY_MS = 100  # auxgps run --gps-delay-ms, as GPS2_DELAY_MS in config/ardupilot/auxgps-gps2.parm
FAIL_AFTER_WAYPOINT = 5  # GPS1 is disabled at the end of the third leg


class StealClock:
    """The time the hypervisor took each virtual CPU away (/proc/stat's steal), sampled about once a second: a
    guest's thread that holds Python's interpreter lock stops every thread of its process while its CPU is taken
    (docs/faults.md). Nothing on a machine without /proc/stat or steal accounting."""

    def __init__(self, every_s: float = 1.0) -> None:
        self.every_s, self._hz = every_s, os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self._last: tuple[float, list[int]] | None = None
        self.spells: list[tuple[float, int, float]] = []  # (monotonic s at the sample's end, cpu, steal s) over 0.2 s
        self.total_s = 0.0

    @staticmethod
    def _read() -> list[int] | None:
        try:
            with open("/proc/stat") as f:
                return [int(line.split()[8]) for line in f if line.startswith("cpu") and line[3].isdigit()]
        except (OSError, IndexError, ValueError):
            return None

    def sample(self) -> None:
        now = time.monotonic()
        if self._last is not None and now - self._last[0] < self.every_s:
            return
        steal = self._read()
        if steal is None:
            return
        if self._last is not None:
            for cpu, (a, b) in enumerate(zip(self._last[1], steal)):
                d_s = (b - a) / self._hz
                self.total_s += d_s
                if d_s >= 0.2:
                    self.spells.append((round(now, 3), cpu, d_s))
        self._last = (now, steal)

    def figures(self) -> dict:
        return {"total_s": round(self.total_s, 2), "spells_over_0_2s": self.spells}


class GroundStation:
    def __init__(self, home):
        self.home = home
        self.c = mavutil.mavlink_connection("tcp:127.0.0.1:5760", source_system=255)
        self.c.wait_heartbeat(timeout=60)
        for mid, hz in ((33, 10), (108, 10), (24, 5), (124, 5)):
            self.c.mav.command_long_send(1, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mid, 1e6 / hz, 0, 0, 0, 0, 0)
        self.last = {}
        self.track: list[tuple[float, float, float]] = []  # (monotonic s, north m, east m): the truth, to score
        self.failed_at_mono: float | None = None  # when GPS1 was disabled, monotonic s
        self.statustexts: list[str] = []  # the autopilot's, after arming
        self.faults: list = []  # auxgps.sim.faults.Fault: the GPS1 ones are applied through SITL's parameters
        self.takeoff_mono: float | None = None
        self._fault_params: dict[str, float] = {}
        self._fault_tick_mono = 0.0
        self.reached: set[int] = set()  # mission items the autopilot said it reached (MISSION_ITEM_REACHED)
        self.steal = StealClock()

    def apply_faults(self):
        """Set SITL's GPS1 parameters for the faults under way (five times a second at most; only changes sent)."""
        now = time.monotonic()
        if not self.faults or self.takeoff_mono is None or now - self._fault_tick_mono < 0.2:
            return
        self._fault_tick_mono = now
        from auxgps.sim.faults import offset_deg  # (the repository is on the path once main has run)

        t = now - self.takeoff_mono
        want = {"SIM_GPS1_GLTCH_X": 0.0, "SIM_GPS1_GLTCH_Y": 0.0, "SIM_GPS1_ACC": 0.3}
        if self.failed_at_mono is None:
            want["SIM_GPS1_ENABLE"] = 1.0
        for f in self.faults:
            if f.kind == "gps1_drag" and f.in_effect(t):
                dlat, dlon = offset_deg(self.home[0], f.drag_ne_m(t))
                want["SIM_GPS1_GLTCH_X"] += dlat
                want["SIM_GPS1_GLTCH_Y"] += dlon
            elif f.kind == "gps1_inflated" and f.active(t):
                want["SIM_GPS1_ACC"] = max(want["SIM_GPS1_ACC"], f.h_acc_m)
            elif f.kind == "gps1_dropout" and f.gps1_silent(t) and self.failed_at_mono is None:
                want["SIM_GPS1_ENABLE"] = 0.0
        for name, value in want.items():
            if self._fault_params.get(name) != value:
                self._fault_params[name] = value
                self.c.mav.param_set_send(1, 1, name.encode(), value, M.MAV_PARAM_TYPE_REAL32)

    def pump(self, seconds):
        t_end = time.time() + seconds
        while time.time() < t_end:
            msg = self.c.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() != M.MAV_COMP_ID_AUTOPILOT1:
                continue  # auxgps's own heartbeat, forwarded by the autopilot
            self.last[msg.get_type()] = msg
            if msg.get_type() == "MISSION_ITEM_REACHED":
                self.reached.add(int(msg.seq))
            if msg.get_type() == "SIM_STATE":
                self.track.append((time.monotonic(), *self.ne(msg.lat_int / 1e7, msg.lon_int / 1e7)))
                self.apply_faults()
                self.steal.sample()
            if msg.get_type() == "STATUSTEXT" and "Arm" not in msg.text:
                print("AP:", msg.text, file=sys.stderr, flush=True)
                if msg.get_srcComponent() == M.MAV_COMP_ID_AUTOPILOT1:
                    self.statustexts.append(msg.text)

    def ne(self, lat_deg, lon_deg):
        n, e, _ = pymap3d.geodetic2ned(lat_deg, lon_deg, self.home[2], *self.home)
        return float(n), float(e)

    def truth(self):
        s = self.last.get("SIM_STATE")
        return None if s is None else self.ne(s.lat_int / 1e7, s.lon_int / 1e7)

    def estimate(self):
        g = self.last.get("GLOBAL_POSITION_INT")
        return None if g is None else self.ne(g.lat / 1e7, g.lon / 1e7)

    def armed(self):
        hb = self.last.get("HEARTBEAT")
        return bool(hb and hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)


def lag_correlation(t_s: np.ndarray, err_ne_m: np.ndarray, lags_s=(0.1, 1.0, 4.0), tol_s: float = 0.05) -> dict:
    """How the fixes' north and east errors hang together in time: for each lag, the correlation of each fix's
    error with that of the first fix at least the lag later (pairs within ``tol_s`` of the lag only). Near 0 at
    0.1 s for errors that are new every frame; near 1 for an error shared over seconds (an autopilot's slow
    attitude error, the map's own), which is what the filter's shared-error state stands for."""
    out = {}
    for lag in lags_s:
        j = np.searchsorted(t_s, t_s + lag)
        ok = j < len(t_s)
        ok[ok] &= np.abs(t_s[j[ok]] - t_s[ok] - lag) <= tol_s
        if ok.sum() < 3:
            out[f"{lag:g}s"] = None
            continue
        a, b = err_ne_m[ok], err_ne_m[j[ok]]
        out[f"{lag:g}s"] = [round(float(np.corrcoef(a[:, k], b[:, k])[0, 1]), 2) for k in (0, 1)]
    return out


def timeline(fix_rows: list, sent_rows: list, failed_at_mono: float, delay_s: float, scored: dict, bin_s: float = 20.0) -> list:
    """What auxgps did after the failure, every ``bin_s`` (to tell a failed flight's story from its JSON alone):
    per bin, the visual fixes accepted and refused, the most frequent reason a frame gave none, the share of
    GPS_INPUT sent with a 3D fix, and the largest error and sigma of those (``scored``: time -> (error, sigma))."""
    out = []
    t_end = max([float(r["t_s"]) for r in sent_rows] + [failed_at_mono])
    for t0 in np.arange(failed_at_mono, t_end, bin_s):
        fx = [r for r in fix_rows if t0 <= float(r["t_s"]) < t0 + bin_s]
        sent = [r for r in sent_rows if t0 <= float(r["t_s"]) - delay_s < t0 + bin_s]
        none = [r["reason"][:48] for r in fx if r["kind"] == "none"]
        errs = [v for t, v in scored.items() if t0 <= t < t0 + bin_s]
        out.append({"t_s": round(float(t0 - failed_at_mono)), "accepted": sum(r["kind"] == "visual" and r["accepted"] == "True" for r in fx),
                    "refused": sum(r["kind"] == "visual" and r["accepted"] != "True" for r in fx),
                    "no_fix": len(none), "no_fix_reason": max(set(none), key=none.count) if none else "",
                    "share_3d": round(sum(r["fix_type"] == "3" for r in sent) / len(sent), 2) if sent else None,
                    "max_err_m": round(max(e for e, _ in errs), 2) if errs else None,
                    "max_sigma_m": round(max(s for _, s in errs), 2) if errs else None})
    return out


#: ArduPilot's dataflash event for a change of primary GPS (LogEvent::GPS_PRIMARY_CHANGED; no STATUSTEXT says it).
EV_GPS_PRIMARY_CHANGED = 67


def primary_changes_after_gps1_off(bin_path: Path) -> list[float]:
    """Seconds from the first ``SIM_GPS1_ENABLE = 0`` in SITL's dataflash log to each change of primary GPS after it
    (empty: GPS1 never disabled, or no change), on the autopilot's own clock."""
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(bin_path))
    off_us, changes = None, []
    while (m := log.recv_match(type=["PARM", "EV"])) is not None:
        if m.get_type() == "PARM" and m.Name == "SIM_GPS1_ENABLE" and m.Value == 0 and off_us is None:
            off_us = m.TimeUS
        elif m.get_type() == "EV" and m.Id == EV_GPS_PRIMARY_CHANGED and off_us is not None:
            changes.append(round((m.TimeUS - off_us) / 1e6, 3))
    return changes


def score_logs(gs: GroundStation, run_dir: Path, failed_at_mono: float, delay_s: float) -> dict:
    """auxgps's own logs against the truth track (one machine, one monotonic clock): its visual fixes and the
    GPS_INPUT it sent while GPS1 was down. A GPS_INPUT describes the vehicle ``delay_s`` before it was sent."""
    track = np.array(gs.track)

    def errors(rows, t_key, shift_s):
        """(K, 2) north/east errors (m) of the rows inside the failure, their times (K,) and which rows they are."""
        t = np.array([float(r[t_key]) for r in rows]) - shift_s
        ne = np.array([gs.ne(float(r["lat_deg"]), float(r["lon_deg"])) for r in rows]).reshape(-1, 2)
        keep = (t >= failed_at_mono) & (t <= track[-1, 0])
        truth = np.column_stack([np.interp(t[keep], track[:, 0], track[:, k]) for k in (1, 2)])
        return ne[keep] - truth, t[keep], keep

    def stats(e):
        return {"count": int(len(e)), "rms_m": round(float(np.sqrt(np.mean(e**2))), 3) if len(e) else None,
                "p95_m": round(float(np.percentile(e, 95)), 3) if len(e) else None, "max_m": round(float(e.max()), 3) if len(e) else None}

    fixes = [r for r in csv.DictReader(open(run_dir / "fixes.csv")) if r["kind"] == "visual"]
    fix_err_ne, fix_t, keep = errors(fixes, "t_s", 0.0)
    fix_err = np.linalg.norm(fix_err_ne, axis=1)
    accepted = np.array([r["accepted"] == "True" for r in fixes])[keep]
    sent = [r for r in csv.DictReader(open(run_dir / "gps_input.csv")) if r["fix_type"] == "3"]
    out_err_ne, _, keep = errors(sent, "t_s", delay_s)
    out_err = np.linalg.norm(out_err_ne, axis=1)
    sigma = np.array([float(r["horiz_accuracy_m"]) for r in sent])[keep]
    sent_t = np.array([float(r["t_s"]) for r in csv.DictReader(open(run_dir / "gps_input.csv"))])
    gaps_ms = np.diff(sent_t) * 1e3
    late = gaps_ms > 245.0
    all_rows = list(csv.DictReader(open(run_dir / "fixes.csv")))
    all_sent = list(csv.DictReader(open(run_dir / "gps_input.csv")))
    return {
        "timeline": timeline(all_rows, all_sent, failed_at_mono, delay_s, dict(zip(np.array(
            [float(r["t_s"]) for r in sent])[keep] - delay_s, zip(out_err, sigma)))),
        "gps_input_intervals_ms": {"mean": round(float(gaps_ms.mean()), 1), "max": round(float(gaps_ms.max()), 1),
                                   "over_245": int(late.sum()), "two_in_a_row_over_245": int(np.sum(late[1:] & late[:-1]))},
        "fixes": {**stats(fix_err), "accepted_over_0_5m": int(np.sum(accepted & (fix_err > 0.5))),
                  "error_correlation_ne": lag_correlation(fix_t, fix_err_ne)},
        "gps_input_3d": {**stats(out_err), "within_3sigma": round(float(np.mean(out_err <= 3 * sigma)), 3) if len(out_err) else None},
    }


def write_truth(gs: GroundStation, path: Path) -> None:
    """The truth track beside auxgps's logs, on the same monotonic clock, so that a flight can be scored again
    (a fix's error, how its errors hang together in time) without flying it again."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "north_m", "east_m", "gps1_failed"])
        for t, n, e in gs.track:
            w.writerow([f"{t:.4f}", f"{n:.4f}", f"{e:.4f}", int(gs.failed_at_mono is not None and t >= gs.failed_at_mono)])


def arm_and_take_off(gs: GroundStation, height_m: float) -> None:
    """Arm in GUIDED (asked again every 3 s, for up to 180 s) and command a take-off to ``height_m``."""
    t0 = time.time()
    while not gs.armed():
        if time.time() - t0 > 180:
            raise RuntimeError("SITL would not arm within 180 s")
        gs.c.set_mode("GUIDED")
        gs.c.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        gs.pump(3)
    gs.c.mav.command_long_send(1, 1, M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, height_m)
    gs.takeoff_mono = time.monotonic()


def fail_gps1(gs: GroundStation) -> float:
    """Disable SITL's GPS1 now; returns the wall time it was done at (and keeps the monotonic one, to score)."""
    gs.c.mav.param_set_send(1, 1, b"SIM_GPS1_ENABLE", 0, M.MAV_PARAM_TYPE_REAL32)
    gs.failed_at_mono = time.monotonic()
    return time.time()


def sample_after_failure(gs: GroundStation, errors: list, gps2_fixes: set) -> None:
    """The autopilot's error against the truth now, and GPS2's fix type."""
    tr, es = gs.truth(), gs.estimate()
    if tr and es:
        errors.append(math.dist(tr, es))
        g2 = gs.last.get("GPS2_RAW")
        gps2_fixes.add(g2.fix_type if g2 else None)


def flight_figures(gs: GroundStation, failed_at: float | None, errors: list, gps2_fixes: set) -> dict:
    """landed, the landing's distance from home, time on auxgps, the autopilot's error after the failure, GPS2's
    fix types."""
    return {
        "landed": not gs.armed(),
        "landing_error_m": round(math.hypot(*gs.truth()), 3),
        "denied_s": round(time.time() - failed_at, 1) if failed_at else None,
        "error_after_failure_m": {"rms": round(math.sqrt(sum(x * x for x in errors) / len(errors)), 3) if errors else None,
                                  "max": round(max(errors), 3) if errors else None},
        "gps2_fix_types_seen": sorted(x for x in gps2_fixes if x is not None),
    }


def fly(gs: GroundStation) -> dict:
    arm_and_take_off(gs, 15)
    gs.pump(20)
    # WPNAV_SPEED (cm/s) paces guided legs and RTL alike; DO_CHANGE_SPEED the current guided target.
    gs.c.mav.param_set_send(1, 1, b"WPNAV_SPEED", SPEED_M_S * 100, M.MAV_PARAM_TYPE_REAL32)
    gs.c.mav.command_long_send(1, 1, M.MAV_CMD_DO_CHANGE_SPEED, 0, 1, SPEED_M_S, -1, 0, 0, 0, 0)
    failed_at, errors, gps2_fixes = None, [], set()
    here = (0.0, 0.0)
    for i, (n, e) in enumerate(WAYPOINTS_NE_M):
        lat, lon, _ = pymap3d.ned2geodetic(n, e, 0, *gs.home)
        gs.c.mav.set_position_target_global_int_send(
            0, 1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b110111111000, int(lat * 1e7), int(lon * 1e7), 15, 0, 0, 0, 0, 0, 0, 0, 0)
        t_leg = time.time()
        leg_timeout_s = math.dist(here, (n, e)) / SPEED_M_S + 20.0
        here = (n, e)
        while time.time() - t_leg < leg_timeout_s:
            gs.pump(0.5)
            if failed_at:
                sample_after_failure(gs, errors, gps2_fixes)
            # The autopilot's own position says the leg is done, as WP_RADIUS does in AUTO (and the emulator's
            # guide): a vehicle on auxgps that waited for the truth to come within 0.7 m hovered on, over bare
            # ground, until the leg timed out.
            es = gs.estimate()
            if es and math.dist(es, (n, e)) < 0.7:
                break
        if i == FAIL_AFTER_WAYPOINT:
            failed_at = fail_gps1(gs)
    gs.c.set_mode("RTL")
    t_rtl = time.time()
    while time.time() - t_rtl < 180:
        gs.pump(1)
        tr, es = gs.truth(), gs.estimate()
        if tr and es:
            errors.append(math.dist(tr, es))
        if not gs.armed() and time.time() - t_rtl > 5:
            break
    return flight_figures(gs, failed_at, errors, gps2_fixes)


def mission_items(mission, home, alt_m: float | None) -> list:
    """MISSION_ITEM_INT messages for ``mission``, item 0 home, every other item as its file numbers it; with
    ``alt_m``, every place the vehicle flies to at that height above home (land and return keep theirs)."""
    items = [M.MAVLink_mission_item_int_message(1, 1, 0, M.MAV_FRAME_GLOBAL, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                                int(home[0] * 1e7), int(home[1] * 1e7), home[2], M.MAV_MISSION_TYPE_MISSION)]
    for it in mission.items:
        frame, z = it.frame, it.alt_m
        if alt_m is not None and it.has_place and it.command not in (M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_RETURN_TO_LAUNCH):
            frame, z = M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, alt_m
        frame = {M.MAV_FRAME_GLOBAL: M.MAV_FRAME_GLOBAL_INT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT: M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                 M.MAV_FRAME_GLOBAL_TERRAIN_ALT: M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}.get(frame, frame)
        params = [0.0 if not math.isfinite(v) else v for v in it.params]
        items.append(M.MAVLink_mission_item_int_message(1, 1, len(items), frame, it.command, 0, 1, *params,
                                                        int(round(it.lat_deg * 1e7)), int(round(it.lon_deg * 1e7)), z,
                                                        M.MAV_MISSION_TYPE_MISSION))
    return items


def upload_mission(gs: GroundStation, items: list, timeout_s: float = 60.0) -> None:
    """The MAVLink mission protocol: MISSION_COUNT, then each item the autopilot asks for, until its ACK. Just
    after boot ArduPilot answers NO_SPACE (its mission storage is not up yet): asked again every 2 s."""
    t_end = time.time() + timeout_s
    refused = None
    while time.time() < t_end:
        gs.c.mav.mission_count_send(1, 1, len(items), M.MAV_MISSION_TYPE_MISSION)
        t_try = time.time() + 10.0
        while time.time() < min(t_try, t_end):
            msg = gs.c.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], blocking=True, timeout=1.0)
            if msg is None:
                continue
            if msg.get_type() != "MISSION_ACK":
                gs.c.mav.send(items[msg.seq])
                continue
            if msg.type == M.MAV_MISSION_ACCEPTED:
                return
            refused = M.enums["MAV_MISSION_RESULT"][msg.type].name
            break
        gs.pump(2.0)
    raise RuntimeError(f"SITL did not take the mission within {timeout_s:g} s (last answer: {refused})")


def fly_mission(gs: GroundStation, mission, alt_m: float | None, speed_m_s: float, lost_at_seq: int) -> dict:
    """Arm in GUIDED, take off, fly ``mission`` in AUTO; GPS1 off on reaching item ``lost_at_seq``; the mission's
    own landing (or RTL once it ends) on auxgps. The figures of :func:`fly`."""
    items = mission_items(mission, gs.home, alt_m)
    if not 0 < lost_at_seq < len(items):
        raise SystemExit(f"--gps-lost-at-waypoint {lost_at_seq}: the mission has items 1 to {len(items) - 1}")
    upload_mission(gs, items)
    takeoff_m = alt_m if alt_m is not None else next((it.alt_m for it in mission.items if it.command == M.MAV_CMD_NAV_TAKEOFF), 15.0)
    arm_and_take_off(gs, takeoff_m)
    gs.c.mav.param_set_send(1, 1, b"WPNAV_SPEED", speed_m_s * 100, M.MAV_PARAM_TYPE_REAL32)
    t_up = time.time()
    while time.time() - t_up < 60:
        gs.pump(0.5)
        g = gs.last.get("GLOBAL_POSITION_INT")
        if g is not None and g.relative_alt / 1000.0 >= 0.95 * takeoff_m:
            break
    gs.c.mav.mission_set_current_send(1, 1, 1)
    gs.c.set_mode("AUTO")
    places = [(0.0, 0.0)] + [gs.ne(it.lat_deg, it.lon_deg) for it in mission.items if it.has_place and (it.lat_deg or it.lon_deg)]
    path_m = sum(math.dist(a, b) for a, b in zip(places, places[1:] + [(0.0, 0.0)]))
    t_end = time.time() + path_m / speed_m_s * 1.5 + 240.0
    failed_at, errors, gps2_fixes = None, [], set()
    while time.time() < t_end:
        gs.pump(0.5)
        if failed_at is None and (lost_at_seq in gs.reached or any(s > lost_at_seq for s in gs.reached)):
            failed_at = fail_gps1(gs)
        if failed_at:
            sample_after_failure(gs, errors, gps2_fixes)
        if failed_at and not gs.armed():
            break
        hb = gs.last.get("HEARTBEAT")
        if hb is not None and gs.armed() and mavutil.mode_string_v10(hb) not in ("AUTO", "RTL", "LAND"):
            gs.c.set_mode("RTL")  # the mission ended without a landing: ArduPilot holds; bring it home
    return {**flight_figures(gs, failed_at, errors, gps2_fixes), "mission_items_reached": sorted(gs.reached), "path_m": round(path_m, 1)}


class PtyPair:
    """Two pseudo-terminals joined back to back (what ``socat pty,raw pty,raw`` makes): SITL opens one end as its
    SERIAL1 UART, auxgps the other, and the bytes cross as on a flight controller's serial port."""

    def __init__(self) -> None:
        import pty
        import threading
        import tty

        (self._m1, s1), (self._m2, s2) = pty.openpty(), pty.openpty()
        for fd in (s1, s2):
            tty.setraw(fd)
        self.a, self.b = os.ttyname(s1), os.ttyname(s2)
        self._slaves = (s1, s2)
        self._stop = threading.Event()
        self.bytes = [0, 0]
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self._m1, self._m2], [], [], 0.1)
            for src, dst, k in ((self._m1, self._m2, 0), (self._m2, self._m1, 1)):
                if src in ready:
                    try:
                        data = os.read(src, 65536)
                        os.write(dst, data)
                        self.bytes[k] += len(data)
                    except OSError:
                        pass


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sitl", default=os.environ.get("ARDUPILOT_SITL"))
    ap.add_argument("--world", default=str(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml"))
    ap.add_argument("--out", default=str(REPO / "out" / "sitl"))
    ap.add_argument("--serial", action="store_true", help="SERIAL1 on a pseudo-terminal pair at 921600 baud, not TCP 5762")
    ap.add_argument("--busy", type=int, default=0, help="processes spinning at normal priority for the whole flight")
    ap.add_argument("--run-args", default="", help="more options for auxgps run, as one string")
    ap.add_argument("--faults", help="fault file (auxgps eval --faults): its GPS1 faults, at_s after take-off")
    ap.add_argument("--mission", help="fly this mission file (.waypoints or .plan) in AUTO instead of the survey")
    ap.add_argument("--alt-m", type=float, help="with --mission: every height at this many metres above home")
    ap.add_argument("--speed-m-s", type=float, default=5.0, help="with --mission: WPNAV_SPEED, m/s (default 5)")
    ap.add_argument("--gps-lost-at-waypoint", type=int, help="with --mission: GPS1 off on reaching this item")
    args = ap.parse_args(argv)
    if bool(args.mission) != (args.gps_lost_at_waypoint is not None):
        ap.error("--mission and --gps-lost-at-waypoint go together")
    if not args.sitl or not Path(args.sitl).exists():
        print("no SITL binary: set ARDUPILOT_SITL or --sitl", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO))
    from auxgps.sim.world import load_world

    origin = load_world(args.world).frame
    home = (origin.lat_deg, origin.lon_deg, origin.alt_amsl_m)
    defaults = ",".join(str(p) for p in (Path(args.sitl).parent / "copter.parm", REPO / "config" / "ardupilot" / "auxgps-gps2.parm") if p.exists())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scratch = tempfile.mkdtemp(prefix="sitl-")
    line = PtyPair() if args.serial else None
    serial = [f"--serial1=uart:{line.a}:921600"] if line else []
    connect = f"{line.b},921600" if line else "tcp:127.0.0.1:5762"
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    sitl = subprocess.Popen([args.sitl, "--model", "quad", "--speedup", "1", "-I0", "--defaults", defaults, *serial,
                             "--home", f"{home[0]},{home[1]},{home[2]},0"], cwd=scratch,
                            stdout=open(out / "sitl.log", "w"), stderr=subprocess.STDOUT)
    run = None
    try:
        time.sleep(2)
        gs = GroundStation(home)
        if args.faults:
            from auxgps.sim.faults import load_fault_plan

            gs.faults = [f for f in load_fault_plan(args.faults).faults if f.kind.startswith("gps1_")]
        run = subprocess.Popen([sys.executable, "-m", "auxgps.cli", "run", "--connect", connect,
                                "--camera", f"sim:{args.world}", "--log-dir", str(out / "run"), "--duration", "1500",
                                "--gps-delay-ms", str(GPS_DELAY_MS), "--record", str(out / "rec"), *shlex.split(args.run_args)],
                               cwd=REPO, stdout=open(out / "run.log", "w"), stderr=subprocess.STDOUT)
        if args.mission:
            from auxgps.io.mission import load_mission

            result = fly_mission(gs, load_mission(args.mission), args.alt_m, args.speed_m_s, args.gps_lost_at_waypoint)
        else:
            result = fly(gs)
        run.terminate()
        run.wait(timeout=20)
        write_truth(gs, out / "truth.csv")
        result["auxgps"] = score_logs(gs, out / "run", gs.failed_at_mono, GPS_DELAY_MS / 1000.0)
        result["autopilot_said"] = [t for t in gs.statustexts if any(w in t for w in ("ailsafe", "EKF", "GPS", "variance"))]
        result["auxgps_said"] = [r["text"] for r in csv.DictReader(open(out / "run" / "events.csv"))][-40:]
        result["busy_processes"] = args.busy
        result["cpu_steal"] = gs.steal.figures()  # beside events.csv's "GPS_INPUT timer held up" (the same clock)
        logs = sorted(Path(scratch, "logs").glob("*.BIN"))
        changes = primary_changes_after_gps1_off(logs[-1]) if logs else []
        result["gps_primary_changed_after_s"] = changes[0] if changes else None
    finally:
        for p in busy:
            p.kill()
            p.wait()
        for p in (run, sitl):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(timeout=20)
    if line is not None:
        result["serial_bytes"] = {"sitl_to_auxgps": line.bytes[0], "auxgps_to_sitl": line.bytes[1]}
    print(json.dumps(result))
    (out / "result.json").write_text(json.dumps(result, indent=2))
    return 0 if result["landed"] and result["landing_error_m"] <= 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
