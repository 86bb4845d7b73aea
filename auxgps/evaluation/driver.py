"""Runs seeded evaluation runs of a scenario, in parallel processes, with a progress bar."""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from tqdm import tqdm

from auxgps.config import PipelineConfig
from auxgps.errors import ConfigError
from auxgps.evaluation.metrics import summarize
from auxgps.evaluation.scenario import RunRecord, run_mission, run_once
from auxgps.io.mission import load_mission
from auxgps.sim.flight import SimConfig, mission_waypoints_ned
from auxgps.sim.world import load_world


@dataclass(frozen=True)
class MissionRun:
    """A mission flown instead of the survey and positioning flight: its file, speed, and the item GPS1 is lost at."""

    path: str
    speed_m_s: float
    gps_lost_at_seq: int


def run_job(args) -> RunRecord:
    """One seeded run from a job tuple (world path, altitude, fps, seed, pipeline, sim, mapping fps, mission or
    None), in a worker."""
    import cv2

    cv2.setNumThreads(1)
    world_path, alt_m, fps, seed, pipeline, sim, mapping_fps, mission = args
    if mission is not None:
        return run_mission(load_world(world_path), load_mission(mission.path), alt_m, mission.speed_m_s, mission.gps_lost_at_seq,
                           fps, seed, pipeline, sim)
    return run_once(load_world(world_path), alt_m, fps, seed, pipeline, sim, mapping_fps=mapping_fps)


def evaluate(
    world_path: Path | str,
    alt_m: float,
    *,
    fps: float,
    runs: int,
    seed: int,
    pipeline: PipelineConfig,
    sim: SimConfig,
    workers: int | None = None,
    progress: bool = True,
    mapping_fps: float | None = None,
    mission: MissionRun | None = None,
) -> dict:
    """Fly ``runs`` seeded runs (seeds ``seed`` .. ``seed + runs - 1``) and return the pooled summary.

    ``fps``: the positioning flight's frame rate; ``mapping_fps``: the survey's (default ``fps``); ``mission``: fly
    it instead (one flight, mapping until GPS1 is lost, at ``fps`` throughout)."""
    world = load_world(world_path)  # fail early, in this process, on a bad world or mission file
    if mission is not None:
        loaded = load_mission(mission.path)
        path_ned, owner = mission_waypoints_ned(loaded, world.frame, alt_m)
        if mission.gps_lost_at_seq not in owner:
            item = loaded.item(mission.gps_lost_at_seq)
            raise ConfigError(f"{mission.path}: item {item.seq} ({item.name}) is not a place the vehicle reaches")
    mapping_fps = mapping_fps or fps
    jobs = [(str(world_path), alt_m, fps, seed + k, pipeline, sim, mapping_fps, mission) for k in range(runs)]
    workers = max(1, min(workers or os.cpu_count() or 1, runs))
    desc = f"{Path(world_path).stem} @ {alt_m:g} m"
    if workers == 1:
        records = [run_job(j) for j in tqdm(jobs, desc=desc, unit="run", disable=not progress)]
    else:
        with ProcessPoolExecutor(workers) as pool:
            records = list(tqdm(pool.map(run_job, jobs), total=runs, desc=desc, unit="run", disable=not progress))
    summary = summarize(records)
    summary["scenario"] = {
        "world": str(world_path),
        "altitude_m": alt_m,
        "fps": fps,
        "mapping_fps": mapping_fps,
        "runs": runs,
        "seeds": [j[3] for j in jobs],
        "mission": asdict(mission) if mission is not None else None,
        "pipeline": asdict(pipeline),
        "sim": asdict(sim),
    }
    return summary
