#!/usr/bin/env python3
"""The largest accepted fixes of a mission, and what their frames saw: for each, its true error, the one sigma it
offered and the filter's, the gate's squared distance, its inliers, where they lie from nadir, and how far their
landmarks are off the truth (median north, east, down); with --landmarks N, each inlier's landmark of the N
largest (its position, error, views, and when it was first seen).

    .venv/bin/python tools/worst_fixes.py --world config/worlds/seneca.yaml \\
        --mission config/missions/seneca_out_and_back.waypoints --alt-m 40 --gps-lost-at-waypoint 3 --seed 3 [--top 5]

Inliers all at one edge of the image, on landmarks that share an error, make a fix far off that claims
little (docs/missions.md). The truth (the renderer's points behind the inliers' pixels, the camera's track) is
read here only, by the evaluator's hook on each frame: the estimator never sees it.
"""
import argparse

import numpy as np

from auxgps.config import load_pipeline_config
from auxgps.evaluation import scenario as S
from landmark_bias import mission_arguments, run_mission  # tools/, beside this script


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mission_arguments(ap)
    ap.add_argument("--top", type=int, default=5, help="how many fixes to show")
    ap.add_argument("--landmarks", type=int, default=0, metavar="N",
                    help="for the N largest, each inlier's landmark too: its error, views, when first seen, where")
    a = ap.parse_args()
    cfg = load_pipeline_config(a.config)  # the built-in defaults without --config
    rows, estimators = [], []
    on_frame, record = S._Scored.on_frame, S._Scored.record

    def keep_estimator(self, seed, est, *rest):
        estimators.append(est)
        return record(self, seed, est, *rest)

    def look(self, seen):
        """The evaluator's hook on each frame: what an accepted fix made while denied saw, against the truth."""
        on_frame(self, seen)
        res, i = seen.result, seen.i
        t_s = float(self.traj.t_s[i])
        if res.kind != "visual" or res.mapping or t_s < self.denied_from or not res.decision.accepted:
            return
        fix, cam_ne = res.located, self.traj.p_ned_m[i, :2]
        row = {"t_s": t_s - self.denied_from, "denied_from_s": self.denied_from, "err_m": float(np.linalg.norm(fix.p_ned_m[:2] - cam_ne)),
               "offered_m": res.decision.fix_sigma_m, "filter_m": res.decision.filter_sigma_m, "m2": res.decision.mahalanobis2,
               "inliers": 0, "ids": None, "truth": None}
        if fix.inliers is not None and len(fix.inliers.lm_id):
            row.update(inliers=len(fix.inliers.lm_id), ids=fix.inliers.lm_id.copy(), cam_ne=cam_ne.copy(),
                       truth=seen.rendered.true_points_at(fix.inliers.uv_px))
        rows.append(row)

    S._Scored.on_frame, S._Scored.record = look, keep_estimator
    run_mission(a, cfg)
    landmarks = estimators[0].landmarks  # the map as the flight ended: the inliers' landmarks barely move once denied
    rows.sort(key=lambda r: -r["err_m"])
    print(f"{len(rows)} accepted fixes while denied; the {min(a.top, len(rows))} largest (t: s after the loss; sigmas: one, "
          "per axis, m; centroid: the inliers' landmarks from nadir, north/east m; landmark error: median, north/east/down m):")
    for r in rows[: a.top]:
        line = (f"  t {r['t_s']:6.1f}  error {r['err_m']:.3f}  offered {r['offered_m']:.3f}  filter {r['filter_m']:.3f}  "
                f"m2 {r['m2']:.2f}  inliers {r['inliers']}")
        if r["truth"] is not None:
            p = landmarks.p_ned_m[r["ids"]].astype(float)
            off = p - r["truth"]
            ok = np.all(np.isfinite(off), axis=1)
            centroid = p[:, :2].mean(axis=0) - r["cam_ne"]
            med = np.median(off[ok], axis=0) if ok.any() else np.full(3, np.nan)
            line += f"  centroid {centroid[0]:+.1f} {centroid[1]:+.1f}  landmark error {med[0]:+.3f} {med[1]:+.3f} {med[2]:+.3f}"
        print(line)
        if r["truth"] is not None and rows.index(r) < a.landmarks:
            for lm, p_lm, o in zip(r["ids"], landmarks.p_ned_m[r["ids"]].astype(float), p - r["truth"]):
                print(f"      landmark {lm}: at {p_lm[0]:+.1f} {p_lm[1]:+.1f} {p_lm[2]:+.2f}, error {o[0]:+.3f} {o[1]:+.3f} {o[2]:+.3f}, "
                      f"seen {int(landmarks.n_seen[lm])} of {int(landmarks.n_visible[lm])} frames in view, "
                      f"first seen {float(landmarks.t_first_s[lm]) - r['denied_from_s']:+.1f} s from the loss")


if __name__ == "__main__":
    main()
