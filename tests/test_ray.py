"""Sweeps beyond one machine: the eval's independent runs on a Ray cluster give what the local process pool gives
for the same seeds. A local Ray (started by the test, two CPUs) stands for the cluster."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from auxgps.config import load_pipeline_config
from auxgps.evaluation.bench import tiny_sim_config
from auxgps.evaluation.driver import MissionRun, evaluate
from auxgps.resources import world_path
from auxgps.sim.flight import load_sim_config

REPO = Path(__file__).resolve().parent.parent
ray = pytest.importorskip("ray", reason="Ray is the optional extra auxgps[cluster] (make test installs it)")


def without_times(figures):
    """The figures without the wall times of the frames (those differ from one machine or run to the next)."""
    if isinstance(figures, dict):
        return {k: without_times(v) for k, v in figures.items() if not (k.endswith("_ms") or k in ("median", "p99"))}
    if isinstance(figures, list):
        return [without_times(v) for v in figures]
    return figures


def test_runs_on_ray_give_the_local_pools_figures_for_the_same_seeds():
    kw = dict(fps=2.0, runs=2, seed=4, pipeline=load_pipeline_config(None), sim=tiny_sim_config(load_sim_config(None)),
              progress=False)
    world = world_path("cubes4_0.5m_different")
    mission = MissionRun(str(REPO / "config" / "missions" / "cubes_out_and_back.waypoints"), 3.0, 3)
    here = evaluate(world, 15.0, workers=2, **kw)
    here_mission = evaluate(world, 15.0, mission=mission, workers=2, **kw)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        there = evaluate(world, 15.0, ray="auto", **kw)  # joins the Ray this process has started
        there_mission = evaluate(world, 15.0, mission=mission, ray="auto", **kw)
    finally:
        ray.shutdown()
    assert here["fused"]["count"] > 0 and here["runs"][0]["seed"] == 4 and here["runs"][1]["seed"] == 5
    assert json.dumps(without_times(there), sort_keys=True, default=str) == json.dumps(without_times(here), sort_keys=True, default=str)
    assert there_mission["fused"] == here_mission["fused"] and there_mission["fused"]["count"] > 0


def test_a_cluster_that_is_not_there_is_one_line():
    done = subprocess.run([sys.executable, "-m", "auxgps.cli", "eval", "--world", "cubes4_0.5m_different", "--altitude", "15",
                           "--ray", "127.0.0.1:1", "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "--ray 127.0.0.1:1" in done.stderr and "Traceback" not in done.stderr, done.stderr[-1500:]
