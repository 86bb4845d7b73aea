#!/usr/bin/env python3
"""The accepted visual fixes of SITL flights after GPS1's failure, against SITL's truth, by their inlier count.

    .venv/bin/python tools/fix_tally.py FLIGHT_DIR [FLIGHT_DIR ...]

FLIGHT_DIR: what ``tools/sitl_flight.py --out`` wrote (``run/fixes.csv``, ``truth.csv`` and the recording's
``rec/recording.json``); the failure's time is ``truth.csv``'s, as ``sitl_flight.score_logs`` scores from it.
Per inlier count (10 and more together): fixes, their error's RMS and maximum (m), their claimed sigma's median
(m), error over sigma (RMS, 99th percentile), how many over 0.5 m; then over all: those over 0.5 m with their error
over sigma, and the share beyond 3 sigma.
"""
import csv
import json
import sys

import numpy as np

from auxgps.sim.world import load_world


def flight_fixes(flight_dir: str) -> np.ndarray:
    """(K, 3): error (m), claimed sigma (m), inliers of each accepted visual fix after GPS1 failed."""
    meta = json.load(open(f"{flight_dir}/rec/recording.json"))
    frame = load_world(meta["options"]["camera"].split("sim:")[1]).frame
    truth = np.genfromtxt(f"{flight_dir}/truth.csv", delimiter=",", names=True)
    t_lost = float(truth["t_s"][np.argmax(truth["gps1_failed"] > 0)])
    rows = [r for r in csv.DictReader(open(f"{flight_dir}/run/fixes.csv"))
            if r["kind"] == "visual" and r["accepted"] == "True" and float(r["t_s"]) >= t_lost]
    t = np.array([float(r["t_s"]) for r in rows])
    p = frame.to_ned(lat_deg=np.array([float(r["lat_deg"]) for r in rows]), lon_deg=np.array([float(r["lon_deg"]) for r in rows]),
                     alt_amsl_m=np.full(len(rows), frame.alt_amsl_m))[:, :2]
    p_true = np.column_stack([np.interp(t, truth["t_s"], truth["north_m"]), np.interp(t, truth["t_s"], truth["east_m"])])
    return np.column_stack([np.linalg.norm(p - p_true, axis=1), [float(r["sigma_m"]) for r in rows], [int(r["n"]) for r in rows]])


def main(flight_dirs: list[str]) -> None:
    fixes = np.vstack([flight_fixes(d) for d in flight_dirs])
    err, sigma, n = fixes.T
    z = err / sigma
    for k in sorted(set(np.minimum(n, 10).astype(int))):
        m = np.minimum(n, 10) == k
        print(f"{k}{'+' if k == 10 else ''} inliers: {m.sum()} fixes, error RMS {np.sqrt(np.mean(err[m] ** 2)):.3f} max {err[m].max():.3f} m, "
              f"sigma median {np.median(sigma[m]):.3f} m, error/sigma RMS {np.sqrt(np.mean(z[m] ** 2)):.2f} p99 {np.percentile(z[m], 99):.2f}, "
              f"over 0.5 m {(err[m] > 0.5).sum()}")
    over = err > 0.5
    print(f"all: {len(err)} fixes, {over.sum()} over 0.5 m (error/sigma {', '.join(f'{v:.2f}' for v in z[over])}), "
          f"beyond 3 sigma {np.mean(z > 3):.4f}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
