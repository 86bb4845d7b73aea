#!/usr/bin/env python3
"""Per-seed fused maxima of one world over many seeds: how wide the tail a 3-seed maximum samples is.

    .venv/bin/python tools/seed_study.py --world cubes3_0.5m_different --seeds 1-20 [--fps 2] [--survey-imu-apart]

Each seed is `auxgps eval --world W --altitude 15 --runs 1 --seed S`. Since the survey runs through the estimator
it draws IMU noise from the seed's IMU generator before the positioning flight does, so a seed's positioning
flight has other IMU noise than before the estimator. ``--survey-imu-apart`` gives the survey a generator of its
own, so that the positioning flight draws the IMU noise it drew at c1fbf07: a diagnosis of whether a move in the
maxima is the code or the draw, not a configuration for the tables.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from auxgps.config import load_pipeline_config  # noqa: E402
from auxgps.evaluation import scenario  # noqa: E402
from auxgps.resources import world_path  # noqa: E402
from auxgps.sim.flight import load_sim_config  # noqa: E402
from auxgps.sim.world import load_world  # noqa: E402


def _survey_with_own_imu(map_flight):
    def flown(su, *args, **kwargs):
        keep, su.rng_imu = su.rng_imu, np.random.default_rng(12345)
        try:
            return map_flight(su, *args, **kwargs)
        finally:
            su.rng_imu = keep
    return flown


def one(job: tuple) -> dict:
    world, seed, fps, mapping_fps, apart = job
    if apart:
        scenario._map_flight = _survey_with_own_imu(scenario._map_flight)
    r = scenario.run_once(load_world(world_path(world)), 15.0, fps, seed, load_pipeline_config(None), load_sim_config(None),
                          mapping_fps=mapping_fps)
    e = np.linalg.norm(r.fused_err_ne_m, axis=1)
    return {"seed": seed, "max_m": round(float(e.max()), 3), "rms_m": round(float(np.sqrt(np.mean(e**2))), 4)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", required=True)
    ap.add_argument("--seeds", default="1-20", help="first-last (default 1-20)")
    ap.add_argument("--fps", type=float, default=2.0)
    ap.add_argument("--mapping-fps", type=float)
    ap.add_argument("--survey-imu-apart", action="store_true")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    first, last = (int(x) for x in args.seeds.split("-"))
    jobs = [(args.world, s, args.fps, args.mapping_fps, args.survey_imu_apart) for s in range(first, last + 1)]
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(one, jobs))
    maxima = np.array([r["max_m"] for r in rows])
    print(json.dumps({"world": args.world, "fps": args.fps, "survey_imu_apart": args.survey_imu_apart, "runs": rows,
                      "max_mean_m": round(float(maxima.mean()), 3), "max_range_m": [float(maxima.min()), float(maxima.max())],
                      "runs_over_0_30m": int(np.sum(maxima > 0.30))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
