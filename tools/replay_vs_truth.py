#!/usr/bin/env python3
"""A real SITL flight's GPS_INPUT, or a replay of its recording, against SITL's truth, after GPS1 failed.

    .venv/bin/python tools/replay_vs_truth.py FLIGHT_DIR [RUN_DIR ...] [--parts 6] [--last-s 8]

FLIGHT_DIR: what ``tools/sitl_flight.py --out`` wrote (``truth.csv``, ``rec/recording.json``, ``run/``); each
RUN_DIR holds a ``gps_input.csv`` and ``fixes.csv``, as ``auxgps replay REC --out RUN_DIR`` writes them (default:
the flight's own ``run/``). A replay feeds the recorded frames and telemetry through today's estimator, so the
same flight can be scored under two versions of the code (the vehicle flies the path it flew). For each run: the
GPS_INPUT messages with a 3D fix from GPS1's failure on (error RMS and max, m; inside 3x their accuracy), the same
per part of that time, the accepted visual fixes' largest error, and the last seconds, message by message.
A GPS_INPUT describes the vehicle ``gps_delay_s`` (the recording's option) before it was sent.
"""
import argparse
import csv
import json

import numpy as np

from auxgps.sim.world import load_world


def errors(rows: list, frame, truth, shift_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Times (K,) and horizontal errors (K,) of ``rows`` (lat_deg, lon_deg, t_s) against the truth track."""
    t = np.array([float(r["t_s"]) for r in rows]) - shift_s
    p = frame.to_ned(lat_deg=np.array([float(r["lat_deg"]) for r in rows]), lon_deg=np.array([float(r["lon_deg"]) for r in rows]),
                     alt_amsl_m=np.full(len(rows), frame.alt_amsl_m))[:, :2]
    p_true = np.column_stack([np.interp(t, truth["t_s"], truth["north_m"]), np.interp(t, truth["t_s"], truth["east_m"])])
    return t, np.linalg.norm(p - p_true, axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight_dir")
    ap.add_argument("run_dirs", nargs="*")
    ap.add_argument("--parts", type=int, default=6, help="into how many equal parts the time after the failure is cut")
    ap.add_argument("--last-s", type=float, default=8.0, help="list the messages of the last this many seconds")
    a = ap.parse_args()
    meta = json.load(open(f"{a.flight_dir}/rec/recording.json"))
    frame = load_world(meta["options"]["camera"].split("sim:")[1]).frame
    delay_s = float(meta["options"]["gps_delay_s"])
    truth = np.genfromtxt(f"{a.flight_dir}/truth.csv", delimiter=",", names=True)
    t_lost = float(truth["t_s"][np.argmax(truth["gps1_failed"] > 0)])
    for run in a.run_dirs or [f"{a.flight_dir}/run"]:
        sent = [r for r in csv.DictReader(open(f"{run}/gps_input.csv")) if r["fix_type"] == "3"]
        t, err = errors(sent, frame, truth, delay_s)
        acc = np.array([float(r["horiz_accuracy_m"]) for r in sent])
        keep = (t >= t_lost) & (t <= truth["t_s"][-1])
        t, err, acc = t[keep], err[keep], acc[keep]
        fixes = [r for r in csv.DictReader(open(f"{run}/fixes.csv")) if r["kind"] == "visual" and r["accepted"] == "True"]
        t_fix, fix_err = errors(fixes, frame, truth, 0.0)
        fix_err = fix_err[t_fix >= t_lost]
        print(f"{run}: GPS_INPUT {len(err)}, error RMS {np.sqrt(np.mean(err**2)):.3f} max {err.max():.3f} m, inside 3x "
              f"accuracy {np.mean(err <= 3 * acc):.3f}; accepted fixes {len(fix_err)}, largest {fix_err.max():.3f} m")
        edges = np.linspace(t[0], t[-1], a.parts + 1)
        parts = [(err[(t >= lo) & (t <= hi)], acc[(t >= lo) & (t <= hi)]) for lo, hi in zip(edges[:-1], edges[1:])]
        print("  by part (RMS / max m / inside 3x): " + "  ".join(
            f"{np.sqrt(np.mean(e**2)):.2f}/{e.max():.2f}/{np.mean(e <= 3 * s):.2f}" for e, s in parts if len(e)))
        last = t >= t[-1] - a.last_s
        print("  last seconds (s before the end: error / accuracy m): " + "  ".join(
            f"{tk - t[-1]:.1f}: {e:.2f}/{s:.2f}" for tk, e, s in list(zip(t[last], err[last], acc[last]))[::5]))


if __name__ == "__main__":
    main()
