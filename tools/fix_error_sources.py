#!/usr/bin/env python3
"""Which error makes a mission's fixes wrong: the map's or the attitude's? Each fix made while GPS1 is lost is
solved again, on the same inliers, with the true landmark positions, with the true attitude, with both, with only
the true heights or only the true north/east of the landmarks, and with the tilt held to the telemetry's.

    .venv/bin/python tools/fix_error_sources.py --world config/worlds/seneca.yaml \\
        --mission config/missions/seneca_out_and_back.waypoints --alt-m 40 --gps-lost-at-waypoint 3 --seed 1

The truth (the renderer's points behind the features that fed each landmark, and its camera poses) is read here
only, after the flight: the estimator never sees it.
"""
import argparse
from dataclasses import replace

import numpy as np

from auxgps.config import load_pipeline_config
from auxgps.core import localise
from auxgps.evaluation import scenario as S
from landmark_bias import mission_arguments, run_mission  # tools/, beside this script

VARIANTS = ("as made", "true map", "true attitude", "both", "true heights only", "true north/east only", "tilt held")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mission_arguments(ap)
    ap.add_argument("--bad-m", type=float, default=0.5, help="fixes off by more than this are shown apart (m)")
    a = ap.parse_args()
    cfg = load_pipeline_config(a.config)  # the built-in defaults without --config

    poses, fixes, truth = {}, [], {}
    on_frame, choose, locate = S._MapTruth.on_frame, localise.Localiser._choose, localise.Localiser.locate

    def keep_pose(self, seen):
        poses[round(seen.result.t_s, 6)] = seen.rendered.pose
        truth["map"] = self
        return on_frame(self, seen)

    def keep_choice(self, corr, view, *args, **kw):
        verdict = choose(self, corr, view, *args, **kw)
        self._kept_choice = (corr, view, verdict)
        return verdict

    def keep_fix(self, features, t_s, R_ned_body, alt_m, prior, candidate_ids=None, **kw):
        self._kept_choice = None
        result = locate(self, features, t_s, R_ned_body, alt_m, prior, candidate_ids, **kw)
        if isinstance(result, localise.Fix) and self._kept_choice is not None:
            fixes.append((t_s, result, alt_m, self, *self._kept_choice))
        return result

    S._MapTruth.on_frame, localise.Localiser._choose, localise.Localiser.locate = keep_pose, keep_choice, keep_fix
    rec, _, _ = run_mission(a, cfg)
    truths_of = truth["map"].truths_of

    rows, shared = [], []
    for t_s, fix, alt_m, loc, corr, view, verdict in fixes:
        pose = poses.get(round(t_s, 6))
        if t_s < rec.denied_from_s or pose is None:
            continue
        inl = verdict.inl
        known = np.array([int(j) in truths_of for j in corr.lm_id])
        L_true = corr.L.copy()
        L_true[known] = [np.median(truths_of[int(j)], axis=0) for j in corr.lm_id[known]]
        d_true = corr.d @ view.R_ned_cam @ pose.R_ned_cam.T  # the same pixels through the true attitude
        L_h, L_ne = corr.L.copy(), corr.L.copy()
        L_h[:, 2], L_ne[:, :2] = L_true[:, 2], L_true[:, :2]
        held = view.prior_info.copy()
        held[3, 3] = held[4, 4] = 1e12

        def err(L, d, info=view.prior_info):
            p = loc._refine(fix.p_ned_m, replace(corr, L=L, d=d), inl, alt_m, 1.0 / view.features.scale, info).p
            return float(np.linalg.norm(p[:2] - pose.p_cam_in_ned_m[:2]))

        rows.append([float(np.linalg.norm(fix.p_ned_m[:2] - pose.p_cam_in_ned_m[:2])), err(L_true, corr.d), err(corr.L, d_true),
                     err(L_true, d_true), err(L_h, corr.d), err(L_ne, corr.d), err(corr.L, corr.d, held)])
        lm_err = (corr.L - L_true)[inl & known]
        seen = loc.map.n_seen[corr.lm_id[inl]]
        first = loc.map.t_first_s[corr.lm_id[inl & known]] - rec.denied_from_s
        shared.append([*lm_err.mean(axis=0), np.median(seen), np.median(first), int(inl.sum())])
    rows, shared = np.array(rows), np.array(shared)
    bad = rows[:, 0] > a.bad_m
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    print(f"seed {a.seed}: {len(rows)} fixes while GPS1 was lost, {bad.sum()} of them over {a.bad_m:g} m")
    print(f"{'solved again with':24s} {'all: RMS m':>11s} {'those over: RMS m':>18s}")
    for k, name in enumerate(VARIANTS):
        print(f"{name:24s} {rms(rows[:, k]):11.3f} {rms(rows[bad, k]) if bad.any() else float('nan'):18.3f}")
    if bad.any():
        s = shared[bad]
        print(f"the inliers of those over {a.bad_m:g} m: {np.median(s[:, 5]):.0f} a fix (median), seen {np.median(s[:, 3]):.0f} times, "
              f"first geotagged {np.median(s[:, 4]):+.1f} s from the loss; their mean error N {s[:, 0].mean():+.3f} "
              f"E {s[:, 1].mean():+.3f} D {s[:, 2].mean():+.3f} m")


if __name__ == "__main__":
    main()
