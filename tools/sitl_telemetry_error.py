"""How far the autopilot's telemetry is from SITL's truth in a recorded flight: attitude and GPS1 timing.

    .venv/bin/python tools/sitl_telemetry_error.py out/sitl_seneca/rec/flight.tlog [--window-s 5] [--until-s T]

Reads the flight's MAVLink log (a recording's ``flight.tlog``, as `auxgps run --record` writes it) with pymavlink:
ATTITUDE (the autopilot's EKF), GPS_RAW_INT (GPS1) and SIM_STATE (the simulator's truth, which the simulated
camera renders). Prints the EKF's roll, pitch and yaw error against the truth (overall, how the tilt error
changes over a lag, then per window of the flight, with the yaw rate), and GPS1's error against the truth at its fix time for a range of receiver lags (the
lag that fits best is what `auxgps run --gps1-lag-ms` should say). Times: SIM_STATE and ATTITUDE by their arrival,
GPS_RAW_INT's fix time (boot clock) moved onto arrival by the least ATTITUDE latency.
"""

from __future__ import annotations

import argparse

import numpy as np
import pymap3d
from pymavlink import mavutil


def read(path: str):
    m = mavutil.mavlink_connection(path)
    att, gps, sim = [], [], []
    while (msg := m.recv_match(type=["ATTITUDE", "GPS_RAW_INT", "SIM_STATE"])) is not None:
        t, kind = msg._timestamp, msg.get_type()
        if kind == "ATTITUDE":
            att.append((t, msg.time_boot_ms / 1e3, msg.roll, msg.pitch, msg.yaw))
        elif kind == "GPS_RAW_INT" and msg.fix_type >= 3:
            gps.append((msg.time_usec / 1e6, msg.lat / 1e7, msg.lon / 1e7))
        elif kind == "SIM_STATE":
            lat = msg.lat_int / 1e7 if getattr(msg, "lat_int", 0) else msg.lat
            lon = msg.lon_int / 1e7 if getattr(msg, "lon_int", 0) else msg.lng
            sim.append((t, lat, lon, msg.roll, msg.pitch, msg.yaw))
    if not (att and gps and sim):
        raise SystemExit(f"{path}: needs ATTITUDE, GPS_RAW_INT and SIM_STATE (a SITL flight's log)")
    return np.array(att), np.array(gps), np.array(sim)


def wrap_deg(a_rad: np.ndarray) -> np.ndarray:
    return np.degrees(np.angle(np.exp(1j * a_rad)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tlog")
    ap.add_argument("--window-s", type=float, default=5.0)
    ap.add_argument("--until-s", type=float, default=None, help="only the first T seconds (e.g. up to GPS1's failure)")
    args = ap.parse_args()
    att, gps, sim = read(args.tlog)
    t0 = sim[0, 0]
    sel = sim[:, 0] - t0 <= (args.until_s if args.until_s is not None else np.inf)
    s = sim[sel]
    errs = {}
    for k, name in ((2, "roll"), (3, "pitch"), (4, "yaw")):
        ekf = np.interp(s[:, 0], att[:, 0], np.unwrap(att[:, k]))
        errs[name] = wrap_deg(ekf - s[:, k + 1])
        d = errs[name]
        print(f"{name:5s}: EKF - truth {d.mean():+.3f} deg mean, {np.sqrt(np.mean(d**2)):.3f} RMS, {np.abs(d).max():.3f} max")
    # How the tilt error wanders: its change over a lag, both axes (what the filter's tilt_walk_deg_sqrt_s stands for).
    t_even = np.arange(s[0, 0] + 30.0, s[-1, 0], 0.5)  # from 30 s in: the EKF settled
    tilt = np.column_stack([np.interp(t_even, s[:, 0], errs[name]) for name in ("roll", "pitch")])
    print("tilt error's change over a lag (roll and pitch together): RMS, 99th percentile of |.|, RMS per sqrt(s)")
    for lag_s in (1, 2, 5, 10, 20):
        k = int(lag_s / 0.5)
        if len(tilt) > k:
            ch = tilt[k:] - tilt[:-k]
            rms = np.sqrt(np.mean(ch**2))
            print(f"  {lag_s:3d} s: {rms:.3f} deg, {np.percentile(np.abs(ch), 99):.3f} deg, {rms / np.sqrt(lag_s):.3f} deg/sqrt(s)")
    yaw_rate = np.degrees(np.abs(np.gradient(np.unwrap(s[:, 5]), s[:, 0])))
    print(f"per {args.window_s:g} s: yaw error mean and max |.|, truth yaw, max yaw rate")
    for k in range(0, int(s[-1, 0] - t0) + 1, int(args.window_s)):
        w = (s[:, 0] - t0 >= k) & (s[:, 0] - t0 < k + args.window_s)
        if w.any():
            print(f"  {k:5d} s  {errs['yaw'][w].mean():+6.2f}  {np.abs(errs['yaw'][w]).max():5.2f} deg  "
                  f"yaw {np.degrees(s[w, 5].mean()) % 360:6.1f}  rate {yaw_rate[w].max():5.1f} deg/s")
    # GPS1 against the truth at its fix time, for a range of receiver lags.
    offset = np.min(att[:, 0] - att[:, 1])  # arrival - boot: the least latency
    lat0, lon0 = s[0, 1], s[0, 2]
    n, e, _ = pymap3d.geodetic2ned(s[:, 1], s[:, 2], 0.0, lat0, lon0, 0.0)
    gn, ge, _ = pymap3d.geodetic2ned(gps[:, 1], gps[:, 2], 0.0, lat0, lon0, 0.0)
    tg = gps[:, 0] + offset
    inside = (tg >= s[0, 0] + 0.5) & (tg <= s[-1, 0])
    speed = np.hypot(np.gradient(n, s[:, 0]), np.gradient(e, s[:, 0]))
    fast = inside & (np.interp(tg, s[:, 0], speed) > 3.0)
    print("GPS1 - truth at the fix time less the lag (RMS over the whole flight, and over 3 m/s and faster):")
    for lag in np.arange(0.0, 0.301, 0.025):
        dn = gn - np.interp(tg - lag, s[:, 0], n)
        de = ge - np.interp(tg - lag, s[:, 0], e)
        d2 = dn**2 + de**2
        fast_rms = np.sqrt(d2[fast].mean()) if fast.any() else float("nan")
        print(f"  lag {1000 * lag:5.0f} ms: {np.sqrt(d2[inside].mean()):.3f} m, fast {fast_rms:.3f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
