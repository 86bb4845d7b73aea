"""Runs seeded evaluation runs of a scenario, in parallel processes, with a progress bar."""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from auxgps.config import PipelineConfig
from auxgps.evaluation.metrics import summarize
from auxgps.evaluation.scenario import RunRecord, run_once
from auxgps.sim.flight import SimConfig
from auxgps.sim.world import load_world


def run_job(args) -> RunRecord:
    """One seeded run from a job tuple (world path, altitude, fps, seed, pipeline, sim, mapping fps), in a worker."""
    import cv2

    cv2.setNumThreads(1)
    world_path, alt_m, fps, seed, pipeline, sim, mapping_fps = args
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
) -> dict:
    """Fly ``runs`` seeded runs (seeds ``seed`` .. ``seed + runs - 1``) and return the pooled summary.

    ``fps``: the positioning flight's frame rate; ``mapping_fps``: the survey's (default ``fps``)."""
    load_world(world_path)  # fail early, in this process, on a bad world file
    mapping_fps = mapping_fps or fps
    jobs = [(str(world_path), alt_m, fps, seed + k, pipeline, sim, mapping_fps) for k in range(runs)]
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
        "pipeline": asdict(pipeline),
        "sim": asdict(sim),
    }
    return summary
