#!/usr/bin/env python3
"""A recorded SITL flight replayed with the heading solver on or off: what the tracker did, and the GPS_INPUT and
accepted fixes after GPS1 was lost against SITL's truth (the recording's SIM_STATE).

    [AUXGPS_HEADING='{"decorrelation_s": 1.0}'] .venv/bin/python tools/heading_replay.py REC_DIR OUT_DIR 1|0

Prints the number of tracker measurements, then one JSON line: out_rms/out_max (m, 3D outputs), within3 (their
share inside 3 sigma), avail, fixes, fix_rms, fix_over_0_5. OUT_DIR gets the replay's logs and heading_diag.json
(each tracker measurement: t, value, variance, accepted, estimate, sigma; rad) and fix_errors.csv (each accepted
fix after the loss: t_s, error_m, sigma_m, inliers). AUXGPS_HEADING: heading settings over the recording's own
(JSON), to try another; AUXGPS_PIPELINE: any pipeline settings over the recording's (JSON, merged key by key, e.g.
'{"noise": {"heading_deg": 1.5}}').
"""
import csv
import json
import os
import sys

import numpy as np

from auxgps import replay as rp
from auxgps.core import heading as hd
from auxgps.config import PipelineConfig, parse_as
from auxgps.io.recording import open_recording


def _merged(base: dict, over: dict) -> dict:
    return {**base, **{k: _merged(base.get(k) or {}, v) if isinstance(v, dict) else v for k, v in over.items()}}


def main(rec_dir: str, out_dir: str, solve: bool) -> None:
    obs = []  # every measurement the tracker weighed, with the estimate after it
    orig = hd.HeadingTracker.observe

    def observe(self, t_s, z, var):
        ok = orig(self, t_s, z, var)
        e = self.at(t_s)
        obs.append((t_s, float(z), float(var), bool(ok), float(e.offset_rad), float(e.sigma_rad)))
        return ok

    hd.HeadingTracker.observe = observe
    meta = open_recording(rec_dir).meta
    cfgd = _merged(_merged(meta["pipeline"], json.loads(os.environ.get("AUXGPS_PIPELINE", "{}"))),
                   {"heading": {"solve": solve, **json.loads(os.environ.get("AUXGPS_HEADING", "{}"))}})
    pipe = parse_as(PipelineConfig, cfgd, f"{rec_dir}/recording.json")
    res = rp.replay(rec_dir, out_dir, pipeline=pipe)
    json.dump({"obs": obs}, open(out_dir + "/heading_diag.json", "w"))
    print(len(obs))
    # The GPS_INPUT and accepted fixes after GPS1 was lost, against SIM_STATE's truth.
    ev_t = None
    for r in csv.DictReader(open(out_dir + "/events.csv")):
        if "GPS1 lost" in r["text"]:
            ev_t = float(r["t_s"]); break
    frame = res.frame
    outs = [o for o in res.outputs if o.gps is not None and o.t_described_s >= ev_t]
    tt = np.array([x.t_s for x in res.truth])
    tp = frame.to_ned(lat_deg=np.array([x.lat_deg for x in res.truth]), lon_deg=np.array([x.lon_deg for x in res.truth]),
                      alt_amsl_m=np.full(len(tt), frame.alt_amsl_m))[:, :2]
    t = np.array([o.t_described_s for o in outs]); f3 = np.array([o.gps.fix_type == 3 for o in outs])
    p = frame.to_ned(lat_deg=np.array([o.gps.lat_deg for o in outs]), lon_deg=np.array([o.gps.lon_deg for o in outs]),
                     alt_amsl_m=np.array([o.gps.alt_amsl_m for o in outs]))[:, :2]
    ref = np.column_stack([np.interp(t, tt, tp[:, k]) for k in (0, 1)])
    e = np.linalg.norm(p - ref, axis=1)[f3]; s = np.array([o.gps.horiz_accuracy_m for o in outs])[f3]
    fx = [r for r in csv.DictReader(open(out_dir + "/fixes.csv")) if r["kind"] == "visual" and r["accepted"] == "True" and float(r["t_s"]) >= ev_t]
    fp = frame.to_ned(lat_deg=np.array([float(r["lat_deg"]) for r in fx]), lon_deg=np.array([float(r["lon_deg"]) for r in fx]), alt_amsl_m=np.zeros(len(fx)))[:, :2]
    ft = np.array([float(r["t_s"]) for r in fx])
    fe = np.linalg.norm(fp - np.column_stack([np.interp(ft, tt, tp[:, k]) for k in (0, 1)]), axis=1)
    with open(out_dir + "/fix_errors.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "error_m", "sigma_m", "inliers"])
        w.writerows((r["t_s"], f"{err:.4f}", r["sigma_m"], r["n"]) for r, err in zip(fx, fe))
    print(json.dumps({"out_rms": float(np.sqrt(np.mean(e**2))), "out_max": float(e.max()), "within3": float(np.mean(e <= 3 * s)),
                      "avail": float(f3.mean()), "fixes": len(fe), "fix_rms": float(np.sqrt(np.mean(fe**2))), "fix_over_0_5": int((fe > 0.5).sum())}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3] == "1")
