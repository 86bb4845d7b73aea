#!/usr/bin/env python3
"""Where a mission's map is off, and which way: the mean error (estimate less truth, north, east, down) of the
landmarks positioning can use, near each of the mission's waypoints, after an `auxgps eval --mission` run.

    .venv/bin/python tools/landmark_bias.py --world config/worlds/seneca.yaml \\
        --mission config/missions/seneca_out_and_back.waypoints --alt-m 40 --gps-lost-at-waypoint 3 --seed 1 \\
        [--config PIPELINE.yaml] [--sim-config SIM.yaml] [--radius-m 25]

A shared offset over a region (not the spread of single landmarks) is what moves every fix made there alike.
Then the same landmarks by how many times they were seen: their mean height error against the height sigma their
own covariance claims (views counted are not views apart: at 10 frames a second a landmark seen 11 times was
seen over a second of flight).
"""
import argparse

import numpy as np

from auxgps.config import PipelineConfig, load_pipeline_config
from auxgps.evaluation import scenario as S
from auxgps.io.mission import load_mission
from auxgps.sim.flight import load_sim_config, mission_waypoints_ned
from auxgps.sim.world import load_world


def mission_arguments(ap: argparse.ArgumentParser) -> None:
    """The arguments of one seeded mission run (shared with tools/fix_error_sources.py)."""
    ap.add_argument("--world", required=True)
    ap.add_argument("--mission", required=True)
    ap.add_argument("--alt-m", type=float, default=None)
    ap.add_argument("--speed-m-s", type=float, default=8.0)
    ap.add_argument("--gps-lost-at-waypoint", type=int, required=True)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--config", default=None, help="pipeline config YAML (default: built-in defaults)")
    ap.add_argument("--sim-config", default=None, help="simulation config YAML (default: built-in defaults)")


def run_mission(a: argparse.Namespace, cfg: PipelineConfig):
    """Fly the mission ``a`` names with ``cfg``: its scored record, the world and the mission."""
    world, mission = load_world(a.world), load_mission(a.mission)
    rec = S.run_mission(world, mission, a.alt_m, a.speed_m_s, a.gps_lost_at_waypoint, a.fps, a.seed, cfg, load_sim_config(a.sim_config))
    return rec, world, mission


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mission_arguments(ap)
    ap.add_argument("--radius-m", type=float, default=25.0)
    a = ap.parse_args()
    cfg = load_pipeline_config(a.config)  # the built-in defaults without --config
    kept = {}
    errors = S._MapTruth.errors

    def keep(self, est, pipeline):
        kept["est"], kept["truth"] = est, self
        return errors(self, est, pipeline)

    S._MapTruth.errors = keep
    _, world, mission = run_mission(a, cfg)
    est, truth = kept["est"], kept["truth"]
    lm, m = est.landmarks, cfg.mapping
    seen = np.flatnonzero((lm.n_seen[: len(lm)] >= m.min_seen) & (lm.source[: len(lm)] == 0))
    used = seen[lm.usable(seen, m.min_seen, m.max_mean_chi2, m.min_found_ratio)]
    p = lm.p_ned_m[used].astype(float)
    err = p - np.array([np.median(truth.truths_of[int(j)], axis=0) for j in used])
    path_ned, _ = mission_waypoints_ned(mission, world.frame, a.alt_m)
    print(f"{len(used)} usable landmarks; mean error within {a.radius_m:g} m of each waypoint (m):")
    for k, w in enumerate(path_ned):
        near = np.linalg.norm(p[:, :2] - w[:2], axis=1) < a.radius_m
        if near.any():
            e = err[near]
            print(f"  path point {k}: at N {w[0]:7.1f} E {w[1]:7.1f}: {near.sum():5d} landmarks, mean N {e[:, 0].mean():+.3f} "
                  f"E {e[:, 1].mean():+.3f} D {e[:, 2].mean():+.3f}, median horizontal {np.median(np.linalg.norm(e[:, :2], axis=1)):.3f}")
    n_seen = lm.n_seen[used].astype(int)
    sigma_d = np.sqrt(lm.covariance(used)[:, 2, 2])
    bias = lm.triangulation_bias_m(used)
    print("by times seen (D: down, m; the height sigma is what the landmark's covariance claims, the model D what "
          "LandmarkMap.triangulation_bias_m expects):")
    for lo, hi in [(0, 20), (20, 40), (40, 80), (80, None)]:
        k = (n_seen >= lo) & (n_seen < (hi or np.iinfo(int).max))
        if k.any():
            print(f"  seen {lo:3d} to {hi or 'more':>4}: {k.sum():6d} landmarks, mean D {err[k, 2].mean():+.3f}, "
                  f"median horizontal {np.median(np.linalg.norm(err[k, :2], axis=1)):.3f}, median height sigma {np.median(sigma_d[k]):.3f}, model D {bias[k, 2].mean():+.3f}")


if __name__ == "__main__":
    main()
