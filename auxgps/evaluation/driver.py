"""Runs seeded evaluation runs of a scenario, in parallel processes or on a Ray cluster, with a progress bar.

Each run is independent and seeded (:func:`run_job`), so where it runs changes nothing in its result: the local
process pool and Ray give the same records for the same seeds. On Ray (``ray=ADDRESS``, the optional extra
``auxgps[cluster]``) the runs go to the cluster's workers: auxgps must be installed there, and the world, mission
and config paths must be readable from them (a shared folder), as they are read where each run flies.
"""

from __future__ import annotations

import multiprocessing
import os
import socket
import threading
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from tqdm import tqdm

from auxgps.config import PipelineConfig
from auxgps.errors import ConfigError
from auxgps.evaluation.metrics import summarize
from auxgps.evaluation.scenario import RunRecord, run_mission, run_once
from auxgps.io.map_file import load_maps
from auxgps.io.mission import load_mission
from auxgps.sim.flight import SimConfig, gps_lost_waypoint, mission_waypoints_ned
from auxgps.sim.world import load_world


@dataclass(frozen=True)
class MissionRun:
    """A mission flown instead of the survey and positioning flight: its file, speed, the item GPS1 is lost at, and
    the maps the estimator starts from (prior maps: an orthophoto's, ``auxgps map build --orthophoto``)."""

    path: str
    speed_m_s: float
    gps_lost_at_seq: int
    maps: tuple[str, ...] = ()


def run_job(args) -> RunRecord:
    """One seeded run from a job tuple (world path, altitude, fps, seed, pipeline, sim, mapping fps, mission or
    None), in a worker."""
    import cv2

    cv2.setNumThreads(1)
    world_path, alt_m, fps, seed, pipeline, sim, mapping_fps, mission = args
    if mission is not None:
        return run_mission(load_world(world_path), load_mission(mission.path), alt_m, mission.speed_m_s, mission.gps_lost_at_seq,
                           fps, seed, pipeline, sim, maps=mission.maps)
    return run_once(load_world(world_path), alt_m, fps, seed, pipeline, sim, mapping_fps=mapping_fps)


#: Held while joining Ray: several evaluations may start at once, from threads (tools/thesis_tables.py --ray).
_RAY_INIT = threading.Lock()


def _join_ray(ray, address: str) -> None:
    with _RAY_INIT:
        if ray.is_initialized():
            return
        host, _, port = address.removeprefix("ray://").rpartition(":")
        if host and port.isdigit():
            # Ray retries an address nobody answers at for minutes: say so at once instead.
            try:
                socket.create_connection((host, int(port)), timeout=5.0).close()
            except OSError as err:
                raise ConfigError(f"--ray {address}: nothing answers there ({err.strerror or err})") from None
        try:
            ray.init(address=None if address == "local" else address, include_dashboard=False, log_to_driver=False,
                     configure_logging=False)
        except (ConnectionError, RuntimeError, ValueError) as err:
            raise ConfigError(f"--ray {address}: cannot join the cluster: {err}".replace("\n", " ")) from None


def _run_on_ray(jobs: list, address: str, desc: str, progress: bool) -> list[RunRecord]:
    """The jobs as Ray tasks (one CPU each), their records in job order."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--ray needs Ray: pip install 'auxgps[cluster]'") from None
    _join_ray(ray, address)
    task = ray.remote(num_cpus=1)(run_job)
    pending = {task.remote(j): k for k, j in enumerate(jobs)}
    records: list[RunRecord | None] = [None] * len(jobs)
    with tqdm(total=len(jobs), desc=desc, unit="run", disable=not progress) as bar:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                records[pending.pop(ref)] = ray.get(ref)
                bar.update()
    return records


def evaluate(
    world_path: Path | str,
    alt_m: float | None,
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
    ray: str | None = None,
) -> dict:
    """Fly ``runs`` seeded runs (seeds ``seed`` .. ``seed + runs - 1``) and return the pooled summary.

    ``fps``: the positioning flight's frame rate; ``mapping_fps``: the survey's (default ``fps``); ``mission``: fly
    it instead (one flight, mapping until GPS1 is lost, at ``fps`` throughout; ``alt_m`` None: at the mission's own
    heights); ``ray``: a Ray cluster's address
    ("auto" for the one this machine belongs to, "local" to start one here) to run on instead of local processes."""
    world = load_world(world_path)  # fail early, in this process, on a bad world or mission file
    if mission is not None:
        loaded = load_mission(mission.path)
        gps_lost_waypoint(loaded, mission_waypoints_ned(loaded, world.frame, alt_m)[1], mission.gps_lost_at_seq)
        if mission.maps:
            load_maps(list(mission.maps), world.frame)
    mapping_fps = mapping_fps or fps
    jobs = [(str(world_path), alt_m, fps, seed + k, pipeline, sim, mapping_fps, mission) for k in range(runs)]
    workers = max(1, min(workers or os.cpu_count() or 1, runs))
    desc = f"{Path(world_path).stem} @ {alt_m:g} m" if alt_m is not None else Path(world_path).stem
    if ray is not None:
        records = _run_on_ray(jobs, ray, desc, progress)
    elif workers == 1:
        records = [run_job(j) for j in tqdm(jobs, desc=desc, unit="run", disable=not progress)]
    else:
        # forkserver, not fork: a process that has threads (Ray's, a progress bar's) must not be forked mid-way
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("forkserver")) as pool:
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
