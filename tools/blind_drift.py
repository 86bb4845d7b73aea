#!/usr/bin/env python3
"""Where the drift of a stretch without visual fixes comes from: a replayed emulator flight, its filter's
horizontal acceleration error over the stretch split into the attitude it turned the IMU with, its accelerometer
bias estimate, and the rest (the accelerometer's noise); and its velocity error when the stretch began.

    .venv/bin/python tools/blind_drift.py REC OUT FROM_S TO_S [--seed N]

REC: a recording of `auxgps run --record REC` beside the emulator (which sends its truth); OUT: the replay's
output directory; FROM_S, TO_S: the stretch, s relative to the recording's last truth sample (negative; stop
before the touchdown, whose bump is not drift). The true bias is the emulator's for ``--seed`` (its default, 1)
with the default telemetry noise.
"""
import argparse

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from auxgps import replay
from auxgps.core import fusion
from auxgps.sim.emulator import emulated_imu_bias
from auxgps.sim.flight import TelemetryNoiseConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rec"), ap.add_argument("out")
    ap.add_argument("from_s", type=float), ap.add_argument("to_s", type=float)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    steps = []  # (t_s, f_body, R_ned_body, bias estimate, velocity estimate) as each IMU sample is integrated
    propagate = fusion.NavFilter.propagate

    def logged(self, sample):
        x = self._ekf.x[:, 0]
        steps.append((sample.t_s, np.asarray(sample.f_body_m_s2, float), np.asarray(sample.R_ned_body, float),
                      x[6:9].copy(), x[3:6].copy()))
        return propagate(self, sample)

    fusion.NavFilter.propagate = logged
    result = replay.replay(args.rec, args.out)
    truth = [x for x in result.truth if x.alt_amsl_m is not None]
    t_truth = np.array([x.t_s for x in truth])
    p_truth = result.frame.to_ned(lat_deg=np.array([x.lat_deg for x in truth]),
                                  lon_deg=np.array([x.lon_deg for x in truth]),
                                  alt_amsl_m=np.array([x.alt_amsl_m for x in truth]))
    end = t_truth[-1]
    a, b = end + args.from_s, end + args.to_s
    window = [s for s in steps if a <= s[0] <= b]
    t = np.array([s[0] for s in window])
    f_body = np.array([s[1] for s in window])
    R_used = np.array([s[2] for s in window])
    bias_est = np.array([s[3] for s in window])
    R_true = Slerp(t_truth, Rotation.from_euler("ZYX", np.array([x.euler_rad for x in truth])[:, ::-1]))(t).as_matrix()
    bias_true = emulated_imu_bias(TelemetryNoiseConfig(), args.seed)

    def v_truth(at_s: float) -> np.ndarray:  # a line through 0.2 s of truth either side
        k = np.searchsorted(t_truth, at_s)
        w = slice(max(k - 10, 0), k + 10)
        return np.array([np.polyfit(t_truth[w], p_truth[w, i], 1)[0] for i in range(3)])

    a_truth = (v_truth(t[-1]) - v_truth(t[0])) / (t[-1] - t[0])
    a_filter = np.einsum("kij,kj->ki", R_used, f_body - bias_est).mean(0) + fusion.GRAVITY_NED_M_S2
    from_attitude = (np.einsum("kij,kj->ki", R_used, f_body) - np.einsum("kij,kj->ki", R_true, f_body)).mean(0)
    from_bias = np.einsum("kij,kj->ki", R_used, bias_true - bias_est).mean(0)
    rest = a_filter - a_truth - from_attitude - from_bias
    print(f"{a - end:.1f} to {b - end:.1f} s, {len(t)} IMU samples; north, east, m/s^2:")
    print(f"  acceleration error {(a_filter - a_truth)[:2].round(4)}")
    print(f"    from the attitude {from_attitude[:2].round(4)}")
    print(f"    from the bias     {from_bias[:2].round(4)} (body: true {bias_true.round(4)}, "
          f"estimated {bias_est.mean(0).round(4)})")
    print(f"    the rest (noise)  {rest[:2].round(4)}")
    print(f"  velocity error at the start {(window[0][4] - v_truth(t[0]))[:2].round(3)} m/s, at the end "
          f"{(window[-1][4] - v_truth(t[-1]))[:2].round(3)} m/s")


if __name__ == "__main__":
    main()
